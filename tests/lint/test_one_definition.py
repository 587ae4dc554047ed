"""Every list the code shares has one definition; a second copy anywhere in appliance/, frontend/ or
rt_core/ fails here (issue 27).

The lists and where each is defined:
- states, commands, which commands are safe, board transports: rt_core/include/xrf/channels.h
  (the X-macros XRF_STATES, XRF_CMDS, XRF_TRANSPORTS; C, cffi, the appliance and the browser
  read them from there);
- roles: appliance/xrflab/server/security/roles.py (the browser gets permissions, never compares
  role names);
- WebSocket message kinds, server and client: appliance/xrflab/server/ws/messages.py.

A copy is found by grep, not by parsing: a stretch of a few lines of one file that names more than
half of a list's items as literals ("RUN", 'stop', `ack`, or a JS/Python object key `RUN:`) is a
list written down again. A single use of an item (`sendCommand("stop")`) is not a copy. Places
that must name the items and are checked against the definition some other way are listed in
ALLOWED with the reason; docs/ and tests/ are not scanned.

Each check runs its scanner on a planted file too, so a scanner that stopped finding copies fails.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCANNED = ("appliance", "frontend", "rt_core")
SUFFIXES = {".py", ".js", ".html", ".css", ".c", ".cpp", ".h", ".hpp"}
SKIP_PARTS = {"vendor", "__pycache__", "corpus"}
CHANNELS_H = "rt_core/include/xrf/channels.h"
ROLES_PY = "appliance/xrflab/server/security/roles.py"
MESSAGES_PY = "appliance/xrflab/server/ws/messages.py"
WINDOW = 12  # lines: a list literal, an enum, a dict of them fits


@dataclass
class ListSpec:
    name: str
    items: tuple[str, ...]
    definition: str
    # More than this many distinct items within WINDOW lines is a copy (default: half the list).
    threshold: int | None = None
    window: int = WINDOW
    allowed: dict[str, str] = field(default_factory=dict)

    def limit(self) -> int:
        return self.threshold if self.threshold is not None else len(self.items) // 2


def _item_re(item: str) -> re.Pattern[str]:
    """`item` as a string literal ("x", 'x'), an object key starting a line or after { or , (JS:
    `{RUN: ...}`), or a CSS attribute value (`[data-cmd=stop]`). Not in backticks: those are
    docstrings' and comments' prose (``stop``) far more often than code."""
    e = re.escape(item)
    return re.compile(rf"""(["']){e}\1|(?:^\s*|[{{,]\s*){e}\s*:(?!:)|=["']?{e}["']?\]""")


def copies(spec: ListSpec, files: Iterable[Path], root: Path = REPO) -> list[str]:
    """`path:line: items` for every stretch of a file outside the definition that names more than
    spec.limit() distinct items of the list."""
    patterns = {item: _item_re(item) for item in spec.items}
    found = []
    for path in files:
        rel = path.relative_to(root).as_posix()
        if rel == spec.definition or rel in spec.allowed:
            continue
        lines = path.read_text(errors="replace").splitlines()
        per_line = [{item for item, rx in patterns.items() if rx.search(line)} for line in lines]
        for i in range(len(lines)):
            if not per_line[i]:
                continue
            seen = set().union(*per_line[i : i + spec.window])
            if len(seen) > spec.limit():
                found.append(f"{rel}:{i + 1}: {', '.join(sorted(seen))}")
                break  # one report per file is enough
    return found


def scanned_files(root: Path = REPO) -> list[Path]:
    out = []
    for top in SCANNED:
        for path in sorted((root / top).rglob("*")):
            if path.suffix in SUFFIXES and path.is_file() and not SKIP_PARTS & set(path.parts):
                out.append(path)
    return out


# ---- the definitions, read from their files (so this test holds no copy of its own) ------------------


def _xmacro(name: str) -> list[list[str]]:
    """The items of channels.h's `#define <name>(X)` list, each as its arguments."""
    text = (REPO / CHANNELS_H).read_text()
    m = re.search(rf"^#define {name}\(X\)((?:[^\n]*\\\n)*[^\n]*)$", text, re.MULTILINE)
    assert m, f"{CHANNELS_H} has no {name}(X) list"
    return [[a.strip().strip('"') for a in args.split(",")] for args in re.findall(r"\bX\(([^)]*)\)", m.group(1))]


def _roles() -> tuple[str, ...]:
    m = re.search(r"^Role = Literal\[([^\]]*)\]", (REPO / ROLES_PY).read_text(), re.MULTILINE)
    assert m, f"{ROLES_PY} has no Role = Literal[...]"
    return tuple(re.findall(r'"([^"]+)"', m.group(1)))


def _kinds(union: str) -> tuple[str, ...]:
    """The kinds of a union of message models in messages.py (`type: Literal["kind"]` of each)."""
    text = (REPO / MESSAGES_PY).read_text()
    m = re.search(rf"^{union} = \(?([^=]*?)\)?\n(?:#|[A-Z])", text, re.MULTILINE)
    assert m, f"{MESSAGES_PY} has no {union} union"
    kinds = []
    for model in re.findall(r"\w+", m.group(1)):
        k = re.search(rf'^class {model}\(.*?\n    type: Literal\["(\w+)"\]', text, re.MULTILINE | re.DOTALL)
        assert k, f"{model} has no type Literal"
        kinds.append(k.group(1))
    return tuple(kinds)


def specs() -> list[ListSpec]:
    states = tuple(args[0] for args in _xmacro("XRF_STATES"))
    commands = _xmacro("XRF_CMDS")
    transports = tuple(args[1] for args in _xmacro("XRF_TRANSPORTS"))
    return [
        ListSpec(
            "states",
            states,
            CHANNELS_H,
            allowed={
                "frontend/app.js": "NODES: where the drawing puts each state (layout, not a list: a state "
                "missing there is still drawn, below the others)",
            },
        ),
        ListSpec("commands", tuple(args[1] for args in commands), CHANNELS_H),
        # Two safe commands: both on one line is a copy of the safe list ({"stop", "pause"}).
        ListSpec(
            "safe commands", tuple(args[1] for args in commands if args[3] == "1"), CHANNELS_H, threshold=1, window=1
        ),
        ListSpec(
            "transports",
            transports,
            CHANNELS_H,
            threshold=len(transports) - 1,
            allowed={
                "rt_core/src/runtime.cpp": "opens each transport (its own code per transport); "
                "its error text is made from the list",
                "rt_core/tools/selfcheck/selfcheck.c": "the C self-check opens each transport the same way",
                "rt_core/tools/selfcheck/selfcheck.h": "documents the self-check's transport argument",
            },
        ),
        ListSpec("roles", _roles(), ROLES_PY, threshold=1),
        ListSpec(
            "server message kinds",
            _kinds("ServerMessage"),
            MESSAGES_PY,
            allowed={
                "frontend/app.js": "HANDLERS: what the page does with each kind; tests/ui/"
                "test_state_machine_ui.py checks it against the published schema",
            },
        ),
        ListSpec("client message kinds", _kinds("ClientMessage"), MESSAGES_PY),
    ]


SPECS = {s.name: s for s in specs()}


@pytest.mark.parametrize("name", list(SPECS))
def test_no_second_copy(name: str) -> None:
    spec = SPECS[name]
    assert len(spec.items) >= 2, f"{name}: the definition lists {spec.items}"
    found = copies(spec, scanned_files())
    assert not found, (
        f"{name} are defined once, in {spec.definition}; read them from there instead of copying:\n" + "\n".join(found)
    )


@pytest.mark.parametrize("name", list(SPECS))
def test_a_planted_copy_is_found(name: str, tmp_path: Path) -> None:
    """The scanner finds a copy: the list written again as a JS array, a Python tuple, a C table."""
    spec = SPECS[name]
    items = spec.items[: spec.limit() + 1]
    nl = "\n" if spec.window > 1 else " "  # a list over several lines, where the spec looks that far
    planted = {
        "frontend/pages/planted.js": "const LIST = [" + ", ".join(f'"{i}"' for i in items) + "];\n",
        "appliance/xrflab/planted.py": f"LIST = ({nl}" + "".join(f"    '{i}',{nl}" for i in items) + ")\n",
        "rt_core/src/planted.c": f'static const char *const names[] = {{"?",{nl}'
        + "".join(f'    "{i}",{nl}' for i in items)
        + "};\n",
    }
    for rel, text in planted.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("// a page\n" + text)
    found = copies(spec, scanned_files(tmp_path), root=tmp_path)
    assert sorted(f.split(":")[0] for f in found) == sorted(planted)
    # One item alone, as any code uses it, is no copy.
    (tmp_path / "frontend/pages/planted.js").write_text(f'send("{spec.items[0]}");\n')
    assert "frontend/pages/planted.js" not in {
        f.split(":")[0] for f in copies(spec, scanned_files(tmp_path), root=tmp_path)
    }


# ---- permissions from role names, and prose read as data -----------------------------------------

ROLE_COMPARISON = re.compile(r"""\brole\s*(?:===?|!==?)\s*["']""")
# A message's prose matched in the browser instead of a typed field (issue 27: the page looked
# for "the controller runs WITHOUT" in a confinement alarm; now `started` says it). Covers a
# WebSocket message's `m.message` and an HTTP error's `e.message` alike.
PROSE_MATCH = re.compile(r"""\.message\b[^;\n]*\.(?:startsWith|includes|indexOf|match)\(|String\(\w+\.message\)\.""")


def scan_lines(pattern: re.Pattern[str], files: Iterable[Path], root: Path = REPO) -> list[str]:
    out = []
    for path in files:
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if pattern.search(line):
                out.append(f"{path.relative_to(root).as_posix()}:{n}: {line.strip()}")
    return out


def test_permissions_are_not_derived_from_role_names(tmp_path: Path) -> None:
    """Code asks for a permission (Python: role_has / user.is_educator; pages: xrf.may(perm) over
    /api/me's perms), never `role == "educator"`."""
    found = scan_lines(ROLE_COMPARISON, [p for p in scanned_files() if p.as_posix() != (REPO / ROLES_PY).as_posix()])
    assert not found, "compare permissions, not role names (server/security/roles.py):\n" + "\n".join(found)
    planted = tmp_path / "frontend" / "x.js"
    planted.parent.mkdir()
    planted.write_text('if (xrf.me.role === "educator") show();\n')
    assert scan_lines(ROLE_COMPARISON, scanned_files(tmp_path), root=tmp_path)


def test_the_browser_reads_typed_fields_not_prose(tmp_path: Path) -> None:
    found = scan_lines(PROSE_MATCH, [p for p in scanned_files() if p.suffix == ".js"])
    assert not found, "a WebSocket message's text is for people; add a typed field (messages.py):\n" + "\n".join(found)
    planted = tmp_path / "frontend" / "x.js"
    planted.parent.mkdir()
    planted.write_text('if (m.message && m.message.startsWith("the controller runs WITHOUT")) banner();\n')
    assert scan_lines(PROSE_MATCH, scanned_files(tmp_path), root=tmp_path)


# ---- inside messages.py: each model in one union ---------------------------------------------------


def listings(text: str, models: Iterable[str]) -> dict[str, int]:
    """How many code lines of messages.py name each model, but its class line, docstrings' and
    comments' mentions (``...``, #) and ReplyMessage (which says which server kinds are replies:
    a fact of its own, not a second list of them)."""
    code = [
        line
        for line in text.splitlines()
        if not line.lstrip().startswith(("class ", "#", "ReplyMessage = ")) and "``" not in line
    ]
    return {m: sum(1 for line in code if re.search(rf"\b{m}\b", line)) for m in models}


def test_messages_lists_each_kind_once(tmp_path: Path) -> None:
    """messages.py listed the server kinds three times (SERVER, ServerMessage, TOPICS) and the client
    kinds twice (CLIENT, IncomingMessage): now each model is named in one union."""
    text = (REPO / MESSAGES_PY).read_text()
    models = re.findall(r"^class (\w+(?:Message|Request))\((?:_Out|_In|BaseModel)\)", text, re.MULTILINE)
    assert len(models) >= len(SPECS["server message kinds"].items) + len(SPECS["client message kinds"].items)
    counts = listings(text, models)
    assert all(n == 1 for n in counts.values()), f"name each model in one union only: {counts}"
    again = text + "\nSERVER = (StateMessage, RunMessage)\n"
    assert listings(again, models)["StateMessage"] == 2
    # Nor are the kinds spelled out again as strings there (TOPICS was a set of them): each
    # model's `type: Literal["kind"]` is the only place, one per class, never a stretch of them.
    for name in ("server message kinds", "client message kinds"):
        spec = replace(SPECS[name], definition="")
        assert not copies(spec, [REPO / MESSAGES_PY])
        planted = tmp_path / MESSAGES_PY
        planted.parent.mkdir(parents=True, exist_ok=True)
        planted.write_text(text + "\nTOPICS = frozenset({" + ", ".join(f'"{k}"' for k in spec.items) + "})\n")
        assert copies(spec, [planted], root=tmp_path)
