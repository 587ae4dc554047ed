"""The builds a run starts from: the projects that come with the appliance (examples and
templates, found in the projects folder and built on first use) and uploaded projects' builds
registered by name once they are built (server/http/projects.py).

A build runs in a worker thread (CMake and the compiler must not stall the event loop); its
output goes to the dashboards line by line as `build` messages. One build per project at a time:
whoever asks while it builds waits for that build instead of starting another.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ... import plants
from ..settings import Settings
from ..ws.messages import BuildMessage
from .errors import SupervisorError


@dataclass
class BuildEntry:
    name: str
    kind: str  # example | template
    path: Path
    sim: str
    status: str = "not built"  # not built | building | ready | failed
    executable: Path | None = None
    error: str = ""
    log_tail: list[str] = field(default_factory=list)
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)


class BuildCatalog:
    """The projects that come with the appliance, built on first use in a worker thread."""

    def __init__(self, settings: Settings, publish: Callable[[BuildMessage], None]) -> None:
        self._settings = settings
        self._publish = publish
        self._entries: dict[str, BuildEntry] = {}
        # Builds made elsewhere (uploaded projects, xrflab.projects): runnable by name, not listed.
        self._external: dict[str, BuildEntry] = {}
        self.scan()

    def scan(self) -> None:
        for kind, folder in (("example", "examples"), ("template", "templates")):
            root = self._settings.projects_dir / folder
            if not root.is_dir():
                continue
            for project in sorted(p for p in root.iterdir() if (p / "CMakeLists.txt").is_file()):
                name = project.name if kind == "example" else f"template-{project.name}"
                if name not in self._entries:
                    sim = project.name if project.name in plants.names() else self._settings.sim
                    self._entries[name] = BuildEntry(name, kind, project, sim)

    def entries(self) -> list[BuildEntry]:
        self.scan()  # examples may appear while we run (a fresh checkout being filled in)
        return list(self._entries.values())

    def add_external(self, name: str, path: Path, executable: Path, sim: str) -> BuildEntry:
        """Register a finished build of an uploaded project so start_run() can start it by name."""
        entry = BuildEntry(name, "project", path, sim, status="ready", executable=executable)
        self._external[name] = entry
        return entry

    def get(self, name: str) -> BuildEntry:
        if name in self._external:
            return self._external[name]
        self.scan()
        if name not in self._entries:
            raise SupervisorError(f"no build named {name!r}; have: {', '.join(self._entries)}", 404)
        return self._entries[name]

    async def ensure_built(self, name: str) -> BuildEntry:
        entry = self.get(name)
        async with entry.lock:  # one build per project at a time; later callers reuse it
            if entry.status == "ready" and entry.executable and entry.executable.exists():
                return entry
            entry.status, entry.error, entry.log_tail = "building", "", []
            loop = asyncio.get_running_loop()

            def log(line: str) -> None:  # called from the build thread
                entry.log_tail = (entry.log_tail + [line])[-200:]
                loop.call_soon_threadsafe(self._publish, BuildMessage(build=name, line=line))

            def work() -> Path:
                from ... import build

                # One build folder per rt_core install: a CMake cache remembers the XrfRt it
                # found first, so reusing a folder across rt_core versions would link the old one.
                prefix = build.ensure_rt_core(log)
                build_dir = self._settings.builds_dir / name / Path(prefix).name
                result = build.build_project(entry.path, build_dir, log=log)
                return Path(result.executable)

            self._publish(BuildMessage(build=name, status="building"))
            try:
                entry.executable = await asyncio.to_thread(work)
            except Exception as exc:  # BuildError and anything unexpected: the user sees why
                entry.status, entry.error = "failed", str(exc).splitlines()[0] if str(exc) else repr(exc)
                self._publish(BuildMessage(build=name, status="failed", error=entry.error))
                raise SupervisorError(f"build {name} failed: {entry.error}", 422) from exc
            entry.status = "ready"
            self._publish(BuildMessage(build=name, status="ready"))
            return entry
