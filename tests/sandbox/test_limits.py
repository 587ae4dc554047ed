"""Resources the kernel bounds (issue 26, holes 5-7 and real-time starvation): a hostile
controller (tests/fixtures/limits_controller over the base template) uploaded, built once and run
through the appliance, each run asked to do one thing (its XRF_MAX_CYCLES says which, see
hostile.cpp): forked children over the memory limit, /dev/shm filled, the run folder filled from
main() before the shared memory exists, a fork bomb, SCHED_FIFO spinners on every CPU it can
reach. Small limits per appliance keep it quick (128 MB, 64 MB of disk, 48 processes).

Each run must end with an alarm naming the limit, the appliance must answer throughout, and
nothing of the run may be left but its kept folder: no cgroup, no mount, no loop device, no image.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from xrf_testing.harness import Server, WsClient, shared_builds_root, start_server, stop_server, wait_for
from xrf_testing.hostile import project_files
from xrf_testing.projects_support import reachable_tmp, targz, upload_and_build
from xrflab.server.runs import cgroups
from xrflab.server.runs import disk as run_disk
from xrflab.server.runs import limits as run_limits

REPO = Path(__file__).resolve().parents[2]
HOSTILE = REPO / "tests" / "fixtures" / "limits_controller"
BASE = REPO / "student_projects" / "templates" / "base"
MEMORY, SHM, DISK, FORK_BOMB, SPIN_HANG, SPIN_CRASH, SPIN_ONLY, DISK_LATER = 1, 2, 3, 4, 5, 6, 7, 8
LIMITS = {"run_memory_mb": 128, "run_disk_mb": 64, "run_files": 4096, "run_pids": 48, "runs_total_mb": 4096}
BOUND_NS = 100_000_000  # outputs safe within 100 ms of the exit (tests/server/test_safety_under_load.py)

pytestmark = [
    pytest.mark.skipif(
        os.geteuid() != 0,
        reason="the kernel's limits need root here (cgroup v1 and loop mounts); a non-root appliance's "
        "missing layers are tested in test_launcher.py",
    ),
    pytest.mark.rt_hog,  # the spinners at real-time priority on the loop's CPU (RLIMIT_RTTIME's cases)
]


def code(mode: int, mb: int = 0) -> int:
    return 1_000_000_000 + mode * 1_000_000 + mb


def archive() -> bytes:
    """The hostile controller: the base template with the fixture's files over it."""
    return targz({**project_files(BASE), **project_files(HOSTILE)}, "limits")


def start(data_dir: Path, **settings: Any) -> Server:
    return start_server(data_dir, shared_builds_root(), **{**LIMITS, **settings})


@pytest.fixture(scope="module")
def server(data_dir: Path) -> Iterator[Server]:
    s = start(data_dir)
    yield s
    stop_server(s)


@pytest.fixture(scope="module")
def hostile(server: Server) -> tuple[httpx.Client, int, int]:
    """mallory, holding the bench, with the hostile controller built: (client, project, build)."""
    http, _ = server.login("mallory", server.create_user("mallory"))
    pid, bid = upload_and_build(http, archive(), "limits.tar.gz")
    assert http.post("/api/lease/take").status_code == 200
    return http, pid, bid


def run_hostile(server: Server, hostile: tuple[httpx.Client, int, int], mode: int, mb: int = 0) -> dict[str, Any]:
    http, pid, bid = hostile
    server.stop_run()
    r = http.post(f"/api/projects/{pid}/builds/{bid}/run", json={"max_cycles": code(mode, mb)}, timeout=60)
    assert r.status_code == 201, r.text
    return r.json()["run"]


def ended(server: Server, run_id: int, timeout: float = 30) -> dict[str, Any]:
    """The run's final record, once its file system and cgroup were let go of (run_end.record
    does that after storing the record)."""

    def final() -> dict[str, Any] | None:
        r = server.http.get(f"/api/runs/{run_id}").json()
        return r if r["status"] in ("ended", "crashed", "failed") else None

    row = wait_for(final, timeout, f"run {run_id} to end")
    wait_for(
        lambda: not cgroup_left(server, run_id) and not run_disk.is_mounted(server.data_dir / "runs" / str(run_id)),
        10,
        "the run's cgroup and file system to be let go of",
    )
    return row


