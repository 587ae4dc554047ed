"""``ros_xeno_bridge``: XRF2's ROS 2 topics on top of a loop's shared memory.

Topics (names and types as in XRF2, so existing nodes need no change):

* ``XenoCmd``  (std_msgs/Int32, subscribed) -> the command ring, source ROS, after the
  ``command_gate``; the outcome (accepted / rejected + reason) goes to the node's log.
* ``Ros2Xeno`` (xrf2_msgs/msg/Ros2Xeno, subscribed) -> the data channel (latest wins).
* ``XenoState`` (std_msgs/Int32, published) on every state change and every ``state_period``.
* ``Xeno2Ros`` (xrf2_msgs/msg/Xeno2Ros, published) for every decimated telemetry sample.

The first XRF2 release named the command and state topics ``Command`` and ``Xenomai_state``;
nodes written for it keep working: ``Command`` is subscribed like ``XenoCmd`` and every state is
published on ``Xenomai_state`` as well as on ``XenoState``.

Event-driven: a reader thread blocks in ``Channels.wait_doorbell`` (a futex; the GIL is
released) and publishes what the loop produced as soon as it rings; there is no polling timer.
Every sample is read from the broadcast ring with the bridge's own cursor, so none is skipped
by the bridge; samples the loop overwrote before the bridge read them are counted (``lost``)
and reported.

The bench lease is not part of this module: ``command_gate(user, cmd) -> (allowed, reason)``
is called for every XenoCmd. ``--gate-url unix:<socket>`` (set by the appliance when it starts the
bridge) makes it ``gate_client``: the appliance's lease gate is asked (xrflab/server/
server/runs/ros_bridge.py). Without it every command goes through.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import signal
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

HELP = "run the ROS 2 bridge node (XenoCmd, XenoState, Ros2Xeno, Xeno2Ros; Command, Xenomai_state)"

NODE_NAME = "ros_xeno_bridge"
TOPIC_CMD = "XenoCmd"
TOPIC_STATE = "XenoState"
TOPIC_ROS2XENO = "Ros2Xeno"
TOPIC_XENO2ROS = "Xeno2Ros"
# The first XRF2 release's names of the command and state topics (same types, same meaning).
TOPIC_CMD_V1_0 = "Command"
TOPIC_STATE_V1_0 = "Xenomai_state"
DEFAULT_DEPTH = 1000
DEFAULT_STATE_PERIOD_S = 1.0
SHUTDOWN_TIMEOUT_S = 5.0
# Upper bound of one doorbell wait: only for noticing shutdown and the periodic XenoState; every
# publication is woken by the doorbell itself.
_WAIT_SLICE_MS = 100

CommandGate = Callable[[str, int], "tuple[bool, str]"]


def allow_all(user: str, cmd: int) -> tuple[bool, str]:
    """The default gate: every command goes through (no bench lease yet)."""
    return True, ""


GATE_TOKEN_ENV = "XRF_ROS_GATE_TOKEN"
GATE_TIMEOUT_S = 2.0

# Live tuning (docs/students/tuning.md): a set of the controller's parameters from ROS 2
# (`ros2 param set`), by our names -> (applied, reason). Started by the appliance, the set goes to
# its parameter service through the gate (checked whole, the bench holder only, logged); a bridge
# of its own (`xrf ros-bridge` by hand) writes it to the segment and waits for the loop's answer.
ParamSetter = Callable[[str, "dict[str, float]"], "tuple[bool, str]"]


def params_gate_client(url: str, token: str) -> ParamSetter:
    """Parameter sets through the appliance's gate socket (one connection per set: they are rare)."""
    if not url.startswith("unix:"):
        raise ValueError(f"--gate-url {url!r}: only unix:<socket path> is supported")
    path = url[len("unix:") :]

    def setter(user: str, values: dict[str, float]) -> tuple[bool, str]:
        line = (json.dumps({"token": token, "user": user, "params": values}) + "\n").encode()
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                s.settimeout(GATE_TIMEOUT_S)
                s.connect(path)
                s.sendall(line)
                reply = s.makefile("rb").readline()
            answer = json.loads(reply)
        except (OSError, ValueError) as exc:
            return False, f"the appliance's gate is unreachable ({exc})"
        return bool(answer.get("allowed")), str(answer.get("reason", ""))

    return setter


