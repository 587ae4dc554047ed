"""The ``xrf`` command: drive and watch a loop process from a terminal.

Each subcommand is a pair of small functions (arguments, action) in the SUBCOMMANDS table. Parts
of the project that live elsewhere register theirs in EXTERNAL_SUBCOMMANDS: a module path whose
module defines ``HELP: str``, ``add_arguments(parser)`` and ``run(args) -> int`` and keeps heavy
imports inside ``run`` (every ``xrf`` call imports it to build the parser).

Exit codes: 0 ok, 1 error (no loop, timeout, build failed), 2 usage, 3 command rejected.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from . import plants

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_REJECTED = 3

DEFAULT_SHM = "xrf"
# How long `xrf run` lets the controller finish its safe stop after forwarding SIGINT.
STOP_GRACE_S = 5.0
KILL_GRACE_S = 2.0
# Doorbell waits are cut into slices so Ctrl-C is noticed promptly (the wait releases the GIL,
# but Python handles the signal only once the C call returns).
DOORBELL_SLICE_MS = 200


class CliError(Exception):
    """A failure to report as one line on stderr with EXIT_ERROR."""


@dataclass(frozen=True)
class Subcommand:
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


SUBCOMMANDS: dict[str, Subcommand] = {}

# name -> module providing HELP, add_arguments(parser), run(args); imported when the parser is built.
EXTERNAL_SUBCOMMANDS: dict[str, str] = {
    "serve": "xrflab.server.cli.serve",
    "login": "xrflab.server.cli.login",
    "decode": "xrflab.logs.cli",
    "doctor": "xrflab.doctor",
    "selfcheck": "xrflab.selfcheck",
    "ros-bridge": "xrflab.ros.bridge",
    "upload": "xrflab.projects_cli",
    "new": "xrflab.projects.cli_new",
    "room": "xrflab.room.cli",
    "param": "xrflab.params.cli",
    "grade": "xrflab.grading.cli",
    "run-disk-helper": "xrflab.server.runs.disk_helper",
}


def _transport(text: str) -> str:
    """--transport: "auto" or one of rt_core's transports (channels.h's XRF_TRANSPORTS), looked up
    only when the option is given (the list comes through the cffi binding)."""
    from .channels.names import TRANSPORTS

    if text not in (*TRANSPORTS, "auto"):
        raise argparse.ArgumentTypeError(f"invalid choice: {text!r} (choose from {', '.join([*TRANSPORTS, 'auto'])})")
    return text


def subcommand(name: str, help: str, add_arguments: Callable[[argparse.ArgumentParser], None]):
    """Decorator registering `run` as ``xrf <name>``."""

    def register(run: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
        SUBCOMMANDS[name] = Subcommand(help, add_arguments, run)
        return run

    return register


def _open_channels(args: argparse.Namespace, wait_s: float | None = None, live: bool = False):
    """The loop's channels. With `live`, a segment whose loop has ended (a previous run's, left
    behind) is not the answer: a new loop that replaces it within the wait is, else an error
    that says the loop ended. Without it, an ended loop's segment is opened (its final state)."""
    from .channels import Channels, ChannelsError

    wait = args.timeout if wait_s is None else wait_s
    deadline = time.monotonic() + wait
    try:
        ch = Channels.open(args.shm, wait_s=wait)
    except (ChannelsError, ValueError, PermissionError) as exc:
        raise CliError(f"cannot reach a loop on shared memory '{args.shm}': {exc}") from None
    while live and not ch.loop_alive():
        newer = _newer_channels(ch, max(0.0, deadline - time.monotonic()))
        if newer is not None:
            ch = newer
            continue
        if time.monotonic() >= deadline:
            status, pid = ch.status(), ch.info["pid"]
            ch.close()
            raise CliError(
                f"the loop on shared memory '{args.shm}' has ended (pid {pid}, state "
                f"{status.state_name}); start one (xrf run) or name another with --shm"
            )
        time.sleep(0.05)
    return ch


