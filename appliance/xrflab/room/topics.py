"""The room's MQTT topics: the one list of them (payloads.py defines what each carries).

    xrf/bench/<name>/online   retained  payloads.Online     true on connect; false: the last will
    xrf/bench/<name>/status   retained  payloads.Status     the tile: every change (<= 20 Hz), every second
    xrf/bench/<name>/event    QoS 1     payloads.Event      alarms, runs started/ended, self-checks, assignments
    xrf/bench/<name>/reply    QoS 1     payloads.Reply      answers to commands
    xrf/bench/<name>/grades   QoS 1     payloads.Grades     its grading table of one assignment (asked for)
    xrf/cmd/<name>            QoS 1     payloads.Command    the room's commands to one bench
    xrf/cmd/all               QoS 1     payloads.Command    the same, for every bench
    xrf/accounts              retained  payloads.ClassList  the class list (accounts_sync.py)
    xrf/assignment/<id>       retained  payloads.Assignment a published assignment (assignments.py)
    xrf/room/online           retained  payloads.RoomOnline the room listens (true after it subscribed;
                                                            false: its last will): benches hold their
                                                            events until then

Only the room writes under xrf/cmd, xrf/accounts, xrf/assignment and xrf/room, and a bench writes only under
its own xrf/bench/<name>, <name> being its broker login (broker.acl_text): the topic, not anything
in a payload, says which bench spoke. The room listens only to enrolled names.
"""

from __future__ import annotations

import re

ROOT = "xrf"
CMD_ALL = f"{ROOT}/cmd/all"
ACCOUNTS = f"{ROOT}/accounts"
BENCH_ALL = f"{ROOT}/bench/+/+"
ASSIGNMENTS = f"{ROOT}/assignment/+"
ROOM_ONLINE = f"{ROOT}/room/online"

# Where the room's broker listens unless told otherwise (IANA's MQTT ports): written once, here,
# because this module is stdlib only and `xrf room`'s parser (built by every `xrf` call) reads them.
MQTT_PORT = 1883
MQTT_TLS_PORT = 8883

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
