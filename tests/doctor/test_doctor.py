"""xrf doctor: every check against prepared /proc, /sys, /dev and /etc trees (tmp dirs) and
faked commands (vcgencmd, timedatectl) for its ok, warning and failure cases."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from xrflab import doctor
from xrflab.doctor import FAILURE, OK, SKIPPED, WARNING, ConfinementProbe, Context, InitProbe
from xrflab.server.runs.guest_spawn import GuestReport

NOW = 1_790_000_000.0  # 2026


def write(root: Path, rel: str, text: str, mode: int | None = None) -> Path:
    p = root / rel.lstrip("/")
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(text)
    if mode is not None:
        os.chmod(p, mode)
    return p


def fake_runner(outputs: dict[str, tuple[int, str]]):
    calls = []

    def run(cmd):
        calls.append(cmd)
        return outputs.get(cmd[0], (127, f"{cmd[0]}: not found"))

    run.calls = calls
    return run


def ctx(root: Path, runner=None, **kw) -> Context:
    kw.setdefault("now", lambda: NOW)
    return Context(root=root, runner=runner or fake_runner({}), **kw)


def pi(root: Path) -> Path:
    write(root, "/proc/device-tree/model", "Raspberry Pi 4 Model B Rev 1.5\0")
    return root


def evl_core(root: Path, abi: int = 36) -> Path:
    (root / "dev/evl/clock").mkdir(parents=True, exist_ok=True)
    write(root, "/dev/evl/control", "")
    write(root, "/sys/devices/virtual/evl/control/abi", f"{abi}\n")
    return root


def libevl(root: Path, prereq: int | None = 36, level: int | None = 36) -> Path:
    write(root, "/usr/evl/include/evl/evl.h", "#include <evl/version.h>\n")
    if prereq is not None:
        write(root, "/usr/evl/include/evl/version.h", f"#define EVL_ABI_PREREQ  {prereq}\n")
    if level is not None:
        write(root, "/usr/evl/include/uapi/evl/control.h", f"#define EVL_ABI_BASE 30\n#define EVL_ABI_LEVEL  {level}\n")
    return root


# ---------------------------------------------------------------------------------------- evl


def test_evl_ok(tmp_path):
    r = doctor.check_evl(ctx(libevl(evl_core(pi(tmp_path)))))
    assert r.status == OK and "ABI 36" in r.detail


def test_evl_missing_is_failure_on_a_pi_warning_elsewhere(tmp_path):
    write(tmp_path, "/proc/sys/kernel/osrelease", "6.8.0-1010-raspi\n")
    laptop = doctor.check_evl(ctx(tmp_path))
    assert laptop.status == WARNING and "no EVL core" in laptop.detail
    r = doctor.check_evl(ctx(pi(tmp_path)))
    assert r.status == FAILURE and "6.8.0-1010-raspi" in r.detail
    assert "evl-kernel.md" in r.fix


def test_evl_abi_mismatch_and_too_old(tmp_path):
    evl_core(pi(tmp_path), abi=37)
    libevl(tmp_path, prereq=36, level=36)
    r = doctor.check_evl(ctx(tmp_path))
    assert r.status == WARNING and "kernel EVL ABI 37" in r.detail and "built against ABI 36" in r.detail
    write(tmp_path, "/sys/devices/virtual/evl/control/abi", "35\n")
    r = doctor.check_evl(ctx(tmp_path))
    assert r.status == FAILURE and "ENOEXEC" in r.detail and "libevl" in r.fix


def test_evl_without_libevl_warns(tmp_path):
    r = doctor.check_evl(ctx(evl_core(pi(tmp_path))))
    assert r.status == WARNING and "/usr/evl" in r.detail


def test_evl_control_device_missing_fails(tmp_path):
    write(tmp_path, "/sys/devices/virtual/evl/control/abi", "36\n")
    r = doctor.check_evl(ctx(libevl(pi(tmp_path))))
    assert r.status == FAILURE and "/dev/evl/control" in r.detail


# ---------------------------------------------------------------------------------- isolcpus

CMD = "console=serial0,115200 root=LABEL=writable rootwait"


def test_isolation_ok(tmp_path):
    evl_core(tmp_path)
    write(tmp_path, "/proc/cmdline", f"{CMD} isolcpus=3 evl.oobcpus=3\n")
    write(tmp_path, "/sys/devices/system/cpu/isolated", "3\n")
    r = doctor.check_isolation(ctx(tmp_path))
    assert r.status == OK and "XRF_CPU=3" in r.detail


def test_isolation_flags_and_ranges(tmp_path):
    evl_core(tmp_path)
    write(tmp_path, "/proc/cmdline", f"{CMD} isolcpus=domain,managed_irq,2-3 evl.oobcpus=2,3\n")
    write(tmp_path, "/sys/devices/system/cpu/isolated", "2-3\n")
    assert doctor.check_isolation(ctx(tmp_path)).status == OK


def test_isolation_missing_fails_on_evl(tmp_path):
    evl_core(tmp_path)
    write(tmp_path, "/proc/cmdline", CMD + "\n")
    r = doctor.check_isolation(ctx(tmp_path))
    assert r.status == FAILURE and "isolcpus=3 evl.oobcpus=3" in r.fix
    write(tmp_path, "/proc/cmdline", f"{CMD} isolcpus=3\n")
    assert doctor.check_isolation(ctx(tmp_path)).status == FAILURE
    write(tmp_path, "/proc/cmdline", f"{CMD} isolcpus=3 evl.oob_cpus=3\n")
    r = doctor.check_isolation(ctx(tmp_path))
    assert r.status == FAILURE and "stale" in r.detail


def test_isolation_mismatch_warns(tmp_path):
    evl_core(tmp_path)
    write(tmp_path, "/proc/cmdline", f"{CMD} isolcpus=3 evl.oobcpus=2\n")
    r = doctor.check_isolation(ctx(tmp_path))
    assert r.status == WARNING and "different CPUs" in r.detail
    write(tmp_path, "/proc/cmdline", f"{CMD} isolcpus=3 evl.oobcpus=3\n")
    write(tmp_path, "/sys/devices/system/cpu/isolated", "\n")
    r = doctor.check_isolation(ctx(tmp_path))
    assert r.status == WARNING and "kernel reports" in r.detail


def test_isolation_without_evl_is_a_warning(tmp_path):
    write(tmp_path, "/proc/cmdline", CMD + "\n")
    assert doctor.check_isolation(ctx(tmp_path)).status == WARNING


# ---------------------------------------------------------------------------------- governor


def governors(root: Path, *govs: str) -> None:
    for i, g in enumerate(govs):
        write(root, f"/sys/devices/system/cpu/cpu{i}/cpufreq/scaling_governor", g + "\n")


def test_governor_ok_warning_failure(tmp_path):
    r = doctor.check_governor(ctx(tmp_path))
    assert r.status == WARNING and "no cpufreq" in r.detail
    governors(tmp_path, "performance", "performance", "performance", "performance")
    assert doctor.check_governor(ctx(tmp_path)).status == OK
    governors(tmp_path, "performance", "ondemand", "performance", "schedutil")
    r = doctor.check_governor(ctx(tmp_path))
    assert r.status == FAILURE and "cpu1=ondemand" in r.detail and "cpu3=schedutil" in r.detail
    assert "xrf-cpufreq.service" in r.fix


# -------------------------------------------------------------------------------- throttling


@pytest.mark.parametrize(
    "value,status,words",
    [
        ("0x0", OK, "no under-voltage"),
        ("0x50000", WARNING, "since boot: under-voltage, throttled"),
        ("0x80000", WARNING, "since boot: soft temperature limit"),
        ("0x50005", FAILURE, "now: under-voltage, throttled"),
        ("0x2", FAILURE, "now: ARM frequency capped"),
    ],
)
def test_throttling_from_vcgencmd(tmp_path, value, status, words):
    run = fake_runner({"vcgencmd": (0, f"throttled={value}\n")})
    r = doctor.check_throttling(ctx(pi(tmp_path), run))
    assert r.status == status and words in r.detail, r
    assert run.calls == [["vcgencmd", "get_throttled"]]
    if status != OK:
        assert "supply" in r.fix


def test_throttling_from_sysfs_when_vcgencmd_missing(tmp_path):
    write(pi(tmp_path), "/sys/devices/platform/soc/soc:firmware/get_throttled", "50000\n")
    r = doctor.check_throttling(ctx(tmp_path))
    assert r.status == WARNING and "get_throttled" in r.detail


def test_throttling_unknown(tmp_path):
    assert doctor.check_throttling(ctx(tmp_path)).status == SKIPPED  # not a Pi
    r = doctor.check_throttling(ctx(pi(tmp_path)))
    assert r.status == WARNING and "vcgencmd" in r.fix


# --------------------------------------------------------------------------------------- spi


def users(root: Path, spi_members: str = "xrf-loop,xrf") -> None:
    write(
        root,
        "/etc/passwd",
        "root:x:0:0:root:/root:/bin/bash\n"
        "xrf:x:998:998::/var/lib/xrf-lab:/usr/sbin/nologin\n"
        "xrf-loop:x:997:997::/nonexistent:/usr/sbin/nologin\n",
    )
    gid = os.stat(root).st_gid  # the gid the prepared files get
    # spi first: the prepared device file's gid (0 when the tests run as root) is spi's
    write(root, "/etc/group", f"spi:x:{gid}:{spi_members}\nroot:x:0:\nxrf:x:998:\nxrf-loop:x:997:xrf\n")


def test_spi_ok_when_loop_user_in_the_group(tmp_path):
    users(pi(tmp_path))
    write(tmp_path, "/dev/spidev0.0", "", 0o660)
    r = doctor.check_spi(ctx(tmp_path))
    assert r.status == OK and "xrf-loop" in r.detail and "spi 660" in r.detail


def test_spi_not_accessible_fails(tmp_path):
    users(pi(tmp_path), spi_members="")
    write(tmp_path, "/dev/spidev0.0", "", 0o660)
    r = doctor.check_spi(ctx(tmp_path))
    assert r.status == FAILURE and "not read/writable by xrf-loop" in r.detail
    assert "udevadm trigger" in r.fix
    users(tmp_path)
    os.chmod(tmp_path / "dev/spidev0.0", 0o600)
    assert doctor.check_spi(ctx(tmp_path)).status == FAILURE


def test_spi_lists_every_board_and_names_the_missing_one(tmp_path):
    """A bench of three ico boards: one device per board ($XRF_SPI_DEVICES); each is checked."""
    users(pi(tmp_path))
    devices = ("/dev/spidev0.0", "/dev/spidev0.1", "/dev/spidev1.0")
    for dev in devices[:2]:
        write(tmp_path, dev, "", 0o660)
    r = doctor.check_spi(ctx(tmp_path, spi_devices=devices))
    assert r.status == FAILURE and r.detail == "board 3: /dev/spidev1.0 does not exist"
    assert "chip select" in r.fix and r.title == "SPI devices " + ", ".join(devices)
    write(tmp_path, devices[2], "", 0o660)
    r = doctor.check_spi(ctx(tmp_path, spi_devices=devices))
    assert r.status == OK
    assert r.detail.startswith("board 1: /dev/spidev0.0, board 2: /dev/spidev0.1, board 3: /dev/spidev1.0 present")


def test_spi_missing(tmp_path):
    r = doctor.check_spi(ctx(pi(tmp_path)))
    assert r.status == FAILURE and "dtparam=spi=on" in r.fix
    laptop = tmp_path / "laptop"
    laptop.mkdir()
    assert doctor.check_spi(ctx(laptop)).status == WARNING


# -------------------------------------------------------------------------------------- fpga


def spi_ready(root: Path) -> Path:
    users(pi(root))
    write(root, "/dev/spidev0.0", "", 0o660)
    return root


@pytest.mark.parametrize(
    "probe,status",
    [
        (InitProbe(OK, "init: the board answered INIT"), OK),
        (InitProbe(WARNING, "init: answered after a retry"), WARNING),
        (InitProbe(FAILURE, "init: no answer to INIT"), FAILURE),
    ],
)
def test_fpga_init(tmp_path, probe, status):
    r = doctor.check_fpga(ctx(spi_ready(tmp_path), init_probe=lambda c: probe))
    assert r.status == status and r.detail == probe.detail
    assert (r.fix == "") == (status == OK)


def test_fpga_not_checked_without_spi_or_live(tmp_path):
    called = []
    r = doctor.check_fpga(ctx(pi(tmp_path), init_probe=lambda c: called.append(1)))
    assert r.status == SKIPPED and "not checked" in r.detail and not called
    r = doctor.check_fpga(ctx(spi_ready(tmp_path), live=False, init_probe=lambda c: called.append(1)))
    assert r.status == SKIPPED and not called


def test_fpga_probe_without_selfcheck_tool_is_not_checked(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    p = doctor.probe_fpga_init(ctx(spi_ready(tmp_path)))
    assert p.status == SKIPPED and "xrf-selfcheck not found" in p.detail


@pytest.mark.live  # probe_fpga_init starts the (stand-in) xrf-selfcheck tool
def test_fpga_probe_stops_after_init(tmp_path):
    """The real probe against a stand-in xrf-selfcheck that would go on to the motor steps."""
    root = spi_ready(tmp_path)
    tool = write(
        root,
        "/var/cache/xrf-lab/rt_core/abc/bin/xrf-selfcheck",
        f"""#!{sys.executable}