def _newer_channels(ch: Any, wait_s: float = 0.0) -> Any:
    """When the segment `ch` maps was replaced by a new loop's (or removed and made again), the
    new one (and `ch` is closed); None while there is none. A loop re-creates its segment under
    the same name (runtime.cpp), so a tool watching the name must follow the object."""
    from .channels import Channels, ChannelsError

    if not ch.replaced():
        return None
    try:
        newer = Channels.open(ch.name, wait_s=min(wait_s, 0.2))
    except (ChannelsError, ValueError, PermissionError):
        return None
    ch.close()
    print(
        f"xrf: a new loop on shared memory '{newer.name}' (pid {newer.info['pid']}): following it",
        file=sys.stderr,
        flush=True,
    )
    return newer


def _add_shm(parser: argparse.ArgumentParser, timeout: float = 2.0) -> None:
    parser.add_argument(
        "--shm", default=os.environ.get("XRF_SHM", DEFAULT_SHM), help="shared-memory name (default: $XRF_SHM or xrf)"
    )
    parser.add_argument("--timeout", type=float, default=timeout, help=f"seconds to wait (default {timeout:g})")


def _print_json(obj: Any) -> None:
    print(json.dumps(obj, separators=(",", ":")), flush=True)


# ---- xrf cmd ------------------------------------------------------------------------------------


def _cmd_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("command", help="initialise, start, stop, reset, pause, quit, or a number")
    _add_shm(p)


@subcommand("cmd", "send a command to the loop and report whether it was accepted", _cmd_arguments)
def run_cmd(args: argparse.Namespace) -> int:
    from .channels import ChannelsError, command_number

    try:
        number = command_number(args.command)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    with _open_channels(args, live=True) as ch:
        try:
            result = ch.wait_command(ch.send_command(number), timeout=args.timeout)
        except ChannelsError as exc:
            raise CliError(str(exc)) from None
    if result.accepted:
        print(f"accepted: {result.state_name}")
        return EXIT_OK
    print(f"rejected: {result.reason}")
    return EXIT_REJECTED


# ---- xrf state ----------------------------------------------------------------------------------


def _state_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--wait", metavar="STATE", help="wait until the loop is in STATE (e.g. RUN)")
    p.add_argument("--json", action="store_true", help="print the whole status as JSON")
    _add_shm(p)


@subcommand("state", "print the loop's state (or wait for one)", _state_arguments)
def run_state(args: argparse.Namespace) -> int:
    from .channels import STATE_NUMBERS

    wanted = args.wait.upper() if args.wait else None
    if wanted is not None and wanted not in STATE_NUMBERS:
        raise CliError(f"unknown state {args.wait!r}; states: {', '.join(STATE_NUMBERS)}")
    deadline = time.monotonic() + args.timeout
    ch = _open_channels(args)
    try:
        status = ch.status()
        while wanted is not None and status.state_name != wanted:
            remaining_ms = int((deadline - time.monotonic()) * 1000)
            if remaining_ms <= 0:
                ended = "" if ch.loop_alive() else " (that loop has ended)"
                print(
                    f"timed out after {args.timeout:g} s waiting for {wanted}: state is {status.state_name}{ended}",
                    file=sys.stderr,
                )
                return EXIT_ERROR
            # A new run replaces the segment of an ended one under the same name: follow it.
            ch = _newer_channels(ch, remaining_ms / 1000) or ch
            # The doorbell only rings on publications; a short slice also catches state changes
            # of a loop that publishes nothing.
            ch.wait_doorbell(ch.doorbell, min(remaining_ms, 20))
            status = ch.status()
    finally:
        ch.close()
    if args.json:
        _print_json(status.as_dict())
    else:
        print(status.state_name)
    return EXIT_OK


# ---- xrf pub ------------------------------------------------------------------------------------


# XRF2's command topic under both releases' names (v1.1: XenoCmd; the first release: Command).
COMMAND_TOPICS = ("XenoCmd", "Command")
# XRF2's state topic under both releases' names (v1.1: XenoState; the first release: Xenomai_state).
STATE_TOPICS = ("XenoState", "Xenomai_state")


def _pub_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "message",
        choices=["Ros2Xeno", *COMMAND_TOPICS],
        help="Ros2Xeno, or a command as on XRF2's command topic (XenoCmd, or Command in the first release)",
    )
    p.add_argument(
        "fields",
        nargs="*",
        metavar="field=value",
        help="Ros2Xeno field values (fields not given are 0); for XenoCmd/Command one command: "
        "data=N, N or a name (initialise, start, ...)",
    )
    _add_shm(p)


