#!/usr/bin/env python3
"""The import graph of appliance/xrflab: no cycles, and every import points down the layers.

    python3 tests/lint/layers.py [APPLIANCE_DIR]     # ./lab check layers runs this

Layers, top to bottom (a module may import its own layer or a lower one, never a higher one):

    roots     the composition roots and command-line entry points: they wire things
    routes    server/http: HTTP routes; nothing but a root imports them
    services  the things that do the work and hold state (runs, security, room, viz, ros, builds...)
    domain    data, formats, rules and the wire's types: no state of the appliance, no I/O of its own
    bindings  the cffi binding of rt_core (channels.h and friends)

LAYER_OF below is the one definition of which module is in which layer; docs/developers/architecture.md
draws it and points here. A module the table does not place is an error too, so a new module is
placed on purpose.

Standard library only, and the package is never imported: its source is parsed with ast, every
import statement counted wherever it stands (inside functions and `if TYPE_CHECKING:` blocks too: a
deferred import still ties the two modules, and a type-only one still says which way the
knowledge flows). Exit 0 when clean, 1 with one line per violation and per cycle otherwise.
"""

from __future__ import annotations

import ast
import sys
from collections import deque
from dataclasses import dataclass
from pathlib import Path

PACKAGE = "xrflab"

LAYERS = ("roots", "routes", "services", "domain", "bindings")  # top first

