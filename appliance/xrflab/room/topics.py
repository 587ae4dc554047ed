"""The room's MQTT topics and payload rules: the one contract between benches and the room.

    xrf/bench/<name>/online   retained  {"online": bool, "conn": int}  -- the last will says false
    xrf/bench/<name>/status   retained  {"seq", "boot", "t", ...}       -- publisher.py STATUS_FIELDS
    xrf/bench/<name>/event    QoS 1     {"seq", "boot", "t", "kind", ...}  alarms, run started/ended
    xrf/bench/<name>/reply    QoS 1     {"id", "t_recv", "t_done", "ok", ...}  answers to commands
    xrf/cmd/<name>            QoS 1     {"id", "cmd", "t", ...}          -- the room's commands
    xrf/cmd/all               QoS 1     the same, for every bench
    xrf/accounts              retained  {"version", "users": [...]}    -- the class list (accounts_sync.py)
    xrf/assignment/<id>       retained  {"id", "name", "sha256", ...}  -- a published assignment (assignments.py)

Only the room writes under xrf/cmd, xrf/accounts and xrf/assignment, and a bench writes only under its own
xrf/bench/<name> (broker.acl_text). Every bench message carries (boot, seq): `boot` is the
appliance's start time in ns (a restarted bench counts higher), `seq` counts up within it, so the
room keeps the newest whatever order messages arrive in (``newer``).
"""

from __future__ import annotations

import re

ROOT = "xrf"
CMD_ALL = f"{ROOT}/cmd/all"
ACCOUNTS = f"{ROOT}/accounts"
BENCH_ALL = f"{ROOT}/bench/+/+"
ASSIGNMENTS = f"{ROOT}/assignment/+"

# A bench's name is its broker username and part of its topics: no MQTT wildcards or separators.
NAME_RE = re.compile(r"^[a-z0-9][a-z0-9-]{0,31}$")
RESERVED = frozenset({"all", "room"})


def check_bench_name(name: str) -> str:
    name = (name or "").strip().lower()
    if not NAME_RE.match(name) or name in RESERVED:
        raise ValueError(f"bench name {name!r}: 1-32 characters a-z, 0-9 and '-', not 'all' or 'room'")
    return name


def bench(name: str, leaf: str) -> str:
    return f"{ROOT}/bench/{name}/{leaf}"


def cmd(name: str) -> str:
    return f"{ROOT}/cmd/{name}"


def assignment(aid: str) -> str:
    return f"{ROOT}/assignment/{aid}"


def parse_bench_topic(topic: str) -> tuple[str, str] | None:
    """(bench name, leaf) of xrf/bench/<name>/<leaf>, else None."""
    parts = topic.split("/")
    if len(parts) == 4 and parts[0] == ROOT and parts[1] == "bench":
        return parts[2], parts[3]
    return None


def newer(a: tuple[int, int] | None, b: tuple[int, int]) -> bool:
    """Is the (boot, seq) `b` newer than `a`? A bench that comes back with an old retained state
    (or a message delayed behind a newer one) never overwrites what the room already has."""
    return a is None or b > a