def params_direct(channels: Any) -> ParamSetter:
    """Parameter sets written to the segment (a bridge without the appliance: no lease, no log)."""
    from ..channels import params as chparams

    table = chparams.read_table(channels.shm, channels.name)
    index = {p.name: p for p in table.params}

    def setter(user: str, values: dict[str, float]) -> tuple[bool, str]:
        entries = []
        for name, v in values.items():
            p = index.get(name)
            if p is None:
                return False, f"unknown parameter '{name}'"
            if p.has_range and not p.min <= v <= p.max:
                return False, f"parameter {name}: {v:g} is out of range {p.min:g} .. {p.max:g}"
            entries.append((p.index, v))
        try:
            seq = chparams.send_set(channels.shm, entries)
        except (ValueError, BlockingIOError) as exc:
            return False, str(exc)
        answer = chparams.wait_answer(channels.shm, seq, 1.0)
        if answer is None or not answer.applied:
            return False, "the loop did not take the set"
        return True, f"applied at cycle {answer.cycle}"

    return setter


def ros_param_name(name: str) -> str | None:
    """A controller parameter's ROS 2 name: 20-sim's path separator `\\` becomes `.`; a name ROS
    would refuse (anything but letters, digits, `_` and `.` between words) is not offered."""
    out = name.replace("\\", ".")
    return out if re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*(\.[A-Za-z][A-Za-z0-9_]*)*", out) else None


# Stopping is always safe (the appliance's STOP rule): with the appliance unreachable the commands
# channels.h marks safe (names.SAFE_COMMANDS) still go through; every other command is refused.


def gate_client(url: str, token: str) -> CommandGate:
    """A command gate asking the appliance's lease gate at `url` (``unix:/path/to/socket``): one
    JSON line ``{"token", "user", "cmd"}`` out, ``{"allowed", "reason"}`` back, on a connection kept
    open between commands (reopened once when the appliance closed it)."""
    import json
    import socket

    if not url.startswith("unix:"):
        raise ValueError(f"--gate-url {url!r}: only unix:<socket path> is supported")
    path = url[len("unix:") :]
    state: dict[str, Any] = {"sock": None, "file": None}
    lock = threading.Lock()

    def close() -> None:
        for k in ("file", "sock"):
            if state[k] is not None:
                try:
                    state[k].close()
                except OSError:
                    pass
                state[k] = None

    def ask(user: str, cmd: int) -> tuple[bool, str]:
        line = (json.dumps({"token": token, "user": user, "cmd": int(cmd)}) + "\n").encode()
        for attempt in (0, 1):
            if state["sock"] is None:
                s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                s.settimeout(GATE_TIMEOUT_S)
                s.connect(path)
                state["sock"], state["file"] = s, s.makefile("rb")
            try:
                state["sock"].sendall(line)
                reply = state["file"].readline()
                if not reply:
                    raise ConnectionError("the appliance closed the gate connection")
                answer = json.loads(reply)
                return bool(answer.get("allowed")), str(answer.get("reason", ""))
            except (OSError, ValueError):
                close()
                if attempt:
                    raise
        raise ConnectionError("unreachable")  # not reached

    def gate(user: str, cmd: int) -> tuple[bool, str]:
        with lock:
            try:
                return ask(user, cmd)
            except (OSError, ValueError) as exc:
                from ..channels.names import SAFE_COMMANDS, command_name

                name = command_name(int(cmd))
                if name in SAFE_COMMANDS:
                    return True, f"the appliance's gate is unreachable ({exc}); {name} is always allowed"
                return False, f"the appliance's gate is unreachable ({exc})"

    return gate


