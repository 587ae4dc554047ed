"""Child processes that die with the process that started them (stdlib only).

``popen_tied`` is ``subprocess.Popen`` plus ``PR_SET_PDEATHSIG``: when the appliance (or an
``xrf`` command) dies, a kill -9 or an OOM kill included, the child gets `death_signal`, so no
rerun server, ROS bridge, build or self-check tool runs on with parent 1 or keeps a port.

The kernel sends that signal when the *thread* that forked the child ends, not the process: a
child forked from a short-lived worker thread would be killed when that thread finishes. So every
tied child is forked by one long-lived thread of ours, whoever asks for it.
"""

from __future__ import annotations

import ctypes
import os
import queue
import signal
import subprocess
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Any

PR_SET_PDEATHSIG = 1
# Resolved now: a forked child must not dlopen (another thread may have held the loader's lock).
_prctl = ctypes.CDLL(None, use_errno=True).prctl


def _die_with(parent: int, sig: int) -> Callable[[], None]:
    def arm() -> None:  # in the forked child, before exec
        _prctl(PR_SET_PDEATHSIG, sig, 0, 0, 0)
        if os.getppid() != parent:  # we died before the prctl took effect
            os._exit(1)

    return arm


_requests: queue.SimpleQueue[tuple[list[str], dict[str, Any], Future[subprocess.Popen[Any]]]] = queue.SimpleQueue()
_forker: threading.Thread | None = None
_forker_lock = threading.Lock()


def _forker_main() -> None:
    while True:
        argv, kwargs, done = _requests.get()
        try:
            done.set_result(subprocess.Popen(argv, **kwargs))
        except BaseException as exc:  # handed to the caller
            done.set_exception(exc)


def popen_tied(argv: Sequence[str], *, death_signal: int = signal.SIGTERM, **popen: Any) -> subprocess.Popen[Any]:
    """``subprocess.Popen(argv, **popen)`` whose child gets `death_signal` when the appliance
    dies (from any thread; close_fds stays Popen's default, True)."""
    global _forker
    with _forker_lock:
        if _forker is None or not _forker.is_alive():
            _forker = threading.Thread(target=_forker_main, name="xrf-child-forker", daemon=True)
            _forker.start()
    if "preexec_fn" in popen:
        raise ValueError("popen_tied sets preexec_fn itself")
    done: Future[subprocess.Popen[Any]] = Future()
    _requests.put((list(argv), {**popen, "preexec_fn": _die_with(os.getpid(), death_signal)}, done))
    return done.result(60)


__all__ = ["popen_tied"]
