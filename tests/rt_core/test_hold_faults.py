"""The `hold` safe reaction on the youBot-like arm, with real processes: a controller
(tests/fixtures/arm_faults) raises the arm on the simulated board and holds it up; a fault takes
it away (segfault, hang, exit(0) in RUN, a STOPPING that never returns); the safety watcher (the
C thread of rt_core/src/watch.c, as the appliance starts it through server/runs/safety.py) holds
the arm, lowers it to its rest pose and zeroes the outputs.

Measured independently of the watcher's own account, from the plant state it mirrors into the
shared memory: while held, no joint leaves the pose it had at the fault by more than DROP_BOUND;
while lowered, no joint leaves the span from that pose to its rest pose by more than DROP_BOUND
(a joint that "drops" would leave it the way gravity pulls); at the end every pitch joint is on
its rest stop. DROP_BOUND = 2°: 17 mm at the youBot's 0.5 m reach, where `zero` lets the shoulder
fall ~10° in the first second (test_hold.c prints it) and on to its stop; the law's own drop on
this model is ~1° (the gear's friction against its stiffness), so 2° fails a law that sags, not
one that is only slower on a loaded machine (docs/developers/safety.md).

The appliance's own death with the real appliance is tests/server/test_appliance_kill_hold.py's;
here a process plays the appliance, and the record xrf-watch leaves in the run folder is checked
against a link the guest planted at its name."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from xrf_testing.arm import (
    DROP_BOUND,
    FAULT_PARAMS,
    HOLD_S,
    REST,
    assert_held_to_rest,
    build_arm,
    follow,
    inject,
    pose,
    raise_arm,
    watch,
)
from xrflab import plants
from xrflab.channels import lib
from xrflab.server.runs import watch_record


@pytest.fixture(scope="module")
def arm_exe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_arm(tmp_path_factory.mktemp("arm-build"))


@pytest.mark.parametrize("fault", FAULT_PARAMS)
def test_a_fault_leaves_the_arm_at_rest_never_dropped(run_loop, arm_exe, fault) -> None:
    lp = run_loop(arm_exe, XRF_TRANSPORT="sim", XRF_SIM="youbot")
    raise_arm(lp)
    w = watch(lp)
    try:
        held = pose(lp.ch)
        assert held[1] > REST[1] + math.radians(30)  # really up: the shoulder off its stop
        t_fault = inject(lp, fault)
        worst, end = follow(w, lp.ch, held, t_fault)
        r = end["result"]
    finally:
        final = w.stop()
    assert r.reason == ("hang" if fault == "hang" else "exit")
    assert r.hold_phase == 3 and final.rest_ns == r.rest_ns
    assert_held_to_rest(fault, worst, r, end)
    # At rest the outputs are zero and the arm stays (it leans on its stops).
    assert not any(lp.ch.shm.sim.pwm)
    assert lp.proc.wait(timeout=5) is not None


# The appliance's part, in a process of its own that the test kills: it maps the run's segment,
# starts the watcher thread as server/runs/watch.py does, and the per-run xrf-watch process
# beside it (in its own session: not tied to the appliance's life).
HOST = """
import os, subprocess, sys, time
from xrflab.channels import Channels
from xrflab.server.runs.safety import SafetyWatcher
shm, path, loop, plant, exe, out, run_dir, record = sys.argv[1:9]
ch = Channels.open(shm, wait_s=5)
w = SafetyWatcher(int(loop), ch, hang_timeout_ms=60, check_ms=5, force_sim=True, safe_reaction="hold", plant=int(plant))
fd = os.open(path, os.O_RDWR)  # the appliance hands its descriptor of the segment over, as watch.py
folder = os.open(run_dir, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)  # and the run folder's
backup = subprocess.Popen([exe, "--shm-fd", str(fd), "--loop", loop, "--host", str(os.getpid()), "--reaction", "hold",
                           "--plant", "youbot", "--record-dir-fd", str(folder), "--record", record],
                          stdout=open(out, "w"), pass_fds=(fd, folder), start_new_session=True)
while "watching" not in open(out).read():
    time.sleep(0.005)  # polling for the backup's ready line