def _login_name() -> str:
    import getpass

    try:
        return getpass.getuser()
    except Exception:  # no USER/LOGNAME and no passwd entry
        return ""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--shm", default=os.environ.get("XRF_SHM", "xrf"), help="shared-memory name (default: $XRF_SHM or xrf)"
    )
    parser.add_argument(
        "--msg-dir",
        default=None,
        help="folder with Ros2Xeno.msg and Xeno2Ros.msg (default: the schemas the running loop publishes)",
    )
    parser.add_argument(
        "--user",
        default=os.environ.get("XRF_USER") or _login_name(),
        help="the user the bridge acts for (checked against the bench lease)",
    )
    parser.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the loop (default 10)")
    parser.add_argument("--depth", type=int, default=DEFAULT_DEPTH, help=f"QoS history depth (default {DEFAULT_DEPTH})")
    parser.add_argument(
        "--executor",
        choices=("single", "events"),
        default="single",
        help="rclpy executor: single (SingleThreadedExecutor, default) or events "
        "(rclpy.experimental.EventsExecutor, C++ dispatch)",
    )
    parser.add_argument(
        "--priority",
        type=int,
        default=int(os.environ.get("XRF_ROS_BRIDGE_PRIO", "0")),
        help="SCHED_FIFO priority for the bridge's threads (1..79, below the loop's; "
        "0 = leave the scheduling alone; needs CAP_SYS_NICE). Default $XRF_ROS_BRIDGE_PRIO or 0",
    )
    parser.add_argument(
        "--state-period",
        type=float,
        default=DEFAULT_STATE_PERIOD_S,
        help="seconds between periodic XenoState messages (default 1)",
    )
    parser.add_argument(
        "--gate-url",
        default=os.environ.get("XRF_ROS_GATE_URL", ""),
        help="ask the appliance before every XenoCmd: unix:<socket> of its lease gate "
        f"(token in ${GATE_TOKEN_ENV}; set by the appliance when it starts the bridge). "
        "Default $XRF_ROS_GATE_URL; empty = no gate (every command goes through)",
    )


# ---- message conversion -------------------------------------------------------------------------


def _to_ros(ftype: str) -> Callable[[Any], Any]:
    # msgdef decodes char/byte as integers; rosidl's Python types want str / bytes for them.
    if ftype == "char":
        return lambda v: [chr(x) for x in v] if isinstance(v, list) else chr(v)
    if ftype == "byte":
        return lambda v: [bytes([x]) for x in v] if isinstance(v, list) else bytes([v])
    return lambda v: v


def _from_ros(ftype: str) -> Callable[[Any], Any]:
    def one(x: Any) -> Any:
        if isinstance(x, (bytes, bytearray)):
            return x[0] if x else 0
        if isinstance(x, str):
            return ord(x) if x else 0
        return x

    if ftype in ("char", "byte"):
        return lambda v: [one(x) for x in v] if not isinstance(v, (str, bytes, int)) else one(v)
    return lambda v: v


class RosMessageType(Protocol):
    """A message class rosidl generated (its classes share no base type we could name)."""

    @classmethod
    def get_fields_and_field_types(cls) -> dict[str, str]: ...


