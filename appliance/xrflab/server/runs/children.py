"""Starting the appliance's child processes with nothing inherited but what they need.

asyncio's ``create_subprocess_exec`` under uvloop (uvicorn's loop when installed) does not close
inherited descriptors: uvloop ignores ``close_fds`` (its TODO). A child would get every
descriptor of the appliance that is not close-on-exec. ``spawn()`` starts the child with
``subprocess.Popen`` instead (``close_fds=True``: fds 0-2 plus ``pass_fds`` only) and waits for it
on the event loop through a pidfd, so it works the same under either event loop. The result
behaves like ``asyncio.subprocess.Process`` for what the appliance uses (pid, returncode,
wait, send_signal, terminate, kill).

Nothing outlives the appliance but the loop: every other child (the ROS bridge, rerun servers,
builds, the self-check tool) is *tied* to it (xrflab/tied.py), so a kill -9 or an OOM kill of the
appliance ends them too and no orphan keeps a port. The loop process is the exception: it must
run on without us (its host_timeout_action decides); the restarted appliance reaps it
(supervisor.recover_orphans).

The loop process is started by the run sandbox (server/runs/guest_spawn.py), which closes descriptors itself.
docs/developers/security.md, "Descriptors", lists every child and what it gets.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
from collections.abc import Sequence
from typing import Any

from ...tied import popen_tied


class Child:
    """A started child process, awaited on the event loop."""

    def __init__(self, popen: subprocess.Popen[bytes]) -> None:
        self.popen = popen
        self.pid = popen.pid
        self._done: asyncio.Future[int] = asyncio.get_running_loop().create_future()
        self._watch()

    @property
    def returncode(self) -> int | None:
        return self.popen.returncode

    def _watch(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            pidfd = os.pidfd_open(self.pid)
        except (AttributeError, OSError):  # no pidfd (kernel < 5.3): a thread waits instead
            fut = asyncio.ensure_future(asyncio.to_thread(self.popen.wait))
            fut.add_done_callback(lambda f: self._set(f.result() if not f.exception() else -1))
            return

        def readable() -> None:
            loop.remove_reader(pidfd)
            os.close(pidfd)
            self._set(self.popen.wait())

        loop.add_reader(pidfd, readable)

    def _set(self, rc: int) -> None:
        if not self._done.done():
            self._done.set_result(rc)

    async def wait(self) -> int:
        return await asyncio.shield(self._done)

    def send_signal(self, sig: int) -> None:
        if self.popen.returncode is None:
            self.popen.send_signal(sig)

    def terminate(self) -> None:
        self.popen.terminate()

    def kill(self) -> None:
        self.popen.kill()


def spawn(
    argv: Sequence[str],
    *,
    pass_fds: Sequence[int] = (),
    tied: bool = True,
    death_signal: int = signal.SIGTERM,
    **popen: Any,
) -> Child:
    """``subprocess.Popen(argv, close_fds=True, pass_fds=pass_fds, **popen)`` as a `Child`
    (call it on the event loop's thread). `tied`: it dies with the appliance (`popen_tied`); only
    the run sandbox's launcher is not. Raises OSError like Popen (missing executable, ...)."""
    popen.pop("close_fds", None)
    if tied:
        proc = popen_tied(list(argv), death_signal=death_signal, close_fds=True, pass_fds=tuple(pass_fds), **popen)
    else:
        proc = subprocess.Popen(list(argv), close_fds=True, pass_fds=tuple(pass_fds), **popen)
    return Child(proc)


__all__ = ["Child", "spawn"]
