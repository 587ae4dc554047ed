"""kill -9 of the whole appliance during a youBot run (issue 29, safe reaction `hold`), with the
real appliance (`xrf serve` on the simulated bench), the bundled youBot example and the per-run
xrf-watch it starts (docs/developers/safety.md, "When the appliance dies").

The example raises the arm in INITIALISING and holds it up in RUN. The appliance is killed with
SIGKILL; only it: the loop (its launcher is not tied to the appliance) and xrf-watch (a session of
its own) live on. xrf-watch then kills the loop and carries out `hold`: the arm held, lowered at
20 °/s onto its rest stops, zero. Followed from the run's segment, mapped by the test before the
kill (the segment is a memfd: once the appliance is gone nothing else names it): no joint leaves
what the reaction may do by more than 2° (tests/xrf_testing/arm.py's DROP_BOUND), the arm ends on
its stops. xrf-watch's record in the run folder says what it did; the restarted appliance finds
the run still marked running, closes it as `appliance_gone` with that outcome (API, message, the
Runs page in Debian's chromium), and nothing is left: no loop process, no xrf-watch, no /dev/shm
segment. bench/safety/arm.py --appliance N measures the same, N times."""

from __future__ import annotations

import math
import os
import signal
import threading
import time
from pathlib import Path

from xrf_testing.arm import DROP_BOUND, REST, comm, ended, follow_until_ended, pose, raise_example
from xrf_testing.harness import (
    CHROMIUM_ARGS,
    UNCONFINED_UNLESS_ROOT,
    Server,
    session_cookies,
    shared_builds_root,
    start_server,
    stop_server,
    wait_for,
)
from xrf_testing.leaks import descendants
from xrflab.channels import Channels, shm_path
from xrflab.server.runs import watch_record

DEG = math.pi / 180
# From the ready pose J4 travels 142.5° at 20 °/s after 0.5 s of holding: ~7.6 s, and settling.
REST_WITHIN_S = 12.0


def start(data_dir: Path, **settings: object) -> Server:
    """An appliance with the bundled examples (the youBot's among them) on the simulated bench."""
    return start_server(data_dir, shared_builds_root(), allow_unconfined=UNCONFINED_UNLESS_ROOT, **settings)


def test_appliance_kill_9_leaves_the_youbot_arm_at_rest_and_the_restart_says_so(
    tmp_path: Path, chromium_path: str
) -> None:
    s = start(tmp_path)
    restarted = None
    loop_side: set[int] = set()
    watchers: list[int] = []
    ch = None
    try:
        run, ch = raise_example(s)
        held = pose(ch)
        children = descendants(s.proc.pid)
        watchers = [p for p in children if comm(p) == "xrf-watch"]
        assert len(watchers) == 1, f"one xrf-watch per hold run, found {watchers}"
        launcher = next(p for p in children if run["pid"] in descendants(p) and _parent(p) == s.proc.pid)
        loop_side = {launcher} | descendants(launcher)

        t_fault = time.monotonic()
        os.kill(s.proc.pid, signal.SIGKILL)  # the appliance only
        s.proc.wait()
        # Its first record says the outputs are safe while the arm is still being lowered.
        first = wait_for(lambda: watch_record.read(run["run_dir"]).outcome, 5, "xrf-watch's first record")
        assert first["reason"] == "host_gone" and first["loop_killed"] and not first["done"], first
        assert first["rest_s"] is None and first["phase"] in ("hold", "closing"), first
        # The arm is followed meanwhile (a thread: the restart below takes seconds).
        followed: dict[str, object] = {}
        follower = threading.Thread(target=_follow, args=(ch, held, t_fault, watchers[0], followed))
        follower.start()
        # A new appliance on the same data folder and port, while xrf-watch is still lowering the
        # arm, finds the run still "running" in its database and closes it (recover_orphans):
        # once xrf-watch is done (the outcome says "done", at rest), with what it recorded.
        try:
            restarted = start(tmp_path, port=int(s.url.rsplit(":", 1)[1]))
            row = wait_for(
                lambda: (r := restarted.http.get(f"/api/runs/{run['id']}").json())["end_reason"] and r,
                40,
                "the restart to close the orphaned run",
            )
        finally:
            follower.join()
        assert "error" not in followed, followed["error"]
        worst = float(followed["worst"])  # type: ignore[arg-type]
        assert worst < DROP_BOUND, f"a joint dropped {math.degrees(worst):.2f}°"
        q = pose(ch)
        for j, rest in REST.items():
            assert abs(q[j] - rest) < 1.0 * DEG, ("not on its rest stops", j, q)
        assert not any(ch.shm.sim.pwm), "outputs not zero at rest"
        wait_for(lambda: all(ended(p) for p in loop_side), 10, "the loop's processes to end")
        got = watch_record.read(run["run_dir"])  # the record as xrf-watch left it: done, at rest
        assert got.outcome is not None and not got.problem, got
        assert got.outcome["done"] and got.outcome["phase"] == "rest"

        assert row["status"] == "crashed" and row["crashed"] and row["ended"], row
        assert row["end_reason"] == "appliance_gone" and row["crash_reason"] == "appliance", row
        o = row["safe_outcome"]
        assert o["by"] == "xrf-watch" and o["reason"] == "host_gone" and o["done"] and o["loop_killed"], o
        assert o["phase"] == "rest" and o["safe_ms"] < 100, o
        assert 0 <= o["drop_deg"] < math.degrees(DROP_BOUND), o
        assert o["rest_s"] is not None and 1.0 < o["rest_s"] < REST_WITHIN_S, o
        assert abs(o["at"] - (time.time() - (time.monotonic() - t_fault))) < 5, o
        assert "xrf-watch killed the loop" in row["message"] and "at rest" in row["message"], row["message"]
        print(
            f"appliance kill -9 (real appliance): first safe output {o['safe_ms']:.2f} ms, largest drop "
            f"{math.degrees(worst):.2f}° (xrf-watch: {o['drop_deg']:.2f}°), at rest {o['rest_s']:.2f} s after"
        )
        listed = restarted.http.get("/api/logs/runs?limit=5").json()
        mine = next(r for r in listed if r["id"] == run["id"])
        assert not mine["live"] and mine["safe_outcome"] == o
        _runs_page_says_so(restarted, run["id"], chromium_path)
        # Nothing left: no process, no segment once our own mapping goes.
        assert ended(watchers[0]) and all(ended(p) for p in loop_side)
        ch.close()
        ch = None
        assert not shm_path(run["shm"]).exists() and not os.path.lexists(f"/dev/shm/{run['shm']}")
    finally:
        if ch is not None:
            ch.close()
        for p in [*watchers, *loop_side]:
            if not ended(p):
                os.kill(p, signal.SIGKILL)
        for server in (restarted, s):
            if server is not None and server.proc.poll() is None:
                stop_server(server)


