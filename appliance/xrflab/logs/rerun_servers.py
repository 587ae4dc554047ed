"""The rerun child processes of the appliance: the web viewer's file server and a run's live proxy.

Both are ``rerun`` processes whose servers listen on 127.0.0.1 only: they have no login of their
own, so browsers reach them only through the appliance (its /rerun/ files route and its gRPC-web
read proxy, server/http/rerun.py). They run below the appliance's priority (``RERUN_NICE``) and
end with it: by ``stop_rerun_children`` on a normal exit (atexit, and the app's shutdown), by a
parent-death signal when it is killed (``tied.popen_tied``).

- ``RerunViewer``: only while the web viewer's files are copied (once per rerun version).
- ``LiveProxy``: one per run, the message proxy the run's live recording (``rerun_live.py``)
  writes to and viewers read from.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

RERUN_NICE = 10  # rerun's child processes run below the appliance
LIVE_WINDOW = "48KiB"  # what a run's live proxy keeps for late viewers: ~2 s of RELbot (LiveProxy)
# Ours, added to the page of each viewer that opens in a tab of its own (rerun's, by
# server/http/rerun.py; viser's 3D scene, by server/http/viser.py): the frontend's shared helpers,
# then the tab script (Esc stops the run there too, frontend/rerun-tab.js).
LIB_SCRIPT = "/static/lib.js"
TAB_SCRIPT = "/static/rerun-tab.js"


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def _free_port(preferred: int) -> int:
    for port in (preferred, 0):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return s.getsockname()[1]
    raise OSError("no free port")


def _rerun_cli() -> list[str]:
    # The binary itself, not the venv's `rerun` wrapper script: the wrapper runs it as a child, and
    # that child would outlive the appliance (the parent-death signal goes to the wrapper).
    with contextlib.suppress(ImportError):
        import rerun_cli

        exe = Path(rerun_cli.__file__).with_name("rerun")
        if exe.is_file():
            return [str(exe)]
    found = shutil.which("rerun")
    if found:
        return [found]
    return [sys.executable, "-m", "rerun_cli"]


def _spawn_rerun(argv: list[str]) -> subprocess.Popen[bytes]:
    """A rerun server that gets SIGTERM when the appliance dies, a kill -9 included (the atexit
    hook below does not run then), so none is left with parent 1 (server/children.popen_tied)."""
    from ..tied import popen_tied

    return popen_tied(
        argv,
        death_signal=signal.SIGTERM,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


class _RerunChild:
    """A ``rerun`` child process whose servers listen on 127.0.0.1 only: they have no login of
    their own, so browsers reach them only through the appliance (its /rerun/ files route and its
    gRPC-web read proxy, server/http/rerun.py). Stopped with the appliance (stop_rerun_children)."""

    def __init__(self, args: list[str], ports: tuple[int, ...], what: str) -> None:
        # Below the appliance (`nice` execs rerun, so every rerun thread inherits it): a live
        # proxy starting with each run must not delay the supervisor's reaction to that run
        # crashing (outputs off within 100 ms).
        nice = ["nice", "-n", str(RERUN_NICE)] if shutil.which("nice") else []
        self.proc = _spawn_rerun([*nice, *_rerun_cli(), *args])
        deadline = time.monotonic() + 20
        while not all(_listening(p) for p in ports):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise OSError(f"the rerun {what} did not start (exit {self.proc.poll()})")
            time.sleep(0.05)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class RerunViewer(_RerunChild):
    """``rerun --serve-web``, only for the web viewer's files (they come from the installed
    rerun-sdk; nothing from the internet): started once per rerun version by the child process
    that copies them into the appliance's data folder (server/http/rerun.py
    ``prepare_in_this_process``), and stopped by it as soon as the copy is made; the appliance
    serves the copy under /rerun/ behind the login. Port from XRF_RERUN_WEB_PORT (default 9090;
    a taken port falls back to a free one)."""

    def __init__(self) -> None:
        self.web_port = _free_port(int(os.environ.get("XRF_RERUN_WEB_PORT", "9090")))
        grpc_port = _free_port(0)  # --serve-web always opens a gRPC server too; nothing uses it
        super().__init__(
            [
                "--serve-web",
                "--bind",
                "127.0.0.1",
                "--port",
                str(grpc_port),
                "--web-viewer-port",
                str(self.web_port),
                "--server-memory-limit",
                "1MiB",
            ],
            (self.web_port,),
            "viewer",
        )


class LiveProxy(_RerunChild):
    """The live stream of ONE run: a ``rerun --serve-grpc`` message proxy on 127.0.0.1 that the
    run's recording (``LiveRerun``) writes to and viewers read from, through the appliance's
    gRPC-web read proxy. One per run, not one per appliance, because a rerun proxy replays
    everything it still buffers to each new viewer: with one shared proxy a student opening the
    live view would receive earlier runs of other students. Opening the next run's proxy stops
    the previous one; the last stays up after its run ends, so its viewers keep their plots.

    A viewer opens at the live edge (issue 31 bug 6): the proxy keeps only a short window
    (``LIVE_WINDOW``, XRF_RERUN_MEMORY; 48 KiB is ~2 s of the RELbot example, which streams
    ~24 KB/s in 12 messages of ~2 KB, and under a second of 64 variables at 100 Hz) and replays
    it newest first (``--newest-first``), so a late viewer's first samples are the loop's latest,
    not cycle 0. The viewer ingests at most 10 ms of messages per frame, and a frame takes ~1 s
    in chromium without a GPU: what it is handed on connect delays the live samples behind it.
    Measured there (bench/appliance/rerun_lag.py, issue 31 bug 6): 1 MiB, first data 2.1 s behind
    live, then 6.5 s behind before it caught up 8 s later; 256 KiB, 2.1 s; 48 KiB, 0.8 s and
    0.7-1.5 s from then on; 16 KiB, 0.7 s. With 256 MiB replayed oldest first, a
    browser opened four minutes into a run drew minutes-old samples for two minutes before it
    reached the live edge, and the proxy grew ~5 MB a minute up to its cap (issue 30 item 4).
    The whole run is in its log: "replay from start" opens the log's .rrd (frontend/rerun-tab.js).
    Blueprint and store info are kept whatever the limit (rerun never drops them), and the
    series names (static) are dropped only after every sample is."""

    _current: LiveProxy | None = None
    _lock = threading.Lock()

    def __init__(self, run_id: int, owner: str) -> None:
        self.run_id = run_id
        self.owner = owner
        self.port = _free_port(0)
        super().__init__(
            [
                "--serve-grpc",
                "--bind",
                "127.0.0.1",
                "--port",
                str(self.port),
                "--server-memory-limit",
                os.environ.get("XRF_RERUN_MEMORY", LIVE_WINDOW),
                "--newest-first",
            ],
            (self.port,),
            "live proxy",
        )
        self.local_url = f"rerun+http://127.0.0.1:{self.port}/proxy"
        # Viewers reading this proxy through the appliance (server/http/rerun.py counts them in and
        # out, on the event loop): the run's recording sends only while there is one (LiveRerun).
        self.readers = 0
        self.read_url = f"http://127.0.0.1:{self.port}"  # where the appliance forwards gRPC-web reads

    @classmethod
    def open_for_run(cls, run_id: int, owner: str) -> LiveProxy:
        with cls._lock:
            if cls._current is not None:
                cls._current.stop()
                cls._current = None
            cls._current = cls(run_id, owner)
            return cls._current

    @classmethod
    def current(cls) -> LiveProxy | None:
        proxy = cls._current
        return proxy if proxy is not None and proxy.proc.poll() is None else None

    @classmethod
    def stop_all(cls) -> None:
        with cls._lock:
            if cls._current is not None:
                cls._current.stop()
                cls._current = None


@atexit.register  # the appliance's normal exit (SIGTERM under systemd) ends them
def stop_rerun_children() -> None:
    """Stop the live proxy (also called by the app's shutdown)."""
    LiveProxy.stop_all()