def cgroup_left(server: Server, run_id: int) -> list[str]:
    name = f"{cgroups.PREFIX}{run_limits.tag(server.data_dir)}-{run_id}"
    return [str(p.base / name) for p in cgroups.find().values() if (p.base / name).exists()]


def wait_alarm(server: Server, ws: WsClient, kind: str, run_id: int, timeout: float = 30) -> dict[str, Any]:
    """The alarm of `kind` for the run; failing, what was seen instead."""
    try:
        return ws.wait_type("alarm", timeout, kind=kind, run_id=run_id)
    except AssertionError:
        seen = [m for m in ws.messages if m.get("type") in ("alarm", "run")]
        row = server.http.get(f"/api/runs/{run_id}").json()
        raise AssertionError(f"no {kind} alarm for run {run_id}: seen {seen}; record {row}") from None


def output(server: Server, run_id: int) -> str:
    path = server.data_dir / "runs" / str(run_id) / "output.txt"
    return path.read_text(errors="replace") if path.is_file() else ""


def assert_nothing_left(server: Server, run_id: int) -> None:
    """The run's cgroup, mount, loop device and image are gone; its folder is an ordinary one."""
    run_dir = server.data_dir / "runs" / str(run_id)
    assert not cgroup_left(server, run_id)
    assert not run_disk.is_mounted(run_dir), f"{run_dir} still mounted"
    assert not run_disk.image_for(server.data_dir, run_id).exists()
    # The loop device frees itself once the last reference to the file system is gone: a reader
    # of the appliance finishing, and any process that made a mount namespace while the run's
    # file system was mounted (a build, another appliance's run on this shared machine): their
    # namespace holds a copy until they exit. None may be of this appliance.
    deadline = time.monotonic() + 5
    while (held := holders(server.data_dir)) and time.monotonic() < deadline:
        time.sleep(0.05)
    ours = [h for h in held if str(server.data_dir) in h or f"XRF_RUN_DIR={server.data_dir}" in h]
    assert not ours, f"the run's file system is still held by: {ours}"


def holders(data_dir: Path) -> list[str]:
    """Processes whose mount namespace still has a run file system of `data_dir` (debugging)."""
    devices = {d for d, f in run_disk._backing_files().items() if str(data_dir) in f}
    out = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            info = Path(f"/proc/{pid}/mountinfo").read_text()
            comm = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()[:300]
        except OSError:
            continue
        if any(f" {d} " in info for d in devices):
            with contextlib.suppress(OSError):
                comm += " " + Path(f"/proc/{pid}/environ").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            out.append(f"{pid} {comm}")
    return out


def assert_answers(server: Server) -> None:
    t = time.monotonic()
    assert server.http.get("/api/health").status_code == 200
    # Answers at all, promptly: a generous bound (the suite shares its CPUs); how fast the appliance
    # answers under a hostile run is the benchmarks' to measure, not a test's.
    assert time.monotonic() - t < 10.0


def test_a_run_folder_of_its_own_is_not_walked(tmp_path: Path) -> None:
    """The limits guard walks a run folder (in a worker thread, every 2 s) only where it has no
    file system of its own; where the kernel bounds it, no walk is started at all (it used to be
    started and to return at once: two threads woken for nothing, issue 30 item 4)."""
    assert run_limits.RunLimits(tmp_path).walks_disk
    assert run_limits.RunLimits(tmp_path, disk=run_limits.RunDisk(tmp_path)).walks_disk  # a probe's answer only
    bounded = run_limits.RunLimits(tmp_path, disk=run_limits.RunDisk(tmp_path, image=tmp_path / "image"))
    assert not bounded.walks_disk and bounded.watched_disk_over() is None
    assert not run_limits.RunLimits(tmp_path, disk=run_limits.RunDisk(tmp_path, helper="/run/helper")).walks_disk