@subcommand("pub", "write a Ros2Xeno message (or an XRF2 command) into the loop's channels", _pub_arguments)
def run_pub(args: argparse.Namespace) -> int:
    from .channels import ChannelsError

    if args.message in COMMAND_TOPICS:
        # As `ros2 topic pub XenoCmd std_msgs/Int32 "{data: 2}"` would: the command channel.
        if len(args.fields) != 1:
            raise CliError(f"{args.message} takes one value (data=N, N or a command name)")
        args.command = args.fields[0].partition("=")[2] if args.fields[0].startswith("data=") else args.fields[0]
        return run_cmd(args)
    with _open_channels(args, live=True) as ch:
        codec = ch.ros2xeno_codec
        values: dict[str, Any] = {}
        try:
            for item in args.fields:
                name, sep, text = item.partition("=")
                if not sep:
                    raise ValueError(f"expected field=value, got {item!r}; fields: {', '.join(codec.field_names)}")
                values[name.strip()] = codec.parse_value(name.strip(), text)
            payload = ch.write_ros2xeno(values)
        except (ValueError, ChannelsError) as exc:
            raise CliError(str(exc)) from None
        _print_json(codec.decode(payload))
    return EXIT_OK


# ---- xrf echo -----------------------------------------------------------------------------------

ECHO_TOPICS = ("Xeno2Ros", "sample", "status", "monitor", *STATE_TOPICS)


def _echo_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("topic", choices=ECHO_TOPICS)
    p.add_argument("--count", type=int, default=0, help="stop after N lines (default: until Ctrl-C)")
    p.add_argument("--shm", default=os.environ.get("XRF_SHM", DEFAULT_SHM), help="shared-memory name")
    p.add_argument("--timeout", type=float, default=0.0, help="give up after S seconds (default: never)")
    p.add_argument("--wait", type=float, default=2.0, help="seconds to wait for the loop to appear")


def _echo_source(ch: Any, topic: str) -> Callable[[], list[dict[str, Any]]]:
    """A function returning the lines published since its last call."""
    if topic == "monitor":
        monitor = ch.monitor_reader()
        return lambda: [{"cycle": m.cycle, "t_ns": m.t_ns, "text": m.text} for m in monitor.read()]
    if topic == "status":
        last_cycles: list[int | None] = [None]

        def new_status() -> list[dict[str, Any]]:
            s = ch.status()
            if s.cycles == last_cycles[0]:
                return []
            last_cycles[0] = s.cycles
            return [s.as_dict()]

        return new_status
    if topic in STATE_TOPICS:
        # As XRF2's state topic: {"data": state} (std_msgs/Int32), on every change.
        last_state: list[int | None] = [None]

        def new_state() -> list[dict[str, Any]]:
            state = ch.status().state
            if state == last_state[0]:
                return []
            last_state[0] = state
            return [{"data": state}]

        return new_state
    telemetry = ch.telemetry_reader()
    if topic == "Xeno2Ros":
        return lambda: [{"cycle": t.cycle, "t_ns": t.t_ns, **t.xeno2ros} for t in telemetry.read()]
    io_fields = ("cycle", "t_ns", "state", "enc", "din", "pwm", "dout")
    return lambda: [{k: getattr(t, k) for k in io_fields} for t in telemetry.read()]


@subcommand("echo", "print what the loop publishes, as JSON lines", _echo_arguments)
def run_echo(args: argparse.Namespace) -> int:
    ch = _open_channels(args, wait_s=args.wait, live=True)
    try:
        fetch = _echo_source(ch, args.topic)
        deadline = time.monotonic() + args.timeout if args.timeout > 0 else None
        printed = 0
        checked = time.monotonic()
        try:
            while True:
                # Every 100 ms: has a new run replaced the segment (same name, new object)?
                if time.monotonic() - checked > 0.1:
                    checked = time.monotonic()
                    newer = _newer_channels(ch)
                    if newer is not None:
                        ch, fetch = newer, _echo_source(newer, args.topic)
                # Read the doorbell before the ring: a publication after the read changes it, so
                # the wait below cannot sleep through it.
                seen = ch.doorbell
                for line in fetch():
                    _print_json(line)
                    printed += 1
                    if args.count and printed >= args.count:
                        return EXIT_OK
                if deadline is not None and time.monotonic() >= deadline:
                    print(f"timed out after {args.timeout:g} s ({printed} lines)", file=sys.stderr)
                    return EXIT_ERROR
                ch.wait_doorbell(seen, DOORBELL_SLICE_MS)
        except KeyboardInterrupt:
            return EXIT_OK
        except BrokenPipeError:  # `xrf echo ... | head`
            sys.stderr.close()
            return EXIT_OK
    finally:
        ch.close()


