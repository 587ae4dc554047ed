"""deploy/install and deploy/uninstall in a throwaway Debian root (debootstrap + chroot).

One tree per module, in order: install, install again (identical tree digest, "nothing to
change"), the unit files through `systemd-analyze verify`, then uninstall (data kept),
uninstall --purge (data and users gone).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from xrf_testing.deploy_support import REPO, run_install, tree_digest

pytestmark = pytest.mark.timeout(1800)

UNITS = ["xrf-lab.service", "xrf-cpufreq.service", "xrf-run-disk.socket", "xrf-run-disk.service"]
# superseded by the run sandbox (xrflab.guest): never installed, removed when an older install left them
STALE = ["etc/systemd/system/xrf-loop@.service", "etc/polkit-1/rules.d/50-xrf-lab.rules"]


def _passwd(root: Path) -> dict[str, list[str]]:
    return {f[0]: f for f in (line.split(":") for line in (root / "etc/passwd").read_text().splitlines())}


def _group(root: Path) -> dict[str, list[str]]:
    return {f[0]: f for f in (line.split(":") for line in (root / "etc/group").read_text().splitlines())}


@pytest.fixture(scope="module")
def installed(debian_root: Path, source: Path):
    first = run_install(debian_root, "--no-deps", source=source)
    assert first.returncode == 0, first.stdout + first.stderr
    digest1 = tree_digest(debian_root)
    second = run_install(debian_root, "--no-deps", source=source)
    assert second.returncode == 0, second.stdout + second.stderr
    digest2 = tree_digest(debian_root)
    return debian_root, first, second, digest1, digest2


def test_install_creates_users_folders_units(installed):
    root, first, *_ = installed
    assert "done:" in first.stdout
    users, groups = _passwd(root), _group(root)
    assert users["xrf"][5] == "/var/lib/xrf-lab" and users["xrf"][6] == "/usr/sbin/nologin"
    assert int(users["xrf"][2]) < 1000 and int(users["xrf-loop"][2]) < 1000  # system users
    for g in ("spi", "gpio", "evl"):
        assert "xrf-loop" in groups[g][3].split(","), g
        assert "xrf" in groups[g][3].split(","), g
    assert "xrf" in groups["xrf-loop"][3].split(",")
    data = root / "var/lib/xrf-lab"
    assert oct(data.stat().st_mode & 0o7777) == "0o750"
    assert data.stat().st_uid == int(users["xrf"][2])
    assert not (data / "loops").exists()  # the old xrf-loop@ unit's folder
    assert (root / "opt/xrf-lab/venv/bin/python").exists()
    assert (root / "opt/xrf-lab/venv/bin/xrf").exists()
    assert (root / "usr/local/bin/xrf").is_symlink()
    assert str((root / "usr/local/bin/xrf").readlink()) == "/opt/xrf-lab/venv/bin/xrf"
    # rt_core built (posix: no /usr/evl in the tree) into the service's cache, owned by xrf
    built = list((root / "var/cache/xrf-lab/rt_core").glob("*/.xrf-complete"))
    assert built, first.stdout
    assert "posix only" in first.stdout
    assert (root / "usr/local/bin/xrf-selfcheck").is_symlink()
    for u in UNITS:
        assert (root / "etc/systemd/system" / u).exists(), u
    for u in ("xrf-lab.service", "xrf-cpufreq.service"):
        assert (root / "etc/systemd/system/multi-user.target.wants" / u).is_symlink()
    assert (root / "etc/systemd/system/sockets.target.wants/xrf-run-disk.socket").is_symlink()
    assert (root / "etc/udev/rules.d/60-xrf-lab.rules").exists()
    limits = (root / "etc/security/limits.d/90-xrf-lab.conf").read_text()
    assert "rtprio" in limits and "memlock" in limits
    for p in STALE:
        assert not (root / p).exists(), p
    # boot files untouched without --boot, but the installer says what to add
    assert "isolcpus=3" in first.stdout and "evl.oobcpus=3" in first.stdout


def _xrf_lines(root: Path, name: str) -> list[str]:
    return [line for line in (root / "etc" / name).read_text().splitlines() if line.startswith("xrf:")]


def test_run_sandbox_ids_devices_and_namespaces(installed):
    """What the run sandbox needs on the Pi: /etc/subuid lets xrf map exactly xrf-loop's uid,
    /etc/subgid exactly xrf-loop's gid (first: the controller's own group) and the device groups
    evl, spi, gpio; /dev/cpu_dma_latency is the launcher's (group xrf); user namespaces on; the
    service may run the setuid newuidmap (no NoNewPrivileges) and nothing gains more than it."""
    root, first, *_ = installed
    users, groups = _passwd(root), _group(root)
    assert _xrf_lines(root, "subuid") == [f"xrf:{users['xrf-loop'][2]}:1"]
    assert _xrf_lines(root, "subgid") == [f"xrf:{groups['xrf-loop'][2]}:1"] + [
        f"xrf:{groups[g][2]}:1" for g in ("evl", "spi", "gpio")
    ]
    for name in ("subuid", "subgid"):
        st = (root / "etc" / name).stat()
        assert (st.st_uid, st.st_gid, oct(st.st_mode & 0o777)) == (0, 0, "0o644"), name
    # the appliance's own reading of those files (xrflab.server.runs.guest_spawn) finds xrf-loop's ids first
    import pwd

    from xrflab.server.runs.guest_spawn import _sub_range

    xrf = pwd.struct_passwd(("xrf", "x", int(users["xrf"][2]), int(users["xrf"][3]), "", "", ""))
    assert _sub_range(str(root / "etc/subuid"), xrf) == (int(users["xrf-loop"][2]), 1)
    assert _sub_range(str(root / "etc/subgid"), xrf) == (int(groups["xrf-loop"][2]), 1)
    rules = (root / "etc/udev/rules.d/60-xrf-lab.rules").read_text().splitlines()
    assert 'SUBSYSTEM=="misc", KERNEL=="cpu_dma_latency", GROUP="xrf", MODE="0660"' in rules
    assert "-kernel.unprivileged_userns_clone = 1" in (root / "etc/sysctl.d/60-xrf-lab.conf").read_text().splitlines()
    unit = (root / "etc/systemd/system/xrf-lab.service").read_text()
    directives = [line.strip() for line in unit.splitlines() if line.strip() and not line.startswith("#")]
    assert not any(d.startswith("NoNewPrivileges=") for d in directives)
    assert "CapabilityBoundingSet=CAP_SETUID CAP_SETGID" in directives and "AmbientCapabilities=" in directives
    assert "RestrictNamespaces=user net mnt pid ipc uts" in directives
    assert "SupplementaryGroups=spi gpio evl video" in directives
    # the run's cgroup (memory, pids, cpuset) below the service's: delegated, and writable
    assert "Delegate=memory pids cpuset" in directives and not any(
        d.startswith("ProtectControlGroups=") for d in directives
    )
    # no uidmap in this tree (and --no-deps: no apt-get): said, not silently skipped
    if not (root / "usr/bin/newuidmap").exists():
        assert "apt-get install uidmap" in first.stdout, first.stdout


def test_installed_package_imports_in_the_chroot(installed):
    root, *_ = installed
    proc = subprocess.run(
        [
            "chroot",
            str(root),
            "/opt/xrf-lab/venv/bin/python",
            "-c",
            "import xrflab.build as b, xrflab.doctor as d; print(b.REPO_ROOT); print(d.HELP[:5])",
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr
    # editable install: xrflab.build finds rt_core next to the package, as in a checkout
    assert proc.stdout.splitlines()[0] == "/opt/xrf-lab/src"


def test_second_run_changes_nothing(installed):
    _root, _first, second, digest1, digest2 = installed
    assert "nothing to change" in second.stdout, second.stdout
    changed = {k for k in digest1.keys() | digest2.keys() if digest1.get(k) != digest2.get(k)}
    assert not changed, sorted(changed)[:20]


def _systemd_analyze() -> str:
    exe = shutil.which("systemd-analyze")
    if exe is None:
        subprocess.run(["apt-get", "install", "-y", "-q", "systemd"], check=True, stdout=subprocess.DEVNULL)
        exe = shutil.which("systemd-analyze")
    assert exe, "systemd-analyze not available"
    return exe


def test_units_pass_systemd_analyze_verify(installed):
    """Verified inside the installed root (--root): the ExecStart binaries (the venv's xrf,
    /bin/sh) and the targets the units name exist there, as on the Pi. No running systemd
    is needed for verify."""
    root, *_ = installed
    exe = _systemd_analyze()
    units = [f"/etc/systemd/system/{u}" for u in UNITS]
    proc = subprocess.run([exe, "verify", f"--root={root}", "--man=no", *units], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    for u in UNITS:
        assert u not in proc.stderr, proc.stderr  # no warnings about our units


def test_room_service_only_when_asked(installed, source):
    """`--room` adds the lab room: xrf-room.service (`xrf room`, which starts its own mosquitto),
    its user and private data folder, /etc/default/xrf-room for its arguments; a plain install has
    none of it. The unit passes systemd-analyze verify in the tree; a later run without --room
    keeps it and changes nothing."""
    root, *_ = installed
    unit = root / "etc/systemd/system/xrf-room.service"
    wants = root / "etc/systemd/system/multi-user.target.wants/xrf-room.service"
    assert not unit.exists() and "xrf-room" not in _passwd(root)
    first = run_install(root, "--no-deps", "--room", source=source)
    assert first.returncode == 0, first.stdout + first.stderr
    assert unit.exists() and wants.is_symlink() and str(wants.readlink()) == "/etc/systemd/system/xrf-room.service"
    text = unit.read_text()
    assert "ExecStart=/opt/xrf-lab/venv/bin/xrf room --host 0.0.0.0 --data /var/lib/xrf-lab-room $XRF_ROOM_ARGS" in text
    assert "User=xrf-room" in text and "EnvironmentFile=-/etc/default/xrf-room" in text
    user = _passwd(root)["xrf-room"]
    assert user[5] == "/var/lib/xrf-lab-room" and int(user[2]) < 1000 and user[6] == "/usr/sbin/nologin"
    data = root / "var/lib/xrf-lab-room"
    assert oct(data.stat().st_mode & 0o7777) == "0o700" and data.stat().st_uid == int(user[2])
    assert 'XRF_ROOM_ARGS=""' in (root / "etc/default/xrf-room").read_text()
    assert "set --broker-name" in first.stdout  # the reminder: benches need the broker's address
    if not (root / "usr/sbin/mosquitto").exists():  # --no-deps: nothing installed, but said
        assert "mosquitto not installed" in first.stdout
    proc = subprocess.run(
        [_systemd_analyze(), "verify", f"--root={root}", "--man=no", "/etc/systemd/system/xrf-room.service"],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "xrf-room.service" not in proc.stderr, proc.stderr
    # the educator's arguments are theirs; a later plain run keeps the room and changes nothing
    (root / "etc/default/xrf-room").write_text('XRF_ROOM_ARGS="--broker-name 10.0.0.5"\n')
    again = run_install(root, "--no-deps", source=source)
    assert again.returncode == 0 and "nothing to change" in again.stdout, again.stdout
    assert unit.exists() and "set --broker-name" not in again.stdout
    assert (root / "etc/default/xrf-room").read_text() == 'XRF_ROOM_ARGS="--broker-name 10.0.0.5"\n'


def test_doctor_runs_in_the_installed_root(installed):
    """The installed `xrf doctor` inside the chroot sees the installer's users and groups: a
    /dev/spidev0.0 of group spi, mode 0660 is usable by xrf-loop; mode 0600 is not."""
    root, *_ = installed
    dev = root / "dev/spidev0.0"
    dev.write_text("")
    os.chown(dev, 0, int(_group(root)["spi"][2]))
    os.chmod(dev, 0o660)
    try:

        def doctor() -> dict:
            proc = subprocess.run(
                ["chroot", str(root), "/usr/local/bin/xrf", "doctor", "--json", "--no-live"],
                capture_output=True,
                text=True,
            )
            assert proc.returncode in (0, 1), proc.stderr
            return {r["id"]: r for r in json.loads(proc.stdout)}

        results = doctor()
        spi = results["spi"]
        assert spi["status"] == "ok" and "xrf-loop" in spi["detail"], spi
        assert "confinement" in results  # the run sandbox's check ran too (whatever a chroot allows)
        os.chmod(dev, 0o600)
        spi = doctor()["spi"]
        assert spi["status"] == "failure" and "udevadm trigger" in spi["fix"], spi
    finally:
        dev.unlink()


def test_boot_settings_only_with_boot_flag(installed, source):
    root, *_ = installed
    fw = root / "boot/firmware"
    fw.mkdir(parents=True, exist_ok=True)
    (fw / "cmdline.txt").write_text("console=serial0,115200 root=LABEL=writable rootwait isolcpus=1\n")
    (fw / "config.txt").write_text("[all]\narm_64bit=1\n")
    plain = run_install(root, "--no-deps", source=source)
    assert "nothing to change" in plain.stdout
    assert "isolcpus=1\n" in (fw / "cmdline.txt").read_text()  # untouched without --boot
    boot = run_install(root, "--no-deps", "--boot", source=source)
    assert boot.returncode == 0, boot.stdout + boot.stderr
    line = (fw / "cmdline.txt").read_text()
    assert line.count("\n") == 1
    words = line.split()
    assert "isolcpus=3" in words and "isolcpus=1" not in words and "evl.oobcpus=3" in words
    assert words[:3] == ["console=serial0,115200", "root=LABEL=writable", "rootwait"]
    assert (fw / "cmdline.txt.xrf-backup").read_text().endswith("isolcpus=1\n")
    assert "dtparam=spi=on" in (fw / "config.txt").read_text().splitlines()
    again = run_install(root, "--no-deps", "--boot", source=source)
    assert "nothing to change" in again.stdout, again.stdout


def test_install_removes_the_superseded_loop_unit(installed, source):
    """An older install's xrf-loop@.service and polkit rule go; the ids stay as they should."""
    root, *_ = installed
    for p in STALE:
        (root / p).parent.mkdir(parents=True, exist_ok=True)
        (root / p).write_text("# from an older install\n")
    (root / "etc/subgid").write_text((root / "etc/subgid").read_text() + "xrf:123456:1\n")  # a stray range
    proc = run_install(root, "--no-deps", source=source)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    for p in STALE:
        assert not (root / p).exists(), p
        assert f"removed /{p}" in proc.stdout
    assert "xrf:123456:1" not in _xrf_lines(root, "subgid") and len(_xrf_lines(root, "subgid")) == 4
    again = run_install(root, "--no-deps", source=source)
    assert "nothing to change" in again.stdout, again.stdout


