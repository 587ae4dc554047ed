"""The `xrf` command against a shared memory driven by a Python thread playing the loop.

The end-to-end walk against a real controller process lives with the runtime's tests.
"""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from xrf_testing.testloop import LoopSide, create_for_test
from xrflab import channels, cli


class FakeLoop(threading.Thread):
    """Handles commands and publishes telemetry/monitor lines every few milliseconds."""

    def __init__(self, ch: channels.Channels, period_s: float = 0.005) -> None:
        super().__init__(daemon=True)
        self.loop = LoopSide(ch)
        self.period_s = period_s
        self.stopping = threading.Event()
        self.cycle = 0

    def run(self) -> None:
        while not self.stopping.is_set():
            self.cycle += 1
            self.loop.handle_commands()
            self.loop.count_cycle()
            self.loop.publish_telemetry(self.cycle, xeno2ros={"pos_left": self.cycle / 10}, enc=[self.cycle, 0, 0, 0])
            self.loop.publish_monitor(self.cycle, f"cycle {self.cycle}")
            time.sleep(self.period_s)

    def stop(self) -> None:
        self.stopping.set()
        self.join(timeout=5)


@pytest.fixture
def fake_loop(shm_name: str):
    ch = create_for_test(shm_name)
    loop = FakeLoop(ch)
    loop.start()
    yield ch, loop
    loop.stop()
    ch.close()