# ---- xrf build / run ----------------------------------------------------------------------------


def _build(project: Path) -> Path:
    from . import build  # the build module pulls in more than the other subcommands need

    try:
        # The build's log goes to stderr: stdout stays the executable's path, for scripts.
        result = build.build_project(project, log=lambda line: print(line, file=sys.stderr, flush=True))
    except Exception as exc:  # any build failure is reported the same way: one line, exit 1
        raise CliError(f"build of {project} failed: {exc}") from None
    return Path(result.executable)


def _build_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "project",
        type=Path,
        help="project folder (with CMakeLists.txt and msg/), an XRF2 "
        "controller package, or a ROS 2 workspace holding one",
    )
    p.add_argument(
        "--no-ros-messages",
        action="store_true",
        help="do not build the project's xrf2_msgs ROS 2 package (built by default when the "
        "ROS 2 build tools are installed, once per set of messages, for xrf ros-bridge)",
    )


def _build_ros_messages(project: Path) -> None:
    """The project's xrf2_msgs interface package, as `xrf ros-bridge` will need it: built now,
    with the controller (about a minute the first time, then cached by the messages' contents),
    so the bridge starts at once. Where ROS 2's build tools are missing, one line says so."""
    from . import build
    from .ros import interfaces

    try:
        # The messages the controller was built with: msg/, or for an XRF2 project its XRF2
        # folder's xrf2_msgs package (the same rules as the build).
        msg_dir = build.locate_project(project).msg_dir
    except build.BuildError:
        return
    say = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    try:
        interfaces.detect_toolchain()
    except interfaces.InterfaceBuildError:
        say("xrf2_msgs: not built (no ROS 2 build tools here); xrf ros-bridge would need them")
        return
    try:
        interfaces.build_interface_package(msg_dir, log=say)
    except (interfaces.InterfaceBuildError, OSError, ValueError) as exc:
        # The controller is built; the bridge's messages are a separate matter.
        say(f"xrf2_msgs: could not be built ({str(exc).splitlines()[0]}); xrf ros-bridge will say why again")


@subcommand("build", "build a controller project and print the executable's path", _build_arguments)
def run_build(args: argparse.Namespace) -> int:
    executable = _build(args.project)
    if not args.no_ros_messages:
        _build_ros_messages(args.project)
    print(executable)
    return EXIT_OK


def _run_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("target", type=Path, help="project folder (built first) or controller executable")
    p.add_argument(
        "--sim",
        type=plants.arg_type,
        metavar="PLANT",
        help="simulated robot (sets XRF_SIM): a plant of rt_core's plant table (relbot, jiwy, ...)",
    )
    p.add_argument("--freq", type=int, help="cycle frequency override in Hz (XRF_FREQ)")
    p.add_argument("--cpu", type=int, help="CPU to pin the loop thread to (XRF_CPU)")
    p.add_argument("--prio", type=int, help="SCHED_FIFO priority (XRF_PRIO)")
    p.add_argument("--shm", help="shared-memory name (XRF_SHM)")
    p.add_argument("--faults", help="simulator fault spec (XRF_SIM_FAULTS)")
    p.add_argument("--max-cycles", type=int, help="leave the loop after N cycles (XRF_MAX_CYCLES)")
    p.add_argument("--backend", choices=["posix", "evl", "auto"], help="XRF_BACKEND")
    p.add_argument(
        "--transport",
        type=_transport,
        metavar="TRANSPORT",
        help="XRF_TRANSPORT: a board transport of rt_core (sim, spidev, ...) or auto",
    )
    p.add_argument(
        "--stop-timeout", type=float, default=STOP_GRACE_S, help="seconds between SIGINT and SIGTERM on Ctrl-C"
    )
    p.add_argument(
        "--log-timing",
        action="store_true",
        help="log every cycle's wake-up jitter and stage durations to cycle_timing.xrf (XRF_LOG_TIMING)",
    )


