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
from collections.abc import Callable
from pathlib import Path

RERUN_NICE = 10  # rerun's child processes run below the appliance
# What a run's live proxy keeps for late viewers (LiveProxy): ~1 s of RELbot. 96 KiB with the rerun
# SDK's sender, whose messages were LZ4-compressed; the appliance's own (rerun_sender.py) sends them
# uncompressed, ~1.6x the bytes, blueprint included: 160 KiB holds the seconds 96 held (measured
# with both senders' streams, 17-18 data messages, 1.0 s; bench/README.md, session 12).
LIVE_WINDOW = "160KiB"
# A viewer's page was loaded (its wasm app starts seconds later, then opens the stream): the run's
# recording streams for this long without a reader, so the proxy holds the live edge when it
# connects (LiveProxy.expect_viewer).
EXPECT_VIEWER_S = 20.0
# A reader of an ended run's proxy is connecting (LiveProxy.ensure_running): its process is kept
# this long before the reader is counted in.
CONNECT_GRACE_S = 10.0
# The proxy's window ends at the live edge while the recording sends (a batch every 0.5 s,
# logs/rerun_live.py SEND_PERIOD_S); once it has not sent for this long, the window is what it
# sent before the last viewer left, however long ago (LiveProxy.fresh).
STALE_S = 1.0
# After a pause, the recording's first batch is in the proxy this long after the recording said
# it sent it: the SDK's batcher flushes every 0.2 s (rerun's default flush tick) and its gRPC
# client sends on a thread of its own. (A blocking flush in the recording's thread took long
# enough to delay its next batches.)
RESUMED_S = 0.5
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
        self._launch(args, ports, what)

    proc: subprocess.Popen[bytes] | None = None

    def _launch(self, args: list[str], ports: tuple[int, ...], what: str) -> None:
        # Below the appliance (`nice` execs rerun, so every rerun thread inherits it): a live
        # proxy starting with each run must not delay the supervisor's reaction to that run
        # crashing (outputs off within 100 ms).
        nice = ["nice", "-n", str(RERUN_NICE)] if shutil.which("nice") else []
        proc = _spawn_rerun([*nice, *_rerun_cli(), *args])
        deadline = time.monotonic() + 20
        while not all(_listening(p) for p in ports):
            if proc.poll() is not None or time.monotonic() > deadline:
                _end(proc)
                raise OSError(f"the rerun {what} did not start (exit {proc.poll()})")
            time.sleep(0.05)
        # Only now: a process that does not listen yet is not running for a reader (a live
        # viewer's page starts the proxy on a thread and is served meanwhile: its stream's request
        # must wait for the start under way, not connect to a port nobody listens on).
        self.proc = proc

    def stop(self) -> None:
        if self.proc is not None:
            _end(self.proc)


