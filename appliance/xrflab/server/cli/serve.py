"""``xrf serve``: the appliance on uvicorn. Registered in cli.py's EXTERNAL_SUBCOMMANDS; heavy
imports stay inside ``run`` because every ``xrf`` call imports this module to build its parser."""

from __future__ import annotations

import argparse
import dataclasses
import socket
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..settings import Settings

HELP = "serve the dashboard and API (simulated bench unless EVL and the ico board are present)"

# Frames beyond this are refused by the WebSocket layer itself (close 1009); between the
# appliance's own 64 KiB limit and this one the client gets an `error` message instead.
WS_PROTOCOL_MAX = 4 * 1024 * 1024


# Each option sets one Settings field, and takes its default from it: the defaults are written
# once, in Settings (server/settings.py). "{default}" in a help text is that default as the option
# takes it. flag: (field, help, option value -> field value, field default -> option default, more
# add_argument keywords). --data, --ros-bridge and --allow-unconfined are below: their defaults are
# decided when Settings is made (the user's data folder, $XRF_ROS_BRIDGE, $XRF_ALLOW_UNCONFINED).
def _same(v: Any) -> Any:
    return v


def _options() -> dict[str, tuple[str, str, Callable[[Any], Any], Callable[[Any], Any], dict[str, Any]]]:
    from ... import plants

    return {
        "--sim": (
            "sim",
            "simulated plant of rt_core's plant table: {default} (default), jiwy, ...",
            _same,
            _same,
            {"type": plants.arg_type, "metavar": "PLANT"},
        ),
        "--host": ("host", "address to listen on (0.0.0.0 for the lab network)", _same, _same, {}),
        "--port": ("port", "", _same, _same, {"type": int}),
        "--telemetry-hz": (
            "telemetry_hz",
            "telemetry rate to browsers (default {default})",
            _same,
            _same,
            {"type": float},
        ),
        "--hang-ms": (
            "hang_timeout_ms",
            "no loop cycle for this long = hung (default {default})",
            _same,
            _same,
            {"type": int},
        ),
        "--allow-origin": (
            "allow_origins",
            "another origin allowed to use the API/WebSocket with a login cookie, e.g. "
            "https://lab.example.edu (repeatable; the page's own address always is)",
            lambda v: tuple(o.rstrip("/") for o in v),
            list,
            {"action": "append", "metavar": "URL"},
        ),
        "--lease-idle-min": (
            "lease_idle_s",
            "release the bench lease after this many minutes without driving (default {default})",
            lambda v: v * 60,
            lambda s: s / 60,
            {"type": float},
        ),
        "--trusted-proxy": (
            "trusted_proxies",
            "address (or network, e.g. 10.0.0.0/24) of a reverse proxy in front of the appliance "
            "whose X-Forwarded-For/-Proto are believed (repeatable; default none: the headers "
            "are ignored)",
            tuple,
            list,
            {"action": "append", "metavar": "ADDR"},
        ),
        "--ros-bridge-user": (
            "ros_bridge_user",
            "the user whose bench lease ROS 2 commands obey (default: who started the run)",
            _same,
            _same,
            {"metavar": "NAME"},
        ),
    }


# What the kernel bounds for each run: the same, in a group of their own.
def _limit_options() -> dict[str, tuple[str, str, Callable[[Any], Any], Callable[[Any], Any], dict[str, Any]]]:
    return {
        "--run-memory-mb": (
            "run_memory_mb",
            "memory of a run, its /dev/shm and /tmp included (default {default})",
            _same,
            _same,
            {"type": int},
        ),
        "--run-pids": ("run_pids", "processes and threads of a run (default {default})", _same, _same, {"type": int}),
        "--run-disk-mb": (
            "run_disk_mb",
            "a run folder's own file system (default {default})",
            _same,
            _same,
            {"type": int},
        ),
        "--run-files": ("run_files", "files and folders in it (default {default})", _same, _same, {"type": int}),
        "--runs-total-mb": (
            "runs_total_mb",
            "every kept run folder together (default {default})",
            _same,
            _same,
            {"type": int},
        ),
        "--loop-cpus": (
            "loop_cpus",
            "the CPUs a run may use, e.g. 3 or 2-3 (default: the isolated ones, else $XRF_CPU, else the last)",
            _same,
            _same,
            {"metavar": "LIST"},
        ),
        "--rt-time-ms": (
            "rt_time_ms",
            "a real-time thread of a run that runs this long without blocking ends the run (default {default})",
            _same,
            _same,
            {"type": int},
        ),
    }


def field_default(name: str) -> Any:
    """A Settings field's default (its factory's value for a field that has one)."""
    from ..settings import Settings

    f = {f.name: f for f in dataclasses.fields(Settings)}[name]
    if f.default is not dataclasses.MISSING:
        return f.default
    assert f.default_factory is not dataclasses.MISSING, name
    return f.default_factory()