class MessageMap:
    """Field-by-field mapping between a ROS message class and the loop's Codec (by field name).

    The codec's leaves of a standard type are dotted paths (``header.stamp.sec``): they are
    reached through the ROS message's own nested objects (``msg.header.stamp.sec``), so the bridge
    publishes and receives real std_msgs/Header, geometry_msgs/Pose, ... fields."""

    def __init__(self, codec: Any, msg_type: type[RosMessageType]) -> None:
        ros_fields = set(msg_type.get_fields_and_field_types())
        tops = list(dict.fromkeys(n.split(".", 1)[0] for n in codec.field_names))
        missing = [n for n in tops if n not in ros_fields]
        if missing or len(ros_fields) != len(tops):
            raise RuntimeError(
                f"{msg_type.__name__}: the ROS type's fields {sorted(ros_fields)} differ from the loop's "
                f"{tops} (was xrf2_msgs built from another project's msg/?)"
            )
        self.msg_type = msg_type
        self._to = [(f.name.split("."), _to_ros(f.type), f.count is not None and not f.is_string) for f in codec.fields]
        self._from = [
            (f.name.split("."), _from_ros(f.type), f.count is not None and not f.is_string) for f in codec.fields
        ]

    def to_msg(self, values: dict[str, Any]) -> Any:
        msg = self.msg_type()
        for path, conv, _array in self._to:
            name = ".".join(path)
            if name in values:
                parent = msg
                for part in path[:-1]:
                    parent = getattr(parent, part)
                setattr(parent, path[-1], conv(values[name]))
        return msg

    def from_msg(self, msg: Any) -> dict[str, Any]:
        out = {}
        for path, conv, array in self._from:
            v = msg
            for part in path:
                v = getattr(v, part)
            out[".".join(path)] = conv(list(v) if array else v)
        return out


def msg_dir_from_loop(channels: Any, into: str | Path) -> Path:
    """Write Ros2Xeno.msg / Xeno2Ros.msg from the schemas the loop publishes in its shared
    memory (same fields, types and order as the project's files; comments are not kept)."""
    out = Path(into)
    out.mkdir(parents=True, exist_ok=True)
    (out / "Ros2Xeno.msg").write_text(channels.ros2xeno_codec.schema + "\n")
    (out / "Xeno2Ros.msg").write_text(channels.xeno2ros_codec.schema + "\n")
    return out


# ---- the node -----------------------------------------------------------------------------------