def test_a_crashed_youbot_controller_is_held_and_the_run_record_says_how(tmp_path: Path, chromium_path: str) -> None:
    """The loop crashes (SIGSEGV) in RUN with the arm up, the appliance alive: its own watcher holds
    the arm and lowers it, and the run record keeps what it measured (safe_outcome by "watcher":
    the largest joint drop, the time to rest), as after an appliance's death; the Runs page says so."""
    s = start(tmp_path)
    ch = None
    try:
        run, ch = raise_example(s)
        t_fault = time.monotonic()
        os.kill(run["pid"], signal.SIGSEGV)
        row = wait_for(
            lambda: (r := s.http.get(f"/api/runs/{run['id']}").json())["end_reason"] and r,
            REST_WITHIN_S + 10,
            "the run to end once the arm is at rest",
        )
        assert row["status"] == "crashed" and row["end_reason"] == "crash", row
        o = row["safe_outcome"]
        assert o is not None and o["by"] == "watcher" and o["reason"] == "exit" and o["done"], row
        assert o["phase"] == "rest" and 0 <= o["drop_deg"] < math.degrees(DROP_BOUND), o
        assert o["rest_s"] is not None and 1.0 < o["rest_s"] < REST_WITHIN_S, o
        assert abs(o["at"] - (time.time() - (time.monotonic() - t_fault))) < 5, o
        assert "the safety watcher" in row["message"] and "largest joint drop" in row["message"], row["message"]
        q = pose(ch)
        for j, rest in REST.items():
            assert abs(q[j] - rest) < 1.0 * DEG, ("not on its rest stops", j, q)
        _runs_page_says_so(
            s, run["id"], chromium_path, ("The controller failed (exit)", "rest stops", "final phase: rest")
        )
    finally:
        if ch is not None:
            ch.close()
        stop_server(s)


def _follow(ch: Channels, held: list[float], t_fault: float, watcher: int, out: dict[str, object]) -> None:
    """follow_until_ended in a thread: the largest excursion in out["worst"], else out["error"]."""
    try:
        out["worst"] = follow_until_ended(ch, held, t_fault, watcher)
    except AssertionError as exc:
        out["error"] = str(exc)


APPLIANCE_GONE = ("crashed (appliance gone)", "xrf-watch", "killed the loop", "rest stops", "final phase: rest")


def _runs_page_says_so(server: Server, run_id: int, chromium_path: str, says: tuple[str, ...] = APPLIANCE_GONE) -> None:
    """The Runs page (Debian's chromium): the run's row, and its panel saying what the watcher did
    (for an appliance's death: xrf-watch, from the record)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=chromium_path, args=CHROMIUM_ARGS)
        try:
            ctx = b.new_context()
            ctx.add_cookies(session_cookies(server.http, server.url))
            page = ctx.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(server.url + "/#runs")
            row = page.locator(f"#runs-row-{run_id}")
            row.wait_for(timeout=15000)
            assert "crashed" in row.inner_text()
            row.click()
            page.locator("#rl-safe").wait_for(state="visible", timeout=10000)
            text = row.inner_text() + "\n" + page.locator("#rl-safe").inner_text()
            assert all(w in text for w in says), (says, text)
            assert not errors, errors
        finally:
            b.close()


def _parent(pid: int) -> int:
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return 0
