"""``xrf serve``: the appliance on uvicorn. Registered in cli.py's EXTERNAL_SUBCOMMANDS; heavy
imports stay inside ``run`` because every ``xrf`` call imports this module to build its parser."""

from __future__ import annotations

import argparse
import socket
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..settings import Settings

HELP = "serve the dashboard and API (simulated bench unless EVL and the ico board are present)"

# Frames beyond this are refused by the WebSocket layer itself (close 1009); between the
# appliance's own 64 KiB limit and this one the client gets an `error` message instead.
WS_PROTOCOL_MAX = 4 * 1024 * 1024


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ... import plants
    from ..settings import default_data_dir

    parser.add_argument(
        "--sim",
        type=plants.arg_type,
        default="relbot",
        metavar="PLANT",
        help="simulated plant of rt_core's plant table: relbot (default), jiwy, ...",
    )
    parser.add_argument("--data", type=Path, default=None, help=f"data folder (default {default_data_dir()})")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0 for the lab network)")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument("--telemetry-hz", type=float, default=30.0, help="telemetry rate to browsers (default 30)")
    parser.add_argument("--hang-ms", type=int, default=200, help="no loop cycle for this long = hung (default 200)")
    parser.add_argument(
        "--allow-origin",
        action="append",
        default=[],
        metavar="URL",
        help="another origin allowed to use the API/WebSocket with a login cookie, e.g. "
        "https://lab.example.edu (repeatable; the page's own address always is)",
    )
    parser.add_argument(
        "--lease-idle-min",
        type=float,
        default=10.0,
        help="release the bench lease after this many minutes without driving (default 10)",
    )
    parser.add_argument(
        "--ros-bridge",
        action="store_true",
        default=None,
        help="start the ROS 2 bridge with every loop run (also $XRF_ROS_BRIDGE=1; "
        "educators can switch it on the dashboard's ROS 2 page)",
    )
    parser.add_argument(
        "--trusted-proxy",
        action="append",
        default=[],
        metavar="ADDR",
        help="address (or network, e.g. 10.0.0.0/24) of a reverse proxy in front of the appliance "
        "whose X-Forwarded-For/-Proto are believed (repeatable; default none: the headers "
        "are ignored)",
    )
    parser.add_argument(
        "--ros-bridge-user",
        default="",
        metavar="NAME",
        help="the user whose bench lease ROS 2 commands obey (default: who started the run)",
    )
    limits = parser.add_argument_group(
        "what the kernel bounds for each run (docs/developers/security.md, 'Resources the kernel bounds')"
    )
    limits.add_argument(
        "--run-memory-mb", type=int, default=1024, help="memory of a run, its /dev/shm and /tmp included (default 1024)"
    )
    limits.add_argument("--run-pids", type=int, default=256, help="processes and threads of a run (default 256)")
    limits.add_argument("--run-disk-mb", type=int, default=2048, help="a run folder's own file system (default 2048)")
    limits.add_argument("--run-files", type=int, default=65536, help="files and folders in it (default 65536)")
    limits.add_argument("--runs-total-mb", type=int, default=8192, help="every kept run folder together (default 8192)")
    limits.add_argument(
        "--loop-cpus",
        default="",
        metavar="LIST",
        help="the CPUs a run may use, e.g. 3 or 2-3 (default: the isolated ones, else $XRF_CPU, else the last)",
    )
    limits.add_argument(
        "--rt-time-ms",
        type=int,
        default=500,
        help="a real-time thread of a run that runs this long without blocking ends the run (default 500)",
    )
    parser.add_argument(
        "--allow-unconfined",
        action="store_true",
        default=False,
        help="let runs start when a protection layer of the run sandbox cannot be had (no "
        "subordinate uid, no user namespaces, ...): the controller then runs WITHOUT that "
        "layer and the dashboard says so on every page (default: such runs are refused; "
        "also $XRF_ALLOW_UNCONFINED=1; `xrf doctor` lists the layers)",
    )


def run(args: argparse.Namespace) -> int:
    import os

    from ..app import create_app
    from ..settings import SYSTEM_DATA_DIR, Settings, default_data_dir

    # Only when given: without the option Settings' default decides (e.g. $XRF_ALLOW_UNCONFINED).
    only_given: dict[str, Any] = {}
    if args.ros_bridge:
        only_given["ros_bridge"] = True
    if getattr(args, "allow_unconfined", False):
        only_given["allow_unconfined"] = True
    settings = Settings(
        data_dir=(args.data or default_data_dir()).expanduser(),
        sim=args.sim,
        host=args.host,
        port=args.port,
        telemetry_hz=args.telemetry_hz,
        hang_timeout_ms=args.hang_ms,
        allow_origins=tuple(o.rstrip("/") for o in args.allow_origin),
        lease_idle_s=args.lease_idle_min * 60,
        ros_bridge_user=args.ros_bridge_user,
        trusted_proxies=tuple(args.trusted_proxy),
        run_memory_mb=args.run_memory_mb,
        run_pids=args.run_pids,
        run_disk_mb=args.run_disk_mb,
        run_files=args.run_files,
        runs_total_mb=args.runs_total_mb,
        loop_cpus=args.loop_cpus,
        rt_time_ms=args.rt_time_ms,
        **only_given,
    )
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


def serve(app: Any, settings: Settings) -> None:
    import os

    import uvicorn

    os.umask(DATA_UMASK)
    # proxy_headers=False: uvicorn would believe X-Forwarded-For from 127.0.0.1, i.e. from any
    # process on this host (a student's controller); create_app() honours it only from
    # settings.trusted_proxies.
    config = uvicorn.Config(app, log_level="warning", ws_max_size=WS_PROTOCOL_MAX, proxy_headers=False)
    close_inherited_fds()
    uvicorn.Server(config).run(sockets=[listening_socket(settings)])