def test_forked_children_over_the_memory_limit(server: Server, hostile: Any) -> None:
    """Hole 5: four children of 100 MB each, 128 MB for the run: the kernel kills, the run ends
    with `memory`, the appliance is untouched."""
    with server.ws() as ws:
        run = run_hostile(server, hostile, MEMORY, 100)
        alarm = wait_alarm(server, ws, "memory", run["id"])
    assert "memory limit (128 MB" in alarm["message"], alarm
    row = ended(server, run["id"])
    assert row["end_reason"] == "memory", row
    assert "memory child 3" in output(server, run["id"])
    assert_answers(server)
    assert_nothing_left(server, run["id"])


def test_dev_shm_filled(server: Server, hostile: Any) -> None:
    """Hole 6: its /dev/shm (a folder of the host's tmpfs) counts as the run's memory."""
    with server.ws() as ws:
        run = run_hostile(server, hostile, SHM, 400)
        wait_alarm(server, ws, "memory", run["id"])
    row = ended(server, run["id"])
    assert row["end_reason"] == "memory", row
    assert not (Path("/dev/shm") / row["shm"].split("/")[0]).exists()
    assert_answers(server)
    assert_nothing_left(server, run["id"])


def test_disk_filled_from_main_before_the_shared_memory(server: Server, hostile: Any) -> None:
    """Hole 7: 200 MB of files written by main() before the loop (and its shared memory) starts,
    64 MB allowed: the kernel stops the writes at the limit from the first byte, the run ends
    with `disk`, and what it wrote up to the limit is kept in an ordinary run folder."""
    with server.ws() as ws:
        run = run_hostile(server, hostile, DISK, 200)
        alarm = wait_alarm(server, ws, "disk", run["id"])
    assert "run folder is full" in alarm["message"], alarm
    row = ended(server, run["id"])
    assert row["end_reason"] == "disk", row
    text = output(server, run["id"])
    wrote = int(text.split("LIMITS disk wrote ", 1)[1].split(" MB", 1)[0])
    assert 40 <= wrote <= 64 and "No space left on device" in text, text
    assert_nothing_left(server, run["id"])
    run_dir = server.data_dir / "runs" / str(run["id"])
    kept = sorted(p.name for p in run_dir.glob("fill*.bin"))
    assert wrote <= len(kept) <= wrote + 1, kept  # and the one the kernel cut short
    assert run_disk.kept_bytes(run_dir) <= 64 << 20
    assert server.http.get(f"/api/logs/runs/{run['id']}").status_code == 200  # the run's files, listed
    assert_answers(server)


def test_the_log_stays_whole_when_the_controller_fills_its_folder(server: Server, hostile: Any) -> None:
    """The appliance writes into the run folder too (the host log writer): when the controller
    has filled its share, the appliance's reserve (ext4's reserved blocks) still takes the log,
    so the run's log is whole up to its end, and the run stops with `disk`. The controller
    ignores SIGINT and SIGTERM once it fills its folder, so it logs on for 4 s until SIGKILL
    (without the reserve: "No space left on device" after ~4300 records, ~2800 lost)."""
    with server.ws() as ws:
        run = run_hostile(server, hostile, DISK_LATER, 200)
        assert ws.command("initialise")["accepted"]
        ws.wait_state("INITIALISED")
        assert ws.command("start")["accepted"]
        ws.wait_state("RUN")  # logging every cycle (the template's logger)
        wait_alarm(server, ws, "disk", run["id"])
    row = ended(server, run["id"])
    assert row["end_reason"] == "disk" and row["log_note"] == "", row  # logging never failed
    assert row["log_records"] > 1000 and row["log_lost"] == 0, row
    logs = server.http.get(f"/api/logs/runs/{run['id']}").json()
    assert sum(f["records"] for f in logs["files"] if f["kind"] == "xrflog") == row["log_records"], logs
    assert "LIMITS disk wrote" in output(server, run["id"])
    assert_nothing_left(server, run["id"])


def test_fork_bomb(server: Server, hostile: Any) -> None:
    with server.ws() as ws:
        run = run_hostile(server, hostile, FORK_BOMB)
        wait_alarm(server, ws, "pids", run["id"])
    row = ended(server, run["id"])
    assert row["end_reason"] == "pids", row
    n = int(output(server, run["id"]).split("fork bomb: ", 1)[1].split(" ", 1)[0])
    assert n < LIMITS["run_pids"], n
    assert_answers(server)
    assert_nothing_left(server, run["id"])