def test_uninstall_keeps_data_then_purge_removes_it(installed, source):
    root, *_ = installed
    marker = root / "var/lib/xrf-lab/runs-keep.txt"
    marker.write_text("a student's run\n")
    proc = run_install(root, script="uninstall", source=source)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert marker.exists()
    assert "xrf" in _passwd(root)
    for p in (
        "opt/xrf-lab",
        "var/cache/xrf-lab",
        "usr/local/bin/xrf",
        "etc/systemd/system/xrf-lab.service",
        "etc/udev/rules.d/60-xrf-lab.rules",
        "etc/security/limits.d/90-xrf-lab.conf",
        "etc/sysctl.d/60-xrf-lab.conf",
        "etc/systemd/system/multi-user.target.wants/xrf-lab.service",
        "etc/systemd/system/xrf-run-disk.socket",
        "etc/systemd/system/sockets.target.wants/xrf-run-disk.socket",
        "etc/systemd/system/xrf-room.service",
        "etc/systemd/system/multi-user.target.wants/xrf-room.service",
        "etc/default/xrf-room",
    ):
        assert not (root / p).exists() and not (root / p).is_symlink(), p
    assert _xrf_lines(root, "subuid") == [] and _xrf_lines(root, "subgid") == []
    again = run_install(root, script="uninstall", source=source)
    assert "nothing to remove" in again.stdout, again.stdout
    purge = run_install(root, "--purge", script="uninstall", source=source)
    assert purge.returncode == 0, purge.stdout + purge.stderr
    assert not (root / "var/lib/xrf-lab").exists() and not (root / "var/lib/xrf-lab-room").exists()
    assert "xrf" not in _passwd(root) and "xrf-loop" not in _passwd(root) and "xrf-room" not in _passwd(root)
    groups = _group(root)
    assert "xrf" not in groups and "xrf-loop" not in groups
    assert "spi" in groups  # shared groups stay