def _add(
    parser: Any, options: dict[str, tuple[str, str, Callable[[Any], Any], Callable[[Any], Any], dict[str, Any]]]
) -> None:
    for flag, (name, help_text, _, to_option, more) in options.items():
        default = to_option(field_default(name))
        shown = f"{default:g}" if isinstance(default, float) else default
        parser.add_argument(flag, default=default, help=help_text.format(default=shown) or None, **more)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..settings import default_data_dir

    options = _options()
    _add(parser, {"--sim": options.pop("--sim")})
    parser.add_argument("--data", type=Path, default=None, help=f"data folder (default {default_data_dir()})")
    _add(
        parser,
        {
            k: options.pop(k)
            for k in ("--host", "--port", "--telemetry-hz", "--hang-ms", "--allow-origin", "--lease-idle-min")
        },
    )
    parser.add_argument(
        "--ros-bridge",
        action="store_true",
        default=None,
        help="start the ROS 2 bridge with every loop run (also $XRF_ROS_BRIDGE=1; "
        "educators can switch it on the dashboard's ROS 2 page)",
    )
    _add(parser, options)
    limits = parser.add_argument_group(
        "what the kernel bounds for each run (docs/developers/security.md, 'Resources the kernel bounds')"
    )
    _add(limits, _limit_options())
    parser.add_argument(
        "--allow-unconfined",
        action="store_true",
        default=False,
        help="let runs start when a protection layer of the run sandbox cannot be had (no "
        "subordinate uid, no user namespaces, ...): the controller then runs WITHOUT that "
        "layer and the dashboard says so on every page (default: such runs are refused; "
        "also $XRF_ALLOW_UNCONFINED=1; `xrf doctor` lists the layers)",
    )


def settings_from(args: argparse.Namespace) -> Settings:
    """The Settings `xrf serve`'s options ask for: every option's field, the rest Settings' defaults."""
    from ..settings import Settings, default_data_dir

    fields: dict[str, Any] = {"data_dir": (args.data or default_data_dir()).expanduser()}
    for flag, (name, _, to_field, _, _) in {**_options(), **_limit_options()}.items():
        fields[name] = to_field(getattr(args, flag[2:].replace("-", "_")))
    # Only when given: without the option Settings' default decides (e.g. $XRF_ALLOW_UNCONFINED).
    if args.ros_bridge:
        fields["ros_bridge"] = True
    if getattr(args, "allow_unconfined", False):
        fields["allow_unconfined"] = True
    return Settings(**fields)


def run(args: argparse.Namespace) -> int:
    import os

    from ..app import create_app
    from ..settings import SYSTEM_DATA_DIR

    settings = settings_from(args)
    shown = "localhost" if args.host in ("127.0.0.1", "0.0.0.0", "::") else args.host
    bench = "real ico board" if settings.bench_is_real() else f"simulated {settings.sim}"
    print(f"XRF Lab: {bench} bench, data in {settings.data_dir}", flush=True)
    if args.data is None and os.geteuid() == 0:
        print(
            f"XRF Lab: running as root: the data folder is {SYSTEM_DATA_DIR}, as on the Pi (builds run as "
            "xrf-build and controllers as xrf-run; they may pass through it, never list it); --data chooses "
            "another",
            flush=True,
        )
    if settings.allow_unconfined:
        print(
            "XRF Lab: --allow-unconfined: runs start even when a protection layer of the run sandbox is "
            "missing (the dashboard then says which)",
            flush=True,
        )
    print(f"XRF Lab: open http://{shown}:{args.port}/ in a browser", flush=True)
    serve(create_app(settings), settings)
    return 0


def listening_socket(settings: Settings) -> socket.socket:
    """The server socket, with a bounded send buffer every accepted connection inherits.

    Close-on-exec (Python's default, kept): no child may hold it. A controller that inherited it
    could accept() other users' logins, and an orphaned child holding it after a kill -9 of the
    appliance kept the port, so the restarted appliance failed with "Address already in use".
    uvicorn serves a non-inheritable socket as well (sockets=[...], one process)."""
    family = socket.AF_INET6 if ":" in settings.host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, settings.send_buffer_bytes)
    sock.bind((settings.host, settings.port))
    sock.listen(128)
    return sock


def close_inherited_fds() -> None:
    """Mark every descriptor above 2 that the appliance was started with close-on-exec: whatever
    its parent leaked to it (a terminal's, a test harness's) must not reach the children it
    starts. Descriptors it opens itself are close-on-exec already (PEP 446, O_CLOEXEC in rt_core)."""
    import os

    for name in os.listdir("/proc/self/fd"):
        fd = int(name)
        if fd > 2:
            try:
                os.set_inheritable(fd, False)
            except OSError:
                pass  # the listing's own descriptor, gone by now


# Everything the appliance creates (databases and their WAL/SHM, runs, logs, projects, uploads,
# builds it starts) is private to its user whatever umask it was started with; what another user
# must read (the build user: a project's source) is granted explicitly (projects/build_user.py).
DATA_UMASK = 0o077