class Pinger:
    """Asks the appliance for /api/health every 50 ms while the spinners run: the slowest answer."""

    def __init__(self, server: Server) -> None:
        self.url = server.url
        self.worst = 0.0
        self.count = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        with httpx.Client(base_url=self.url, timeout=10) as c:
            while not self.stop.is_set():
                t = time.monotonic()
                c.get("/api/health")
                self.worst = max(self.worst, time.monotonic() - t)
                self.count += 1
                time.sleep(0.05)

    def __enter__(self) -> Pinger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join()


def spinners_then(server: Server, hostile: Any, mode: int, kind: str) -> dict[str, Any]:
    """SCHED_FIFO spinners on every CPU the controller can reach, then its loop hangs (starved)
    or it crashes: the outputs are safe within the usual bound, the appliance answers."""
    with server.ws() as ws, Pinger(server) as pinger:
        run = run_hostile(server, hostile, mode)
        alarm = wait_alarm(server, ws, kind, run["id"])
        ended(server, run["id"])
    text = output(server, run["id"])
    assert "LIMITS spinners on 1 CPU(s)" in text, text  # the run's cpuset: the loop's CPU only
    assert "LIMITS spinning on CPU" in text, text
    assert alarm["safe_ns"] - alarm["event_ns"] < BOUND_NS, alarm
    assert alarm["watcher_rt"], alarm
    assert pinger.count > 5 and pinger.worst < 1.0, (pinger.count, pinger.worst)
    assert_nothing_left(server, run["id"])
    return alarm


def test_spinners_starve_the_loop_the_watcher_is_not_starved(server: Server, hostile: Any) -> None:
    alarm = spinners_then(server, hostile, SPIN_HANG, "hang")
    # Seen within the hang timeout (200 ms) and a check period of the last beat.
    assert alarm["event_ns"] - alarm["heartbeat_ns"] < 200_000_000 + BOUND_NS, alarm


def test_spinners_then_a_crash(server: Server, hostile: Any) -> None:
    alarm = spinners_then(server, hostile, SPIN_CRASH, "crash")
    assert alarm["exit_signal"] == signal.SIGSEGV, alarm


def test_a_real_time_thread_that_never_blocks_is_stopped(hostile: Any) -> None:
    """RLIMIT_RTTIME: spinners alone (no loop to starve, a hang timeout far away): after 300 ms of
    real-time CPU without blocking the kernel sends SIGXCPU; the run ends with `cpu`."""
    d = reachable_tmp("limits-cpu")
    s = start(d, rt_time_ms=300, hang_timeout_ms=5000)
    try:
        http, _ = s.login("mallory", s.create_user("mallory"))
        # The build belongs to the other appliance: upload and build here too (same sources: quick).
        pid, bid = upload_and_build(http, archive(), "limits.tar.gz")
        assert http.post("/api/lease/take").status_code == 200
        with s.ws() as ws, Pinger(s) as pinger:
            run = run_hostile(s, (http, pid, bid), SPIN_ONLY)
            alarm = wait_alarm(s, ws, "cpu", run["id"])
            row = ended(s, run["id"])
        assert row["end_reason"] == "cpu" and row["exit_signal"] == signal.SIGXCPU, row
        # The run's record names the limit; the alarm may carry an earlier symptom when the
        # spinner kept the loop from opening its segment first (seen under a loaded CI run).
        assert "RLIMIT_RTTIME" in row["message"] or "RLIMIT_RTTIME" in alarm["message"], (row, alarm)
        assert pinger.worst < 5.0, pinger.worst
        assert_nothing_left(s, run["id"])
    finally:
        stop_server(s)
        import shutil

        shutil.rmtree(d, ignore_errors=True)