def test_other_prefix_and_data_folder(installed, source):
    """After the purge above, the same tree takes an install with --prefix/--data elsewhere:
    the units name those paths and still pass verify; a second run changes nothing."""
    root, *_ = installed
    args = ("--no-deps", "--prefix", "/srv/xrf", "--data", "/srv/xrf-data")
    first = run_install(root, *args, source=source)
    assert first.returncode == 0, first.stdout + first.stderr
    unit = (root / "etc/systemd/system/xrf-lab.service").read_text()
    assert "ExecStart=/srv/xrf/venv/bin/xrf serve --host 0.0.0.0 --data /srv/xrf-data" in unit
    assert "ReadWritePaths=/srv/xrf-data" in unit and "/opt/xrf-lab" not in unit.replace("file:///opt", "")
    assert len(_xrf_lines(root, "subuid")) == 1 and len(_xrf_lines(root, "subgid")) == 4  # users made anew
    assert _passwd(root)["xrf"][5] == "/srv/xrf-data"
    assert str((root / "usr/local/bin/xrf").readlink()) == "/srv/xrf/venv/bin/xrf"
    proc = subprocess.run(
        [_systemd_analyze(), "verify", f"--root={root}", "--man=no", "/etc/systemd/system/xrf-lab.service"],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    again = run_install(root, *args, source=source)
    assert "nothing to change" in again.stdout, again.stdout


def test_install_refuses_a_root_without_a_system(tmp_path):
    if not shutil.which("chroot"):
        pytest.skip("no chroot")
    import os

    if os.geteuid() != 0:
        pytest.skip("needs root")
    proc = subprocess.run([str(REPO / "deploy/install"), "--root", str(tmp_path)], capture_output=True, text=True)
    assert proc.returncode != 0
    assert "debootstrap" in proc.stderr