# glibc's malloc arenas for the appliance (its default: 8 per core). A thread that allocates while
# another holds an arena gets one of its own, and what was freed in an arena is kept by it, in
# pieces: with the default, the appliance's RSS grew ~1-2 MB a round of a practical's events with
# no Python object kept (tracemalloc: ~0.15 MB a round), and settled 15-25 MB higher
# (bench/README.md, "memory": MALLOC_ARENA_MAX=2 measured against the default). Its threads
# (uvicorn's loop, the run's reader and writers, the thread pools, viser, rerun's) mostly wait,
# so two arenas cost them no measurable contention. MALLOC_ARENA_MAX in the environment wins.
MALLOC_ARENAS = 2
_M_ARENA_MAX = -8  # mallopt's parameter (malloc.h)


def limit_malloc_arenas(arenas: int = MALLOC_ARENAS) -> bool:
    """glibc's arena limit set for this process (from now on: arenas are made lazily, so early in
    the process is what counts); False where there is no glibc (musl) or the environment sets it."""
    import ctypes
    import os

    if os.environ.get("MALLOC_ARENA_MAX"):
        return False
    try:
        return bool(ctypes.CDLL(None).mallopt(_M_ARENA_MAX, arenas))
    except (OSError, AttributeError):
        return False


def serve(app: Any, settings: Settings) -> None:
    import os

    import uvicorn

    limit_malloc_arenas()  # before the app's threads start (its lifespan, below)
    os.umask(DATA_UMASK)
    # proxy_headers=False: uvicorn would believe X-Forwarded-For from 127.0.0.1, i.e. from any
    # process on this host (a student's controller); create_app() honours it only from
    # settings.trusted_proxies.
    # ws_per_message_deflate=False: compressing each WebSocket message (browsers ask for it) cost
    # ~44 us of zlib and websockets' Python per telemetry message, 7.5 a second per dashboard, and a
    # compressor's window per connection; a telemetry message is ~1.8 KB (six samples: 9 KB/s).
    config = uvicorn.Config(
        app,
        log_level="warning",
        ws_max_size=WS_PROTOCOL_MAX,
        ws_per_message_deflate=False,
        proxy_headers=False,
    )
    close_inherited_fds()
    quiet_server(config).run(sockets=[listening_socket(settings)])


def quiet_server(config: Any) -> Any:
    """uvicorn's Server, with no tick at all.

    uvicorn's main loop sleeps 0.1 s at a time to see whether a signal asked it to stop, and
    refreshes its Date header every tenth tick: 10 wake-ups a second of the event loop, a sixth
    of an idle appliance's Python time (py-spy, issue 30 item 4). Session 9 made it one a
    second; it was still about a tenth of the idle event loop's Python (the tick's wait and the
    header, py-spy, session 14). Here nothing ticks: the stop request wakes the main loop itself
    (the signal handler sets an event through the event loop), so a stop is as quick as before,
    and the Date header is made when a response reads it (`DatedState`: formatted once per
    second that has a response, the same text uvicorn's tick made)."""
    import asyncio
    import time
    from email.utils import formatdate

    import uvicorn
    from uvicorn.server import ServerState

    class DatedState(ServerState):
        """uvicorn's shared state whose default headers (Date and the configured ones) are made
        when a connection or a response reads them, not by a tick: uvicorn's protocols read
        `server_state.default_headers` for each response (and each WebSocket handshake)."""

        def __init__(self) -> None:
            self._second = -1
            self._headers: list[tuple[bytes, bytes]] = []
            super().__init__()

        @property
        def default_headers(self) -> list[tuple[bytes, bytes]]:
            now = int(time.time())
            if now != self._second:
                date = [(b"date", formatdate(now, usegmt=True).encode())] if config.date_header else []
                self._headers = date + config.encoded_headers
                self._second = now
            return self._headers

        @default_headers.setter
        def default_headers(self, value: list[tuple[bytes, bytes]]) -> None:
            pass  # (uvicorn's on_tick and ServerState's __init__ set it: made at reading here)

    class QuietServer(uvicorn.Server):
        _stop_event: asyncio.Event | None = None
        _loop: asyncio.AbstractEventLoop | None = None

        def __init__(self, config: Any) -> None:
            super().__init__(config)
            self.server_state = DatedState()

        async def main_loop(self) -> None:
            self._loop = asyncio.get_running_loop()
            self._stop_event = asyncio.Event()
            while True:
                if await self.on_tick(0):
                    return
                await self._stop_event.wait()  # set by handle_exit, whatever thread it runs in
                self._stop_event.clear()

        def handle_exit(self, sig: int, frame: Any) -> None:
            super().handle_exit(sig, frame)
            loop, event = self._loop, self._stop_event
            if loop is not None and event is not None:
                try:
                    loop.call_soon_threadsafe(event.set)
                except RuntimeError:  # the loop is closed already
                    pass

    return QuietServer(config)