def _end(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


class RerunViewer(_RerunChild):
    """``rerun --serve-web``, only for the web viewer's files (they come from the installed
    rerun-sdk; nothing from the internet): started once per rerun version by the child process
    that copies them into the appliance's data folder (server/http/rerun.py
    ``rerun_files.py``), and stopped by it as soon as the copy is made; the appliance
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
    the previous one.

    Its process (~33 MB RSS, issue 30 item 4) starts at the run's first viewer, not with the run
    (``ensure_running``: when a live viewer's page is served, ``expect_viewer``, or a reader
    connects; the run's recording sends nothing before, rerun_live.py), on the port reserved
    when the run started if it is still free. After its run has ended (``run_ended``) the process
    runs only while a viewer reads it or one is loading (``in_use``): the viewers open at the
    end keep their plots, and when the last of them leaves (or at once, when none was open) it
    stops (``_retire``). The proxy itself stays the last run's (``current``, /api/logs/rerun as
    before); a viewer that opens it later starts the process again, an empty stream: the run's
    data is in its log ("replay from start").

    A viewer opens at the live edge (issue 31 bug 6): the proxy keeps only a short window
    (``LIVE_WINDOW``, XRF_RERUN_MEMORY; 160 KiB since the appliance sends uncompressed messages,
    session 12, holding what 96 KiB held of the SDK's; 96 KiB was ~1.5 s of the RELbot example, which streams
    ~24 KB/s in 12 messages of ~2 KB: rerun counts ~45 KiB for what it never drops, so 48 KiB,
    the limit before, held no sample at all and a late viewer got no window, only the next
    batches; measured with a headless reader connecting 5 s after the recording started: 48 KiB
    nothing, 80 KiB 1.3 s, 96 KiB 1.6 s, 128 KiB 2.9 s, 256 KiB all 5.6 s) and replays
    it newest first (``--newest-first``), so a late viewer's first samples are the loop's latest,
    not cycle 0. The viewer ingests at most 10 ms of messages per frame, and a frame takes ~1 s
    in chromium without a GPU: what it is handed on connect delays the live samples behind it.
    Measured there (bench/appliance/rerun_lag.py, issue 31 bug 6): 1 MiB, first data 2.1 s behind
    live, then 6.5 s behind before it caught up 8 s later; 256 KiB, 2.1 s; 48 KiB (no window:
    see above), 0.8 s and 0.7-1.5 s from then on. The window matters since the recording starts
    with the viewer's page (``expect_viewer``): the proxy then holds the live edge when the
    viewer connects, and hands it at once, newest first. With 256 MiB replayed oldest first, a
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
        # Viewers reading this proxy through the appliance (server/http/rerun.py counts them in and
        # out, on the event loop): the run's recording sends only while there is one (LiveRerun).
        self.readers = 0
        self._expected_until = 0.0  # monotonic s: a viewer's page is loading (expect_viewer)
        self._kept_until = 0.0  # monotonic s: a reader is connecting (ensure_running)
        self._expect_met = False  # a reader connected since the last expect_viewer
        self.ended = False  # the run has ended and its recording is flushed (run_ended)
        self.closed = False  # replaced by the next run's proxy, or the appliance stops
        self._life = threading.Lock()  # starting and stopping the process
        self._retire_timer: threading.Timer | None = None
        # The recording's (LiveRerun): wakes its sending thread when a viewer is coming, so it
        # starts now, not at its next round (up to 0.5 s later).
        self.on_viewer: Callable[[], None] | None = None
        self.recording_connected = False  # the run's recording has connected: the window may hold data
        self._sent_at: float | None = None  # monotonic s: the recording's last round (sent); None: never
        self._resumed_at = 0.0  # ...and its first after a pause
        self._set_port(_free_port(0))  # the process starts at the first viewer (ensure_running)

    def _set_port(self, port: int) -> None:
        self.port = port
        self.local_url = f"rerun+http://127.0.0.1:{port}/proxy"  # where the run's recording sends
        self.read_url = f"http://127.0.0.1:{port}"  # where the appliance forwards gRPC-web reads

    def _start(self) -> None:
        """The process, on self.port (another free port if it was taken meanwhile)."""
        self._set_port(_free_port(self.port))
        self._launch(
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

    def running(self) -> bool:
        """Its process is up."""
        return self.proc is not None and self.proc.poll() is None

    def in_use(self) -> bool:
        """Read, or a viewer's page is loading and has not connected yet, or a reader is
        connecting: the process must stay. (Not ``watched``: for the recording, the loading
        window lasts its full EXPECT_VIEWER_S; a viewer that came and went does not keep an
        ended run's process.)"""
        now = time.monotonic()
        return self.readers > 0 or now < self._kept_until or (now < self._expected_until and not self._expect_met)

    def ensure_running(self) -> bool:
        """A reader is about to connect: the process up (started at the first, again if it was
        stopped after the run's end, or died), and kept for a few seconds even before the reader
        is counted.
        Blocking (a start takes up to a second): call it off the event loop. False when this is
        no longer the current proxy or rerun does not start."""
        with self._life:
            self._kept_until = time.monotonic() + CONNECT_GRACE_S
            if self.closed:
                return False
            if not self.running():
                try:
                    self._start()
                except OSError:
                    return False
        if self.ended:
            self._retire_later()
        return True

    def expect_viewer(self) -> None:
        """A live viewer's page was served: its app opens the stream seconds later (1.5-4 s of
        wasm start-up in chromium, more under load). The run's recording starts now (rerun's
        import and connection, ~1 s, and the first batches), so that what the proxy replays when
        the viewer connects is the live edge (issue 31 bug 6). For EXPECT_VIEWER_S: a page that
        never connects costs that much streaming, not more. The process is started first if it
        is not running (``ensure_running``: blocking, off the event loop), so the recording,
        which starts sending now, finds it."""
        self.ensure_running()
        self._expected_until = time.monotonic() + EXPECT_VIEWER_S
        self._expect_met = False
        if self.on_viewer is not None:
            self.on_viewer()

    def sent(self) -> None:
        """The run's recording sent a batch of records (LiveRerun's thread). A run whose loop
        logs nothing (no records) never looks fresh: a viewer reopened then waits the read
        route's LIVE_EDGE_WAIT_S."""
        now = time.monotonic()
        if self._sent_at is None:
            # The recording's first batch: the window holds nothing older to wait out (what it
            # holds was sent since the recording connected, moments ago), so a waiting viewer is
            # connected at once, not RESUMED_S later (issue 31 bug 6: the first viewer of a run).
            self._resumed_at = now - RESUMED_S
        elif now - self._sent_at > STALE_S:
            self._resumed_at = now
        self._sent_at = now

    def fresh(self) -> bool:
        """What the proxy replays to a viewer connecting now starts at the live edge: the recording
        has been sending (it sends only while watched: a viewer reopened after a pause would
        otherwise be handed, newest first, the window from before the pause, seconds or minutes
        old, before the live data; issue 31 bug 6). The read route waits for this. A proxy the
        recording never connected to holds nothing to replay: a reader connects at once and gets
        the first batch as it comes."""
        if not self.recording_connected:
            return True
        if self._sent_at is None:  # connected, its telemetry maybe sent, no records yet
            return False
        now = time.monotonic()
        return now - self._sent_at <= STALE_S and now - self._resumed_at >= RESUMED_S

    def watched(self) -> bool:
        """A viewer reads the stream, or one is loading (expect_viewer): the recording sends."""
        return self.readers > 0 or time.monotonic() < self._expected_until

    def run_ended(self) -> None:
        """The run has ended and its recording is flushed to the proxy (logs/live.py ``finish``):
        from now on the process runs only while in use."""
        self.ended = True
        self._retire()

    def reader_joined(self) -> None:
        """A reader connected (server/http/rerun.py, on the event loop): counted in ``readers``."""
        self.readers += 1
        self._kept_until = 0.0  # counted now: no connecting window needed
        self._expect_met = True  # the page that was loading (if any) has connected
        if self.readers == 1 and self.on_viewer is not None:
            # Watched from now on: the recording's thread, asleep while nobody watched (it looks
            # on no timer), and the host writer's drain wake now, whoever counted the reader in
            # (the read route; a test). One place for it: the read route called it itself.
            self.on_viewer()

    def reader_left(self) -> None:
        """A reader went away (server/http/rerun.py, on the event loop: the stop, if any, happens
        on a thread)."""
        self.readers -= 1
        if self.ended and self.readers == 0:  # now, or when a loading page's window has passed
            threading.Thread(target=self._retire, name="xrf-rerun-retire", daemon=True).start()

    def _retire(self) -> None:
        """Stop the process of an ended run nobody uses; while one is loading or connecting,
        look again when that window has passed."""
        with self._life:
            if self.closed or not self.ended or not self.running():
                return
            if not self.in_use():
                self.stop()
                return
        if self.readers == 0:  # a page loading or a reader connecting: look again after
            self._retire_later()

    def _retire_later(self) -> None:
        """``_retire`` once the loading and connecting windows are over (readers leaving call
        it themselves)."""
        wait = max(self._expected_until, self._kept_until) - time.monotonic()
        with self._life:
            if self._retire_timer is not None:
                self._retire_timer.cancel()
            self._retire_timer = threading.Timer(max(0.0, wait) + 0.05, self._retire)
            self._retire_timer.daemon = True
            self._retire_timer.start()

    def close(self) -> None:
        """For good: the next run's proxy replaces it, or the appliance stops."""
        with self._life:
            self.closed = True
            if self._retire_timer is not None:
                self._retire_timer.cancel()
            self.stop()

    @classmethod
    def open_for_run(cls, run_id: int, owner: str) -> LiveProxy:
        with cls._lock:
            if cls._current is not None:
                cls._current.close()
                cls._current = None
            cls._current = cls(run_id, owner)
            return cls._current

    @classmethod
    def current(cls) -> LiveProxy | None:
        """The last run's proxy: its process may not run (nobody watched yet, or an ended run
        nobody watches) but a reader starts it (``ensure_running``); None before the first run
        and after ``stop_all``."""
        proxy = cls._current
        return None if proxy is None or proxy.closed else proxy

    @classmethod
    def stop_all(cls) -> None:
        with cls._lock:
            if cls._current is not None:
                cls._current.close()
                cls._current = None


@atexit.register  # the appliance's normal exit (SIGTERM under systemd) ends them
def stop_rerun_children() -> None:
    """Stop the live proxy (also called by the app's shutdown)."""
    LiveProxy.stop_all()