class Bridge:
    """The bridge node on one loop. ``start()`` creates the ROS entities and the reader thread;
    the caller spins ``node`` (or uses ``spin_until``); ``stop()`` ends the threads."""

    def __init__(
        self,
        channels: Any,
        ros2xeno_type: type[RosMessageType],
        xeno2ros_type: type[RosMessageType],
        *,
        user: str = "",
        command_gate: CommandGate = allow_all,
        param_setter: ParamSetter | None = None,
        depth: int = DEFAULT_DEPTH,
        state_period: float = DEFAULT_STATE_PERIOD_S,
        node_name: str = NODE_NAME,
        context: Any = None,
    ) -> None:
        from rclpy.node import Node
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from std_msgs.msg import Int32

        from ..channels import lib

        self.ch = channels
        self.user = user
        self.command_gate = command_gate
        self.state_period = state_period
        self._source_ros = lib.XRF_SOURCE_ROS
        self._Int32 = Int32
        self.out_map = MessageMap(channels.xeno2ros_codec, xeno2ros_type)
        self.in_map = MessageMap(channels.ros2xeno_codec, ros2xeno_type)
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=depth,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
        )
        self.node = Node(node_name, context=context)
        self.log = self.node.get_logger()
        self.pub_state = self.node.create_publisher(Int32, TOPIC_STATE, qos)
        self.pub_state_v1_0 = self.node.create_publisher(Int32, TOPIC_STATE_V1_0, qos)
        self.pub_xeno2ros: Any = self.node.create_publisher(xeno2ros_type, TOPIC_XENO2ROS, qos)
        self.node.create_subscription(Int32, TOPIC_CMD, self._on_cmd, qos)
        self.node.create_subscription(Int32, TOPIC_CMD_V1_0, self._on_cmd, qos)
        self.node.create_subscription(ros2xeno_type, TOPIC_ROS2XENO, self._on_ros2xeno, qos)

        self._stop = threading.Event()
        self._cmd_cv = threading.Condition()
        self._cmd_queue: list[int] = []
        self._threads: list[threading.Thread] = []
        self.published = 0
        self.lost = 0
        self.commands_sent = 0
        self.ros2xeno_written = 0
        self.last_state: int | None = None
        self.param_setter = param_setter
        self._ros_params: dict[str, str] = {}  # ROS 2 name -> the controller's name
        self._param_index: dict[str, int] = {}  # ROS 2 name -> index in the loop's table
        self._param_table: Any = None
        self._param_seen = -1  # the loop's last answered set when the node's values were taken
        self._echo = threading.local()  # set in the thread that copies the loop's values in
        self._declare_parameters()

    # -- parameters (live tuning) ---------------------------------------------------------------

    def _declare_parameters(self) -> None:
        """The controller's tunable parameters as this node's ROS 2 parameters, with descriptors
        carrying the unit and, where the controller declared one, the range (ROS 2 refuses a
        value outside it before asking us)."""
        if self.param_setter is None:
            return
        from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, ParameterType, SetParametersResult

        from ..channels import ChannelsCorrupt
        from ..channels import params as chparams

        self._SetParametersResult = SetParametersResult
        try:
            table = chparams.read_table(self.ch.shm, self.ch.name)
            self._param_seen = chparams.last_answer(self.ch.shm)
            values = chparams.read_values(self.ch.shm, table)
        except ChannelsCorrupt as exc:
            self.log.error(f"no parameters: {exc}")
            return
        for p in table.params:
            ros_name = ros_param_name(p.name)
            if ros_name is None:
                self.log.warning(f"parameter '{p.name}' has no ROS 2 name; not offered")
                continue
            d = ParameterDescriptor(
                name=ros_name,
                type=ParameterType.PARAMETER_DOUBLE,
                description=f"{p.name} [{p.unit}] (default {p.default:g})",
            )
            if p.has_range:
                d.floating_point_range = [FloatingPointRange(from_value=p.min, to_value=p.max, step=0.0)]
            self.node.declare_parameter(ros_name, float(values[p.index]), d)
            self._ros_params[ros_name] = p.name
            self._param_index[ros_name] = p.index
        self._param_table = table
        self.node.add_on_set_parameters_callback(self._on_set_parameters)

    def _follow_parameters(self, force: bool = False) -> None:
        """The node's parameters follow the loop's values: a set applied from the dashboard or
        the CLI (or saved parameters, or 20-sim's Initialize) is what `ros2 param get` answers
        next. Checked when the loop has answered a new set (one shared-memory read per pass of
        the reader), and every state period (`force`) for values changed without a set."""
        if not self._param_index:
            return
        from rclpy.parameter import Parameter

        from ..channels import params as chparams

        seen = chparams.last_answer(self.ch.shm)
        if seen == self._param_seen and not force:
            return
        self._param_seen = seen
        values = chparams.read_values(self.ch.shm, self._param_table)
        changed = [
            Parameter(ros_name, Parameter.Type.DOUBLE, values[i])
            for ros_name, i in self._param_index.items()
            if self.node.get_parameter(ros_name).value != values[i]
        ]
        if not changed:
            return
        self._echo.on = True  # the loop's own values: taken as they are, not sent back as a set
        try:
            for r in self.node.set_parameters(changed):
                if not r.successful:  # e.g. outside a descriptor's range: say so, keep bridging
                    self.log.warning(f"parameter not followed: {r.reason}")
        finally:
            self._echo.on = False

    def _on_set_parameters(self, params: list[Any]) -> Any:
        """`ros2 param set`: the parameters as one set, applied whole or refused whole."""
        from rclpy.parameter import Parameter

        if getattr(self._echo, "on", False):
            return self._SetParametersResult(successful=True, reason="the loop's value")
        values: dict[str, float] = {}
        for prm in params:
            name = self._ros_params.get(prm.name)
            if name is None:
                return self._SetParametersResult(successful=False, reason=f"no parameter {prm.name}")
            if prm.type_ not in (Parameter.Type.DOUBLE, Parameter.Type.INTEGER):
                return self._SetParametersResult(successful=False, reason=f"{prm.name}: not a number")
            values[name] = float(prm.value)
        assert self.param_setter is not None
        ok, reason = self.param_setter(self.user, values)
        # Two call sites: rclpy refuses one call site logging at two severities.
        if ok:
            self.log.info(f"parameters {values}: {reason}")
        else:
            self.log.warning(f"parameters {values} refused: {reason}")
        return self._SetParametersResult(successful=ok, reason=reason)

    # -- ROS -> loop --------------------------------------------------------------------------

    def _on_cmd(self, msg: Any) -> None:
        # Handed to a worker: waiting for the loop's verdict must not block the executor (and
        # with it Ros2Xeno). The worker keeps the commands' order.
        with self._cmd_cv:
            self._cmd_queue.append(int(msg.data))
            self._cmd_cv.notify()

    def _command_worker(self) -> None:
        from ..channels import ChannelsError, command_name

        while True:
            with self._cmd_cv:
                while not self._cmd_queue and not self._stop.is_set():
                    self._cmd_cv.wait(0.5)
                if self._stop.is_set():
                    return
                cmd = self._cmd_queue.pop(0)
            name = f"{cmd} ({command_name(cmd)})"
            try:
                allowed, reason = self.command_gate(self.user, cmd)
            except Exception as exc:  # a broken gate refuses, it does not let everything through
                allowed, reason = False, f"command gate failed: {exc}"
            if not allowed:
                self.log.warning(f"XenoCmd {name} refused for user '{self.user}': {reason}")
                continue
            try:
                ticket = self.ch.send_command(cmd, source=self._source_ros)
                self.commands_sent += 1
                result = self.ch.wait_command(ticket, timeout=2.0)
            except ChannelsError as exc:
                self.log.error(f"XenoCmd {name}: {exc}")
                continue
            if result.accepted:
                self.log.info(f"XenoCmd {name} accepted: state {result.state_name}")
            else:
                self.log.warning(f"XenoCmd {name} rejected: {result.reason}")

    def _on_ros2xeno(self, msg: Any) -> None:
        try:
            self.ch.write_ros2xeno(self.in_map.from_msg(msg))
            self.ros2xeno_written += 1
        except (ValueError, RuntimeError) as exc:
            self.log.error(f"Ros2Xeno not written: {exc}")

    # -- loop -> ROS --------------------------------------------------------------------------

    def _publish_state(self, state: int) -> None:
        m = self._Int32()
        m.data = int(state)
        self.pub_state.publish(m)
        self.pub_state_v1_0.publish(m)
        self.last_state = int(state)

    def _reader(self) -> None:
        from ..channels import StatusBusy

        reader = self.ch.telemetry_reader()
        last_periodic = 0.0
        loop_pid = int(self.ch.info.get("pid", 0))
        seen = self.ch.doorbell
        while not self._stop.is_set():
            # Read the doorbell before draining: a ring that comes while we publish is not missed.
            seen = self.ch.doorbell
            for sample in reader.read():
                self.pub_xeno2ros.publish(self.out_map.to_msg(sample.xeno2ros))
                self.published += 1
            if reader.lost != self.lost:
                self.log.warning(
                    f"{reader.lost - self.lost} Xeno2Ros sample(s) overwritten by the loop before the bridge "
                    f"read them ({reader.lost} in total)"
                )
                self.lost = reader.lost
            try:
                state = self.ch.status().state
            except StatusBusy:  # the loop mid-write, no copy read yet: the next round asks again
                self.ch.wait_doorbell(seen, _WAIT_SLICE_MS)
                continue
            now = time.monotonic()
            periodic = now - last_periodic >= self.state_period
            self._follow_parameters(force=periodic)
            if state != self.last_state or periodic:
                self._publish_state(state)
                last_periodic = now
                if loop_pid and not _alive(loop_pid):
                    self.log.error(f"the loop process (pid {loop_pid}) is gone; bridge stops")
                    self._stop.set()
                    self.loop_gone = True
                    return
            self.ch.wait_doorbell(seen, _WAIT_SLICE_MS)

    loop_gone = False

    # -- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        for target, name in ((self._reader, "xrf-ros-reader"), (self._command_worker, "xrf-ros-cmd")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        self.log.info(
            f"bridging shm '{self.ch.name}' (program {self.ch.info.get('program')}, "
            f"Xeno2Ros at {self.ch.info.get('write_decimator_freq')} Hz) for user '{self.user}'"
        )

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def stop(self, timeout: float = SHUTDOWN_TIMEOUT_S) -> bool:
        """Stop the threads; True when both ended within timeout."""
        self._stop.set()
        with self._cmd_cv:
            self._cmd_cv.notify_all()
        deadline = time.monotonic() + timeout
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
        return not any(t.is_alive() for t in self._threads)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