# Module or package (dotted) -> layer: a name matches itself and every module below it, the longest
# match wins (so a module's own entry overrides its package's); a name ending in "$" matches only
# itself (a package's __init__, not what is below it).
LAYER_OF: dict[str, str] = {
    # ---- roots: whoever starts a process (a console script, `python -m`, the app factory) may wire anything
    "xrflab.server.app": "roots",  # the appliance's composition root: makes every service, includes every router
    "xrflab.server.cli": "roots",  # `xrf serve`, `xrf login`: start the app or talk to it
    "xrflab.cli": "roots",  # the `xrf` command: dispatches to every tool
    "xrflab.room.service": "roots",  # `xrf room` is a second FastAPI app: its own composition root
    "xrflab.room.cli": "roots",  # `xrf room ...` subcommands
    "xrflab.logs.cli": "roots",  # `xrf logs ...` subcommands
    "xrflab.projects_cli": "roots",  # `xrf project ...` subcommands
    "xrflab.projects.cli_new": "roots",  # `xrf new`: a project from a template
    # ---- routes: FastAPI routers, one per feature; only the roots include them
    "xrflab.server.http": "routes",
    # ---- services: stateful parts the roots make and hand to the routes
    "xrflab.server.runs": "services",  # the run supervisor and its parts, run records
    "xrflab.server.security": "services",  # accounts, sessions, permissions, the lease, the audit trail
    "xrflab.server.security.roles": "domain",  # the roles and their permissions: a rule, shared with the room's payloads
    "xrflab.room": "services",  # the lab room's bench side: MQTT, publisher, enrolment, sign-on
    "xrflab.room.topics": "domain",  # the room's MQTT topic names: pure strings, shared by both ends
    "xrflab.room.payloads": "domain",  # the room's MQTT payload models: the wire's types
    "xrflab.viz": "services",  # the 3D view: viser scene, per-run recordings
    "xrflab.viz.kinematics": "domain",  # forward kinematics: pure maths over a URDF
    "xrflab.ros": "services",  # the ROS 2 bridge node
    "xrflab.params.cli": "roots",  # `xrf param`: a command (through the API), imported by nobody
    "xrflab.grading.cli": "roots",  # `xrf grade`: a scenario on a project, here
    "xrflab.params": "services",  # live tuning: the current run's parameters, sets, change log (a run observer)
    "xrflab.twentysim_params": "domain",  # a 20-sim export's parameters from its tokens file (stdlib, installed for builds)
    "xrflab.selfcheck": "services",  # the self-check driver: runs xrf-selfcheck, keeps its reports
    "xrflab.selfcheck_service": "services",  # one self-check at a time over the bench, made by the app
    "xrflab.logs.live": "services",  # a run's logging from start to finish
    "xrflab.logs.host_writer": "services",  # the host log writer thread (ring -> file)
    "xrflab.logs.rerun_live": "services",  # a run's live rerun recording
    "xrflab.logs.rerun_servers": "services",  # rerun's child processes
    "xrflab.logs.rerun_sender": "services",  # the live recording's messages, sent to the run's proxy (gRPC-web)
    "xrflab.logs.rerun_files": "services",  # the rerun viewer's files copied (a child of the appliance; starts rerun_servers.RerunViewer)
    "xrflab.doctor": "services",  # the install's checks: run by `xrf doctor` and served by the system route
    "xrflab.projects.service": "services",  # the projects service the app makes: store, builds, versions
    "xrflab.projects.store": "services",  # the project/build store: SQLite and the project folders
    "xrflab.projects.versions": "services",  # the source versions kept on disk, through the store
    "xrflab.projects.builder": "services",  # the build queue and one build's steps; its parts follow
    "xrflab.projects.build_log": "services",  # one build's log file and its live stream to the hub
    "xrflab.projects.build_procs": "services",  # ends exactly one build's processes
    "xrflab.projects.build_result": "services",  # runs the build inside the sandbox, writes its outcome
    "xrflab.projects.build_user": "services",  # the system account builds run as
    "xrflab.projects.rt_core_mirror": "services",  # the rt_core copy builds compile against
    "xrflab.projects.sandbox": "services",  # the build sandbox process
    "xrflab.projects.sandbox_launch": "services",  # starts the build sandbox (what it is given, its wall time)
    "xrflab.guest": "services",  # the run sandbox's launcher (a process of its own, under a run)
    "xrflab.grading": "services",  # grading (issue 32): the runner of a scenario, the queue, the results' store
    "xrflab.credentials": "services",  # the saved login of `xrf login`, read by the command-line tools
    # ---- domain: data, formats and rules; no appliance state
    "xrflab$": "domain",  # xrflab/__init__.py: the package's version, nothing wired
    "xrflab.server$": "domain",  # server/__init__.py only (its folders take their own entries): nothing wired
    "xrflab.server.ws": "domain",  # WebSocket message models and the hub: the wire's types and their fan-out
    "xrflab.server.settings": "domain",  # Settings: the appliance's configuration, read by everyone
    "xrflab.projects": "domain",  # projects data: archives, source layout, build keys, digests, diagnostics, 20-sim
    "xrflab.projects.assignments": "domain",  # an assignment's id, limits and its folder on a bench (no store)
    "xrflab.build": "domain",  # where a project's sources are and how cmake builds them (`xrf build`, the builder)
    "xrflab.ticks": "domain",  # the common whole-second boundaries of the appliance's slow periodic work
    "xrflab.loopback": "domain",  # httpx clients for the appliance's children on 127.0.0.1 (no proxy, no TLS)
    "xrflab.tied": "domain",  # a process primitive (children die with their parent); knows nothing of the appliance
    "xrflab.records": "domain",  # column(...): a dataclass as a SQLite table and an API model
    "xrflab.plants": "domain",  # the plant table (through the binding)
    "xrflab.plant_field": "domain",  # the API's field naming a plant of the table, shared by two routers
    "xrflab.statemachine": "domain",  # the state machine (through the binding)
    "xrflab.profiles": "domain",  # the bench profile schema and its validator
    "xrflab.profile_flat": "domain",  # a profile's flat form for the checker
    "xrflab.selfcheck_limits": "domain",  # the self-check's hard limits (through the binding)
    "xrflab.runfolder": "domain",  # how a guest-writable folder is read: a rule, no state
    "xrflab.private_files": "domain",  # files created private
    "xrflab.errors": "domain",  # XrfError and its kinds: imported by every layer
    "xrflab.grading.scenario": "domain",  # the scenario file: its format and its checks (TOML, lines)
    "xrflab.grading.expr": "domain",  # custom checks' expressions: parsed with ast, evaluated over arrays
    "xrflab.grading.checks": "domain",  # evaluating checks over a log's columns
    "xrflab.grading.results": "domain",  # the result types the API serves
    "xrflab.logs": "domain",  # log formats: logformat, reader, converters, XRF2 .bin, record files
    # ---- bindings: the cffi binding of rt_core's headers and the host side of a segment
    "xrflab.channels": "bindings",  # a loop's segment through the cffi binding of channels.h
    "xrflab.msgdef": "bindings",  # .msg parser and codec: the segment's payloads are decoded with it (stdlib only)
    "xrflab._cffi_build": "bindings",  # cffi's build script for the binding
}

# Nothing but a root may import these, whatever its layer (the issue: no module imports a routes
# module but the app).
ROOT_ONLY = ("xrflab.server.http",)


@dataclass(frozen=True)
class Edge:
    source: str  # importing module, dotted, with the package
    target: str
    path: Path
    line: int