import json, sys, time, signal, pathlib
signal.signal(signal.SIGTERM, lambda *a: (pathlib.Path({str(tmp_path / "terminated")!r}).write_text('y'), sys.exit(2)))
print(json.dumps({{"event": "start"}}), flush=True)
print(json.dumps({{"event": "step", "id": "spi", "status": "pass", "title": "SPI", "text": "opened"}}), flush=True)
print(json.dumps({{"event": "step", "id": "init", "status": "pass", "title": "INIT", "text": "board answered INIT"}}), flush=True)
time.sleep(30)
print(json.dumps({{"event": "step", "id": "motor.1", "status": "pass"}}), flush=True)
""",
        0o755,
    )
    assert tool.exists()
    p = doctor.probe_fpga_init(ctx(root))
    assert p.status == OK and "board answered INIT" in p.detail
    assert (tmp_path / "terminated").exists()


# ------------------------------------------------------------------------------------- clock


def test_clock_ok_warning_failure(tmp_path):
    r = doctor.check_clock(ctx(tmp_path, fake_runner({"timedatectl": (0, "yes\n")})))
    assert r.status == OK
    write(tmp_path / "b", "/run/systemd/timesync/synchronized", "")
    assert doctor.check_clock(ctx(tmp_path / "b")).status == OK
    r = doctor.check_clock(ctx(tmp_path, fake_runner({"timedatectl": (0, "no\n")})))
    assert r.status == WARNING and "timedatectl says no" in r.detail and "set-ntp true" in r.fix
    r = doctor.check_clock(ctx(tmp_path, fake_runner({"timedatectl": (0, "no\n")}), now=lambda: 86400.0 * 365))
    assert r.status == FAILURE and "1971" in r.detail


# -------------------------------------------------------------------------------------- disk


@pytest.mark.parametrize("free,status", [(50 * 10**9, OK), (1 * 10**9, WARNING), (100 * 10**6, FAILURE)])
def test_disk(tmp_path, free, status):
    seen = []

    def usage(p):
        seen.append(p)
        return (10**12, 10**12 - free, free)

    (tmp_path / "var/lib").mkdir(parents=True)
    r = doctor.check_disk(ctx(tmp_path, disk_usage=usage))
    assert r.status == status
    assert seen == [tmp_path / "var/lib"]  # nearest existing folder of the data dir


# -------------------------------------------------------------------------------------- ros2


def test_ros2(tmp_path):
    r = doctor.check_ros2(ctx(tmp_path, find_module=lambda n: True))
    assert r.status == OK
    write(tmp_path, "/opt/ros/jazzy/setup.bash", "")
    r = doctor.check_ros2(ctx(tmp_path, find_module=lambda n: True))
    assert r.status == OK and "jazzy" in r.detail
    r = doctor.check_ros2(ctx(tmp_path, find_module=lambda n: False))
    assert r.status == WARNING and "/opt/ros/jazzy/setup.bash" in r.fix
    r = doctor.check_ros2(ctx(tmp_path / "none", find_module=lambda n: False))
    assert r.status == WARNING and "bridge is off" in r.detail


# ------------------------------------------------------------------------------ all together


def ready_pi(root: Path) -> Path:
    libevl(evl_core(spi_ready(root)))
    write(root, "/proc/cmdline", f"{CMD} isolcpus=3 evl.oobcpus=3\n")
    write(root, "/sys/devices/system/cpu/isolated", "3\n")
    governors(root, *["performance"] * 4)
    write(root, "/opt/ros/jazzy/setup.bash", "")
    return root


def test_run_checks_on_a_ready_pi(tmp_path):
    run = fake_runner({"vcgencmd": (0, "throttled=0x0\n"), "timedatectl": (0, "yes\n")})
    results = doctor.run_checks(
        ready_pi(tmp_path),
        run,
        now=lambda: NOW,
        disk_usage=lambda p: (1, 0, 10**11),
        find_module=lambda n: True,
        init_probe=lambda c: InitProbe(OK, "init: answered"),
        guest_probe=lambda c: ConfinementProbe(
            GuestReport(mode="userns", layers={"user": "", "mount": ""}), "as xrf-loop"
        ),
    )
    assert [r.id for r in results] == [
        "evl",
        "isolcpus",
        "governor",
        "throttling",
        "spi",
        "fpga",
        "clock",
        "disk",
        "ros2",
        "confinement",
    ]
    assert all(r.status == OK for r in results), [(r.id, r.status, r.detail) for r in results]
    assert all(set(r.to_dict()) == {"id", "title", "status", "detail", "fix"} for r in results[:-1])
    assert set(results[-1].to_dict()) == {"id", "title", "status", "detail", "fix", "items"}


def test_a_crashing_check_is_reported_not_raised(tmp_path, monkeypatch):
    def boom(c):
        raise RuntimeError("boom")

    boom.__name__ = "check_governor"
    monkeypatch.setattr(doctor, "CHECKS", [boom])
    (r,) = doctor.run_checks(tmp_path, fake_runner({}))
    assert r.status == FAILURE and "boom" in r.detail


def test_cli_json_and_exit_code(tmp_path):
    """`xrf doctor --root` through the real CLI: a broken Pi exits 1, JSON lists the fixes."""
    pi(tmp_path)
    write(tmp_path, "/proc/cmdline", CMD + "\n")
    governors(tmp_path, "ondemand")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "xrflab.cli",
            "doctor",
            "--json",
            "--no-live",
            "--root",
            str(tmp_path),
            "--data",
            "/var/lib/xrf-lab",
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 1, proc.stderr
    results = {r["id"]: r for r in json.loads(proc.stdout)}
    assert results["evl"]["status"] == FAILURE
    assert results["governor"]["status"] == FAILURE and results["governor"]["fix"]
    assert results["fpga"]["status"] == SKIPPED
    assert results["confinement"]["status"] == SKIPPED  # the sandbox is probed on the machine itself only
    text = subprocess.run(
        [sys.executable, "-m", "xrflab.cli", "doctor", "--no-live", "--root", str(tmp_path)],
        capture_output=True,
        text=True,
    )
    assert "[FAIL] CPU frequency governor" in text.stdout and "fix: " in text.stdout