# ---- running it ---------------------------------------------------------------------------------


def prepare_messages(
    channels: Any, msg_dir: str | Path | None, log: Callable[[str], None] = print
) -> tuple[type, type]:
    """Build (cached) and import xrf2_msgs for this loop; returns (Ros2Xeno, Xeno2Ros)."""
    from ..msgdef import Codec, parse_msg_file
    from .interfaces import build_interface_package, use_in_this_process

    with tempfile.TemporaryDirectory(prefix="xrf-ros-msg-") as tmp:
        if msg_dir is None:
            msg_dir = msg_dir_from_loop(channels, tmp)
        else:
            for name, codec in (("Ros2Xeno", channels.ros2xeno_codec), ("Xeno2Ros", channels.xeno2ros_codec)):
                theirs = Codec(parse_msg_file(Path(msg_dir) / f"{name}.msg")).schema
                if theirs != codec.schema:
                    raise RuntimeError(
                        f"{msg_dir}/{name}.msg does not match the running loop's {name} "
                        f"({theirs!r} vs {codec.schema!r}): rebuild the controller or pick the right --msg-dir"
                    )
        prefix = build_interface_package(msg_dir, log=log)
    loaded = sys.modules.get("xrf2_msgs")
    if loaded is not None and not str(getattr(loaded, "__file__", "")).startswith(str(prefix) + os.sep):
        # Python modules and the shared libraries (one soname each) cannot be swapped in a
        # running process: one project's xrf2_msgs per process.
        raise RuntimeError(
            f"this process already uses xrf2_msgs from {loaded.__file__}; "
            f"another project's messages ({prefix}) need their own process"
        )
    use_in_this_process(prefix)
    from xrf2_msgs.msg import Ros2Xeno, Xeno2Ros  # noqa: E402  (importable only now)

    return Ros2Xeno, Xeno2Ros