def _parent_of(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def _live(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_a_killed_appliance_leaves_nothing_after_its_restart(hostile: Any) -> None:
    """kill -9 of the appliance mid-run: the run's cgroup and file system stay (the loop runs on,
    by design) until the restarted appliance closes the run: then its files are kept in an
    ordinary folder and nothing else is left. And a run file system whose mount was lost (a
    reboot) is mounted again from its image, kept, removed."""
    d = reachable_tmp("limits-kill")
    s = start(d)
    restarted = None
    try:
        password = s.create_user("mallory")
        http, _ = s.login("mallory", password)
        pid, bid = upload_and_build(http, archive(), "limits.tar.gz")
        assert http.post("/api/lease/take").status_code == 200
        first = run_hostile(s, (http, pid, bid), DISK, 5)  # 5 MB written, then an ordinary loop
        # a bound on failure, not a delay: a guest's 5 MB on its own file system took over 20 s
        # once in a parallel CI run (two workers, each with an appliance and a build)
        wait_for(lambda: "LIMITS disk wrote 5 MB" in output(s, first["id"]), 60, "the first run's files")
        os.kill(s.proc.pid, signal.SIGKILL)
        s.proc.wait()
        run_dir = d / "runs" / str(first["id"])
        assert run_disk.is_mounted(run_dir) and cgroup_left(s, first["id"])  # still the run's, live

        restarted = start(d, port=int(s.url.rsplit(":", 1)[1]))
        row = wait_for(
            lambda: (
                (r := restarted.http.get(f"/api/runs/{first['id']}").json())["end_reason"] == "appliance_restart" and r
            ),
            20,
            "the orphaned run to be closed",
        )
        wait_for(lambda: not run_disk.is_mounted(run_dir) and not cgroup_left(restarted, first["id"]), 10, "clean-up")
        assert_nothing_left(restarted, first["id"])
        assert len(list(run_dir.glob("fill*.bin"))) == 5 and "LIMITS disk wrote 5 MB" in output(restarted, first["id"])
        assert row["status"] == "crashed"

        # A reboot: the run and its mount are gone, its image is not.
        http2, _ = restarted.login("mallory", password)
        assert http2.post("/api/lease/take").status_code == 200
        second = run_hostile(restarted, (http2, pid, bid), DISK, 3)
        # (the same bound as the first run's: CI, session 13, 3 MB took over 20 s beside a practical replay)
        wait_for(lambda: "LIMITS disk wrote 3 MB" in output(restarted, second["id"]), 60, "the second run's files")
        launcher = _parent_of(_parent_of(second["pid"]))
        os.kill(restarted.proc.pid, signal.SIGKILL)
        restarted.proc.wait()
        os.kill(launcher, signal.SIGKILL)  # the controller and its namespace go with it
        wait_for(lambda: not _live(second["pid"]), 10, "the run to end")
        run_dir = d / "runs" / str(second["id"])
        import subprocess

        subprocess.run(["umount", "--lazy", str(run_dir)], check=True)
        assert run_disk.image_for(d, second["id"]).exists() and not run_disk.is_mounted(run_dir)
        restarted = start(d, port=int(s.url.rsplit(":", 1)[1]))
        wait_for(lambda: not run_disk.image_for(d, second["id"]).exists(), 20, "the image to be kept and removed")
        assert len(list(run_dir.glob("fill*.bin"))) == 3
        wait_for(lambda: not cgroup_left(restarted, second["id"]), 10, "the run cgroup to be removed")
        assert_nothing_left(restarted, second["id"])
    finally:
        for server in (restarted, s):
            if server is not None and server.proc.poll() is None:
                stop_server(server)
        import shutil

        shutil.rmtree(d, ignore_errors=True)


def test_without_a_file_system_of_its_own_the_folder_is_watched(tmp_path: Path) -> None:
    """Where the `disk` layer is missing (a non-root appliance without the helper, allowed by an
    educator), the run folder's size is still watched (every 2 s by the limits guard), as before."""
    lim = run_limits.RunLimits(tmp_path, disk_mb=1)
    assert lim.watched_disk_over() is None
    (tmp_path / "deep" / "er").mkdir(parents=True)
    (tmp_path / "deep" / "er" / "big").write_bytes(b"x" * (2 << 20))
    over = lim.watched_disk_over()
    assert over is not None and over[0] == "disk" and "watched" in over[1], over
