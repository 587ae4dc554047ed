"""Where the appliance's event loop spends its CPU, per asyncio task (bench/appliance/footprint.py
--task-cpu; issue 30 item 4, session 16).

Loaded by the appliance's Python when this folder is on its PYTHONPATH and $XRF_TASK_CPU_OUT is
set (footprint.py does both). Every asyncio task's coroutine is driven through a wrapper that adds
the thread CPU time (time.thread_time_ns) of each of its steps to its name (the coroutine's
qualified name; the run's supervised tasks, all `guarded`, by the name they are guarded as), and
a few functions named below are timed per call the same way. Every 5 s the sums, and the event
loop thread's whole CPU time (its schedstat), are appended to $XRF_TASK_CPU_OUT.<pid> as a JSON
line; task_cpu_report.py prints a window of them.

Why not a sampling profiler: py-spy, on this VM, counted the event loop as busy while it waited
in uvloop's epoll and put the idle appliance's Python at several times its measured CPU; it sent
session 15 after pieces that each cost tens of microseconds hot. What a wake-up costs here is
mostly cold caches (a 30 us call hot takes 200 us after a second asleep), which only timing the
real steps in the running appliance shows. The wrapper costs ~1 us a step.
"""

from __future__ import annotations

import asyncio
import collections
import functools
import json
import os
import sys
import threading
import time
from typing import Any

_task_ns: collections.Counter[str] = collections.Counter()
_task_steps: collections.Counter[str] = collections.Counter()
_call_ns: collections.Counter[str] = collections.Counter()
_calls: collections.Counter[str] = collections.Counter()
_MAIN_TID = threading.get_native_id()

# (module, class or None, function): timed per call once the appliance has imported them.
CALLS = [
    ("xrflab.channels.rings", "TelemetryReader", "read_batch"),
    ("xrflab.channels.rings", "TelemetryBatch", "__getitem__"),
    ("xrflab.server.runs.lifecycle", "RunLifecycle", "samples"),
    ("xrflab.server.runs.lifecycle", "RunLifecycle", "live"),
    ("xrflab.viz.scene", "VizService", "on_samples"),
    ("xrflab.viz.recorder", "Recorder", "add_many"),
    ("xrflab.server.runs.timing", None, "refresh_state"),
    ("xrflab.server.runs.timing", None, "timing_message_fields"),
    ("xrflab.server.runs.timing", None, "_miss_alarm"),
    ("xrflab.server.runs.reader", None, "refresh_state"),
    ("xrflab.logs.host_writer", "HostLogWriter", "take_timing"),
    ("xrflab.logs.host_writer", "HostLogWriter", "_drain"),
    ("xrflab.logs.timing_series", "TimingSeries", "write_pending"),
    ("xrflab.server.runs.limits", "RunLimits", "over"),
    ("xrflab.server.ws.hub", "Hub", "publish_fields"),
    ("xrflab.server.ws.hub", "Client", "_send_now"),
    ("xrflab.server.ws.hub", None, "encode"),
    ("xrflab.channels.host", "Channels", "host_heartbeat"),
]


class _Timed:
    """Awaitable driving `coro` step by step, each step's thread CPU added to `name`."""

    __slots__ = ("coro", "name")

    def __init__(self, coro: Any, name: str) -> None:
        self.coro, self.name = coro, name

    def __await__(self) -> Any:
        coro, name = self.coro, self.name
        value: Any = None
        error: BaseException | None = None
        while True:
            t0 = time.thread_time_ns()
            try:
                step = coro.send(value) if error is None else coro.throw(error)
            except StopIteration as done:
                return done.value
            finally:
                _task_ns[name] += time.thread_time_ns() - t0
                _task_steps[name] += 1
            try:
                value, error = (yield step), None
            except BaseException as exc:  # handed to the coroutine, as a task would
                value, error = None, exc


async def _timed(coro: Any, name: str) -> Any:
    return await _Timed(coro, name)


def _task_name(coro: Any) -> str:
    name = getattr(coro, "__qualname__", type(coro).__name__)
    if name == "guarded":  # server/runs/reader.py guarded(name, body, ...): the name it guards
        frame = getattr(coro, "cr_frame", None)
        if frame is not None:
            name = f"guarded:{frame.f_locals.get('name')}"
    return name


class _TimedTask(asyncio.Task):  # type: ignore[type-arg]
    def __init__(self, coro: Any, *args: Any, **kwargs: Any) -> None:
        if hasattr(coro, "send"):
            coro = _timed(coro, _task_name(coro))
        super().__init__(coro, *args, **kwargs)


def _timed_call(key: str, f: Any) -> Any:
    @functools.wraps(f)
    def call(*args: Any, **kwargs: Any) -> Any:
        t0 = time.thread_time_ns()
        try:
            return f(*args, **kwargs)
        finally:
            _call_ns[key] += time.thread_time_ns() - t0
            _calls[key] += 1

    return call


def _wrap_calls() -> None:
    for module, cls, name in CALLS:
        m = sys.modules.get(module)
        owner: Any = getattr(m, cls, None) if (m is not None and cls) else m
        f = None if owner is None else (owner.__dict__.get(name) if cls else getattr(owner, name, None))
        if f is not None:
            setattr(owner, name, _timed_call(f"{cls or module.rsplit('.', 1)[1]}.{name}", f))


def _dump(out: str) -> None:
    started = time.monotonic()
    time.sleep(8)  # the appliance's start-up: its modules imported before their calls are wrapped
    _wrap_calls()
    while True:
        time.sleep(5)  # a snapshot every 5 s: the report takes the difference of two
        try:
            with open(f"/proc/self/task/{_MAIN_TID}/schedstat") as f:
                main_ns = int(f.read().split()[0])
        except OSError:
            main_ns = -1
        line = {
            "t": time.monotonic() - started,
            "main_ns": main_ns,
            "tasks": dict(_task_ns),
            "steps": dict(_task_steps),
            "calls_ns": dict(_call_ns),
            "calls": dict(_calls),
        }
        with open(f"{out}.{os.getpid()}", "a") as f:
            f.write(json.dumps(line) + "\n")


def _install() -> None:
    out = os.environ.get("XRF_TASK_CPU_OUT")
    with open("/proc/self/cmdline", "rb") as f:
        appliance = b"serve_for_test" in f.read()  # the appliance, not every Python that inherits the path
    if not out or not appliance:
        return
    asyncio.Task = _TimedTask  # type: ignore[misc]  # before uvloop and asyncio's users import it
    asyncio.tasks.Task = _TimedTask  # type: ignore[misc]
    threading.Thread(target=_dump, args=(out,), name="xrf-task-cpu", daemon=True).start()


_install()