print(backup.pid, flush=True)
while True:
    time.sleep(3600)  # the appliance idles: the test kills it
"""


def test_the_appliance_killed_leaves_the_arm_at_rest(run_loop, arm_exe, tmp_path) -> None:
    from xrflab.build import ensure_rt_core
    from xrflab.channels import shm_path

    watch_exe = Path(ensure_rt_core(log=lambda line: None)) / "bin" / "xrf-watch"
    # The run folder is the guest's: it planted a link at the record's name, to a file of ours.
    run_dir, victim = tmp_path / "run", tmp_path / "victim"
    run_dir.mkdir()
    victim.write_text("not to be written through\n")
    (run_dir / watch_record.RECORD).symlink_to(victim)
    lp = run_loop(arm_exe, XRF_TRANSPORT="sim", XRF_SIM="youbot")
    raise_arm(lp)
    host = subprocess.Popen(
        [
            sys.executable,
            "-c",
            HOST,
            lp.shm,
            str(shm_path(lp.shm)),
            str(lp.proc.pid),
            str(plants.get("youbot").id),
            str(watch_exe),
            str(tmp_path / "backup.out"),
            str(run_dir),
            watch_record.RECORD,
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    backup_pid = 0
    try:
        backup_pid = int(host.stdout.readline())  # once the host has its backup watching
        held = pose(lp.ch)
        t_fault = time.monotonic()
        host.kill()
        host.wait(timeout=5)
        # The loop is killed by the backup, the arm held and lowered: followed from the segment.
        worst = 0.0
        deadline = time.monotonic() + 30
        while not _gone(backup_pid):
            q = pose(lp.ch)
            t = time.monotonic() - t_fault
            for j, rest in REST.items():
                if t < HOLD_S:
                    worst = max(worst, abs(q[j] - held[j]))
                lo, hi = min(rest, held[j]), max(rest, held[j])
                worst = max(worst, lo - q[j], q[j] - hi)
            assert time.monotonic() < deadline, "the backup watcher never finished"
            time.sleep(0.002)  # sampling the arm's motion, as _follow
    finally:
        if host.poll() is None:
            host.kill()
            host.wait()
        if backup_pid and not _gone(backup_pid):
            os.kill(backup_pid, signal.SIGKILL)
    assert lp.proc.wait(timeout=5) == -signal.SIGKILL  # the backup killed the orphaned loop
    q = pose(lp.ch)
    for j, rest in REST.items():
        assert abs(q[j] - rest) < math.radians(1.0), (j, q)
    assert not any(lp.ch.shm.sim.pwm)
    report = json.loads((tmp_path / "backup.out").read_text().splitlines()[-1])
    assert report["reason"] == lib.XRF_WATCH_HOST_GONE and report["hold_phase"] == 3  # at rest
    assert report["safe_ns"] - report["event_ns"] < 100_000_000
    # Its record replaced the planted link (never written through it), and reads back as it did.
    assert report["record_status"] == 0
    assert victim.read_text() == "not to be written through\n"
    assert not (run_dir / watch_record.RECORD).is_symlink()
    assert [p.name for p in run_dir.iterdir()] == [watch_record.RECORD]  # no temporary file left
    got = watch_record.read(run_dir)
    assert got.outcome is not None and not got.problem, got
    o = got.outcome
    assert o["reason"] == "host_gone" and o["done"] and o["phase"] == "rest" and o["loop_killed"]
    assert o["rest_s"] == pytest.approx((report["rest_ns"] - report["event_ns"]) / 1e9, abs=1e-3)
    assert o["drop_deg"] == pytest.approx(math.degrees(report["drop_urad"] / 1e6), abs=1e-3)
    rest_s = (report["rest_ns"] - report["event_ns"]) / 1e9
    print(f"appliance kill -9: largest drop {math.degrees(worst):.2f}°, at rest {rest_s:.2f} s after")
    assert worst < DROP_BOUND, f"a joint dropped {math.degrees(worst):.2f}°"


def _gone(pid: int) -> bool:
    """The backup watcher (not our child: its parent was the killed host) has exited."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True