def _setter_or_none(make: Callable[[Any], ParamSetter], ch: Any, say: Callable[[str], None]) -> ParamSetter | None:
    from ..channels import ChannelsCorrupt

    try:
        return make(ch)
    except ChannelsCorrupt as exc:
        say(f"no parameters offered: {exc}")
        return None


def run(args: argparse.Namespace, command_gate: CommandGate = allow_all) -> int:
    from ..channels import Channels, ChannelsError

    stop = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stop.set()

    # Explicit handlers (rclpy's own are disabled below): SIGTERM from the appliance's
    # supervisor and Ctrl-C both end the spin loop and run the orderly shutdown.
    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)

    def say(text: str) -> None:
        print(f"xrf ros-bridge: {text}", file=sys.stderr, flush=True)

    gate_url = getattr(args, "gate_url", "")
    if gate_url and command_gate is allow_all:
        # Started by the appliance: every XenoCmd is asked at its lease gate (the bench lease).
        try:
            command_gate = gate_client(gate_url, os.environ.get(GATE_TOKEN_ENV, ""))
        except ValueError as exc:
            say(str(exc))
            return 2
        say(f"XenoCmd obey the appliance's lease gate ({gate_url}) for user '{args.user}'")
    param_setter_of: Callable[[Any], ParamSetter] = params_direct
    if gate_url:
        token = os.environ.get(GATE_TOKEN_ENV, "")
        param_setter_of = lambda _ch: params_gate_client(gate_url, token)  # noqa: E731

    prio = getattr(args, "priority", 0)
    if prio:
        # Before any thread exists: the reader, the command worker and the DDS threads inherit
        # it, so a busy host delays the bridge no more than it delays other real-time work.
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
        except (PermissionError, OSError, ValueError) as exc:
            say(f"cannot use SCHED_FIFO priority {prio} ({exc}); running with normal scheduling")

    try:
        ch = Channels.open(args.shm, wait_s=args.timeout)
    except (ChannelsError, ValueError, PermissionError) as exc:
        say(f"cannot reach a loop on shared memory '{args.shm}': {exc}")
        return 1
    try:
        ros2xeno_type, xeno2ros_type = prepare_messages(ch, args.msg_dir, log=say)
    except Exception as exc:
        say(f"cannot provide xrf2_msgs: {exc}")
        return 1

    try:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
    except ImportError as exc:
        say(f"rclpy is not available ({exc}): {rclpy_missing_hint(platform.machine())}")
        return 1

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    bridge = Bridge(
        ch,
        ros2xeno_type,
        xeno2ros_type,
        user=args.user,
        command_gate=command_gate,
        param_setter=_setter_or_none(param_setter_of, ch, say),
        depth=args.depth,
        state_period=args.state_period,
    )
    if getattr(args, "executor", "single") == "events":
        from rclpy.experimental import EventsExecutor

        executor = EventsExecutor()
    else:
        executor = SingleThreadedExecutor()
    executor.add_node(bridge.node)
    bridge.start()
    try:
        while not stop.is_set() and not bridge.stopping:
            executor.spin_once(timeout_sec=0.1)
    finally:
        # Shutdown with a watchdog: a rare hang in DDS teardown must not keep the process alive.
        watchdog = threading.Timer(SHUTDOWN_TIMEOUT_S, lambda: os._exit(1 if bridge.loop_gone else 0))
        watchdog.daemon = True
        watchdog.start()
        clean = bridge.stop(SHUTDOWN_TIMEOUT_S / 2)
        say(
            f"stopping: {bridge.published} Xeno2Ros published, {bridge.lost} lost in the ring, "
            f"{bridge.commands_sent} commands, {bridge.ros2xeno_written} Ros2Xeno written"
            + ("" if clean else " (threads did not end in time)")
        )
        executor.shutdown(timeout_sec=1.0)
        bridge.node.destroy_node()
        rclpy.try_shutdown()
        watchdog.cancel()
    return 1 if bridge.loop_gone else 0


def rclpy_missing_hint(machine: str) -> str:
    """How to get rclpy on this machine. PyPI's ROS 2 wheels are x86_64 only (pyproject.toml's `ros`
    extra leaves them out elsewhere): a Pi uses the system's ROS 2, from apt."""
    if machine == "x86_64":
        return (
            "install the `ros` extra into the appliance's venv (./lab does: pip install -e '.[ros]'), "
            "or source /opt/ros/<distro>/setup.bash before starting the appliance"
        )
    return (
        f"PyPI has no ROS 2 wheels for {machine}: install ROS 2 from apt (Ubuntu 24.04: "
        "ros-jazzy-ros-base, docs/install/pi.md) and source /opt/ros/jazzy/setup.bash before starting "
        "the appliance (its venv then finds the system's rclpy)"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="xrf ros-bridge", description=HELP)
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