def run_environment(args: argparse.Namespace) -> dict[str, str]:
    """The XRF_* variables (docs/developers/architecture.md) for the options given."""
    env = dict(os.environ)
    mapping = {
        "XRF_SIM": args.sim,
        "XRF_FREQ": args.freq,
        "XRF_CPU": args.cpu,
        "XRF_PRIO": args.prio,
        "XRF_SHM": args.shm,
        "XRF_SIM_FAULTS": args.faults,
        "XRF_MAX_CYCLES": args.max_cycles,
        "XRF_BACKEND": args.backend,
        "XRF_TRANSPORT": args.transport,
    }
    if args.log_timing:
        mapping["XRF_LOG_TIMING"] = "1"
    if args.sim and not args.transport:
        mapping["XRF_TRANSPORT"] = "sim"  # asking for a simulated robot means the simulated board
    env.update({k: str(v) for k, v in mapping.items() if v is not None})
    return env


def _remove_segment(child: subprocess.Popen, name: str) -> None:
    """The controller has exited: its segment goes with it (docs/developers/architecture.md,
    "Whose segment"). Only if it is still the controller's: a newer loop may own the name."""
    from .channels import ChannelsError, remove_if_owned

    try:
        remove_if_owned(name, child.pid)
    except (ChannelsError, ValueError, OSError):
        pass


def _exit_code(returncode: int) -> int:
    return 128 - returncode if returncode < 0 else returncode


@subcommand("run", "run a controller in the foreground (Ctrl-C stops it safely)", _run_arguments)
def run_run(args: argparse.Namespace) -> int:
    target: Path = args.target
    if target.is_dir():
        executable = _build(target)
    elif target.is_file() and os.access(target, os.X_OK):
        executable = target
    else:
        raise CliError(f"{target}: neither a project folder nor an executable file")
    # Own process group: a terminal's Ctrl-C reaches only us, and we forward exactly one SIGINT
    # (the runtime turns it into a safe stop) instead of the child getting it twice.
    env = run_environment(args)
    child = subprocess.Popen([str(executable.resolve())], env=env, start_new_session=True)
    stop_requested_at: list[float] = []

    def on_signal(signum: int, _frame: Any) -> None:
        if not stop_requested_at:
            stop_requested_at.append(time.monotonic())
            child.send_signal(signal.SIGINT)
        else:  # asked twice: stop waiting for the graceful path
            child.kill()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        escalated = False
        while True:
            try:
                code = _exit_code(child.wait(timeout=0.1))
            except subprocess.TimeoutExpired:
                pass
            else:
                _remove_segment(child, env.get("XRF_SHM") or DEFAULT_SHM)
                return code
            if not stop_requested_at:
                continue
            waited = time.monotonic() - stop_requested_at[0]
            if not escalated and waited > args.stop_timeout:
                print(
                    f"xrf run: controller still running {args.stop_timeout:g} s after SIGINT; sending SIGTERM",
                    file=sys.stderr,
                )
                child.terminate()
                escalated = True
            elif escalated and waited > args.stop_timeout + KILL_GRACE_S:
                print("xrf run: sending SIGKILL", file=sys.stderr)
                child.kill()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


# ---- entry point --------------------------------------------------------------------------------


def _register_external(subparsers: Any) -> None:
    for name, module_path in EXTERNAL_SUBCOMMANDS.items():
        if name in SUBCOMMANDS:
            continue
        try:
            module = importlib.import_module(module_path)
        except ImportError as exc:
            unavailable = f"'xrf {name}' is not available here ({module_path}: {exc})"
            p = subparsers.add_parser(name, help=f"(unavailable) {module_path}", add_help=False)
            p.add_argument("rest", nargs=argparse.REMAINDER)
            p.set_defaults(_run=lambda _a, msg=unavailable: _fail(msg))
            continue
        p = subparsers.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)


def _fail(message: str) -> int:
    raise CliError(message)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="xrf", description="XRF Lab: build, run, command and watch real-time controllers."
    )
    subparsers = parser.add_subparsers(dest="subcommand", metavar="SUBCOMMAND", required=True)
    for name, sub in SUBCOMMANDS.items():
        p = subparsers.add_parser(name, help=sub.help, description=sub.help)
        sub.add_arguments(p)
        p.set_defaults(_run=sub.run)
    _register_external(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except CliError as exc:
        print(f"xrf {args.subcommand}: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