def module_names(appliance: Path) -> dict[str, Path]:
    """Every module of the package by dotted name (a package by its own name, for its __init__)."""
    out: dict[str, Path] = {}
    for path in sorted((appliance / PACKAGE).rglob("*.py")):
        parts = list(path.relative_to(appliance).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _known(name: str, modules: dict[str, Path]) -> str | None:
    """The module `name` lands in: itself, or the nearest package above it that exists."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def imports_of(module: str, path: Path, modules: dict[str, Path]) -> list[Edge]:
    """Every import of the package in one file, wherever it stands in the file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"
    found: list[Edge] = []

    def add(name: str, line: int) -> None:
        if name != PACKAGE and not name.startswith(PACKAGE + "."):
            return
        target = _known(name, modules)
        if target is not None and target != module:
            found.append(Edge(module, target, path, line))

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name, node.lineno)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                # `from .x import y` is relative to the module's package (a package is its own).
                here = module.split(".") if is_package else module.split(".")[:-1]
                here = here[: len(here) - (node.level - 1)]
                base = ".".join(here + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for alias in node.names:
                # `from pkg import sub` imports the submodule when there is one, else a name of pkg.
                sub = f"{base}.{alias.name}"
                add(sub if sub in modules else base, node.lineno)
    return found


def layer_of(module: str) -> str | None:
    if module + "$" in LAYER_OF:
        return LAYER_OF[module + "$"]
    name = module
    while name:  # the longest entry that is the module or a package above it
        if name in LAYER_OF:
            return LAYER_OF[name]
        name = name.rpartition(".")[0]
    return None


def _is_under(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def layer_violations(edges: list[Edge]) -> list[str]:
    out: list[str] = []
    for e in edges:
        src, dst = layer_of(e.source), layer_of(e.target)
        if src is None or dst is None:
            continue  # reported once per module by unplaced()
        back = LAYERS.index(dst) < LAYERS.index(src)
        root_only = src != "roots" and any(_is_under(e.target, p) for p in ROOT_ONLY)
        if back or root_only:
            why = "" if back else ", only roots may"
            out.append(f"{e.path}:{e.line}: {e.source} imports {e.target} (layer {src} → {dst}{why})")
    return out


def unplaced(modules: dict[str, Path]) -> list[str]:
    return [
        f"{path}: {name} is in no layer (add it to LAYER_OF in tests/lint/layers.py)"
        for name, path in modules.items()
        if layer_of(name) is None
    ]


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's components with more than one module, iteratively (the graph is deep)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    top = stack.pop()
                    on_stack.discard(top)
                    component.append(top)
                    if top == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return sorted(found)


def shortest_cycle(graph: dict[str, set[str]], start: str, within: set[str]) -> list[str]:
    """The shortest way from start back to itself inside one component (breadth first)."""
    came_from: dict[str, str] = {}
    queue = deque([start])
    while queue:
        node = queue.popleft()
        for nxt in sorted(graph[node] & within):
            if nxt == start:
                path = [node]
                while path[-1] != start:
                    path.append(came_from[path[-1]])
                return [start, *reversed(path[:-1]), start] if node != start else [start, start]
            if nxt not in came_from:
                came_from[nxt] = node
                queue.append(nxt)
    return [start]


def cycles(edges: list[Edge], modules: dict[str, Path]) -> list[str]:
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for e in edges:
        graph[e.source].add(e.target)
    out = []
    for component in strongly_connected(graph):
        loop = shortest_cycle(graph, component[0], set(component))
        line = "cycle: " + " → ".join(loop)
        if len(component) > len(loop) - 1:
            line += f" (one of the cycles among {len(component)} modules: {', '.join(component)})"
        out.append(line)
    return out


def check(appliance: Path) -> list[str]:
    modules = module_names(appliance)
    edges: dict[tuple[str, str], Edge] = {}
    unreadable: list[str] = []
    for name, path in modules.items():
        try:
            found = imports_of(name, path, modules)
        except SyntaxError as exc:  # its imports cannot be known: a problem, not a traceback
            unreadable.append(f"{path}:{exc.lineno}: {name} does not parse ({exc.msg})")
            continue
        for e in found:
            edges.setdefault((e.source, e.target), e)  # one line per pair: its first import
    found_edges = list(edges.values())
    return unreadable + unplaced(modules) + layer_violations(found_edges) + cycles(found_edges, modules)


def main(argv: list[str]) -> int:
    appliance = Path(argv[1]) if len(argv) > 1 else Path(__file__).resolve().parents[2] / "appliance"
    problems = check(appliance)
    for line in problems:
        print(line)
    if problems:
        print(f"layers: {len(problems)} problem(s); the layers are LAYER_OF in {Path(__file__).name}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