def xrf(*args: str) -> subprocess.CompletedProcess:
    """`xrf` as a user runs it: a separate process, through the package's entry point."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(Path(cli.__file__).resolve().parents[1]) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.run(
        [sys.executable, "-m", "xrflab.cli", *args], capture_output=True, text=True, timeout=60, env=env
    )


def test_cmd_accepted_and_rejected(fake_loop, shm_name: str) -> None:
    ok = xrf("cmd", "initialise", "--shm", shm_name)
    assert (ok.returncode, ok.stdout.strip()) == (0, "accepted: INITIALISING"), ok.stderr
    bad = xrf("cmd", "start", "--shm", shm_name)
    assert bad.returncode == 3
    assert bad.stdout.strip() == "rejected: start is not allowed in state INITIALISING; allowed: none"
    unknown = xrf("cmd", "7", "--shm", shm_name)
    assert unknown.returncode == 3 and unknown.stdout.startswith("rejected: 7 is not a command")


def test_cmd_usage_and_missing_loop(shm_name: str) -> None:
    nothing = xrf("cmd", "start", "--shm", shm_name, "--timeout", "0.2")
    assert nothing.returncode == 1 and f"cannot reach a loop on shared memory '{shm_name}'" in nothing.stderr
    typo = xrf("cmd", "strat", "--shm", shm_name)
    assert typo.returncode == 1 and "initialise, start, stop" in typo.stderr


def test_state_plain_json_and_wait(fake_loop, shm_name: str) -> None:
    ch, _loop = fake_loop
    assert xrf("state", "--shm", shm_name).stdout.strip() == "IDLE"
    status = json.loads(xrf("state", "--json", "--shm", shm_name).stdout)
    assert status["state_name"] == "IDLE" and status["cycles"] > 0
    threading.Timer(0.3, lambda: ch.send_command("initialise")).start()
    waited = xrf("state", "--wait", "initialising", "--timeout", "5", "--shm", shm_name)
    assert (waited.returncode, waited.stdout.strip()) == (0, "INITIALISING"), waited.stderr
    timeout = xrf("state", "--wait", "RUN", "--timeout", "0.3", "--shm", shm_name)
    assert timeout.returncode == 1 and "waiting for RUN" in timeout.stderr


def test_pub_writes_the_ros2xeno_buffer(shm_name: str) -> None:
    with create_for_test(shm_name) as ch:
        loop = LoopSide(ch)
        done = xrf("pub", "Ros2Xeno", "steer_left=1.5", "steer_right=-2", "--shm", shm_name)
        assert done.returncode == 0, done.stderr
        assert json.loads(done.stdout) == {"steer_left": 1.5, "steer_right": -2.0}
        assert loop.read_ros2xeno() == {"steer_left": 1.5, "steer_right": -2.0}
        wrong = xrf("pub", "Ros2Xeno", "speed=1", "--shm", shm_name)
        assert wrong.returncode == 1 and "valid fields: steer_left, steer_right" in wrong.stderr
        garbled = xrf("pub", "Ros2Xeno", "steer_left", "--shm", shm_name)
        assert garbled.returncode == 1 and "field=value" in garbled.stderr


@pytest.mark.parametrize("topic", ["Xeno2Ros", "sample", "status", "monitor"])
def test_echo_prints_count_json_lines(fake_loop, shm_name: str, topic: str) -> None:
    done = xrf("echo", topic, "--count", "3", "--timeout", "10", "--shm", shm_name)
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    assert len(lines) == 3
    if topic == "Xeno2Ros":
        assert set(lines[0]) == {"cycle", "t_ns", "pos_left", "pos_right"}
        assert lines[1]["cycle"] == lines[0]["cycle"] + 1
        assert lines[0]["pos_left"] == pytest.approx(lines[0]["cycle"] / 10)
    elif topic == "sample":
        assert lines[0]["enc"][0] == lines[0]["cycle"] and len(lines[0]["din"]) == 8
    elif topic == "status":
        assert lines[0]["state_name"] == "IDLE"
    else:
        assert lines[0]["text"] == f"cycle {lines[0]['cycle']}"


def test_echo_is_woken_by_the_doorbell(shm_name: str) -> None:
    """With no publication for a while, echo sleeps in the doorbell wait and wakes on the next."""
    with create_for_test(shm_name) as ch:
        loop = LoopSide(ch)
        threading.Timer(1.0, lambda: loop.publish_monitor(1, "late")).start()
        t0 = time.monotonic()
        done = xrf("echo", "monitor", "--count", "1", "--timeout", "10", "--shm", shm_name)
        assert done.returncode == 0, done.stderr
        assert json.loads(done.stdout)["text"] == "late"
        assert time.monotonic() - t0 < 5


def test_echo_timeout(shm_name: str) -> None:
    with create_for_test(shm_name):
        done = xrf("echo", "monitor", "--count", "1", "--timeout", "0.3", "--shm", shm_name)
        assert done.returncode == 1 and "timed out" in done.stderr


def test_run_sets_the_environment_and_passes_the_exit_code(tmp_path: Path) -> None:
    program = tmp_path / "fake_controller"
    program.write_text(
        textwrap.dedent(
            """\
            #!/bin/sh
            env | grep '^XRF_' | sort
            exit 7
            """
        )
    )
    program.chmod(program.stat().st_mode | stat.S_IXUSR)
    done = xrf(
        "run",
        str(program),
        "--sim",
        "jiwy",
        "--freq",
        "500",
        "--shm",
        "bench1",
        "--max-cycles",
        "10",
        "--faults",
        "dead_encoder:2",
    )
    assert done.returncode == 7
    env = dict(line.split("=", 1) for line in done.stdout.splitlines())
    assert env["XRF_SIM"] == "jiwy" and env["XRF_FREQ"] == "500" and env["XRF_SHM"] == "bench1"
    assert env["XRF_MAX_CYCLES"] == "10" and env["XRF_SIM_FAULTS"] == "dead_encoder:2"
    assert env["XRF_TRANSPORT"] == "sim"
    missing = xrf("run", str(tmp_path / "nope"))
    assert missing.returncode == 1 and "neither a project folder nor an executable" in missing.stderr


def test_run_forwards_one_sigint_then_reports_the_exit_code(tmp_path: Path) -> None:
    """Ctrl-C on `xrf run`: the controller gets SIGINT once and its (safe-stop) exit code comes back."""
    program = tmp_path / "controller.py"
    program.write_text(
        textwrap.dedent(
            f"""\
            #!{sys.executable}
            import signal, sys, time
            count = []
            signal.signal(signal.SIGINT, lambda *a: count.append(1))
            print("ready", flush=True)
            deadline = time.monotonic() + 20
            while not count and time.monotonic() < deadline:
                time.sleep(0.01)
            time.sleep(0.3)  # a second SIGINT would arrive in this window
            print("sigints", len(count), flush=True)
            sys.exit(5)
            """
        )
    )
    program.chmod(0o755)
    env = dict(os.environ)
    env["PYTHONPATH"] = str(Path(cli.__file__).resolve().parents[1])
    proc = subprocess.Popen(
        [sys.executable, "-m", "xrflab.cli", "run", str(program)], stdout=subprocess.PIPE, text=True, env=env
    )
    assert proc.stdout.readline().strip() == "ready"
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 5
    assert out.strip() == "sigints 1"


def test_run_escalates_when_the_controller_ignores_sigint(tmp_path: Path) -> None:
    program = tmp_path / "stubborn.py"
    program.write_text(
        f"#!{sys.executable}\nimport signal, time\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\n"
        "print('ready', flush=True)\ntime.sleep(30)\n"
    )
    program.chmod(0o755)
    env = dict(os.environ)
    env["PYTHONPATH"] = str(Path(cli.__file__).resolve().parents[1])
    proc = subprocess.Popen(
        [sys.executable, "-m", "xrflab.cli", "run", str(program), "--stop-timeout", "0.3"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert proc.stdout.readline().strip() == "ready"
    proc.send_signal(signal.SIGTERM)
    _out, err = proc.communicate(timeout=20)
    assert proc.returncode == 128 + signal.SIGTERM
    assert "sending SIGTERM" in err


def test_parser_has_the_subcommands_and_room_for_more() -> None:
    parser = cli.build_parser()
    help_text = parser.format_help()
    for name in ("cmd", "state", "pub", "echo", "run", "build", "serve"):
        assert name in help_text
    assert "serve" in cli.EXTERNAL_SUBCOMMANDS  # registered by the appliance
