"""``xrf doctor``: is this machine ready to be a real-time bench? Each check says ok, warning,
failure (or "not checked") and, when not ok, the exact fix.

Every check reads the machine through a :class:`Context`: a root directory (default ``/``)
that prefixes every path it reads (``/proc``, ``/sys``, ``/dev``, ``/etc``, ``/usr/evl``,
``/opt/ros``), a command runner (``vcgencmd``, ``timedatectl``), and small hooks for the FPGA
INIT probe, disk usage, module lookup and the clock - so tests run each check against a
prepared tree and fake commands. docs/install/doctor.md lists every message.

The appliance's System page uses :func:`run_checks`::

    from xrflab.doctor import run_checks
    for r in run_checks(Path("/")):   # list[CheckResult]
        r.id, r.title, r.status, r.detail, r.fix

Paths this module assumes (see docs/install/doctor.md for why):

- EVL core present: ``/dev/evl`` (devtmpfs folder the EVL core's device class "evl" creates:
  ``/dev/evl/control``, ``/dev/evl/clock/...``) and ``/sys/devices/virtual/evl/control``
  (the class device of the control element; also reachable as ``/sys/class/evl/control``).
- Kernel ABI: ``/sys/devices/virtual/evl/control/abi`` (linux-evl's control.c ``abi_show``
  prints ``EVL_ABI_LEVEL``).
- libevl's ABI: the headers libevl installed, ``/usr/evl/include``: ``EVL_ABI_PREREQ`` (the
  ABI libevl needs, ``evl/version.h`` in recent libevl, ``evl/evl.h`` in older ones) and
  ``EVL_ABI_LEVEL`` (the kernel uapi it was built against, ``uapi/evl/control.h`` or
  ``evl/control-abi.h``).
- Throttling: ``vcgencmd get_throttled``, else
  ``/sys/devices/platform/soc/soc:firmware/get_throttled`` (Raspberry Pi kernels).
"""

from __future__ import annotations

import argparse
import glob
import importlib.util
import json
import os
import re
import shutil
import signal
import subprocess
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from .server.settings import SYSTEM_DATA_DIR, Settings, spi_devices_from_env

HELP = (
    "check this machine for real-time readiness (EVL, isolated CPU, governor, throttling, SPI, clock, disk, "
    "ROS 2) and which run sandbox confines students' controllers"
)

OK, WARNING, FAILURE, SKIPPED = "ok", "warning", "failure", "not checked"
STATUSES = (OK, WARNING, FAILURE, SKIPPED)

DEFAULT_DATA_DIR = str(SYSTEM_DATA_DIR)
DEFAULT_LOOP_USER = "xrf-loop"
SPI_DEVICE = Settings.spi_device
EVL_SYSFS = ("sys/devices/virtual/evl/control", "sys/class/evl/control")
THROTTLED_SYSFS = "sys/devices/platform/soc/soc:firmware/get_throttled"
DISK_FAIL_BYTES = 200 * 1000**2
DISK_WARN_BYTES = 2 * 1000**3
# A clock before this is certainly wrong (the Pi has no RTC: it boots at the last saved time
# or 1970 until NTP answers).
SANE_EPOCH = 1704067200  # 2024-01-01

# (returncode, stdout+stderr); returncode 127 = command not found
Runner = Callable[[list], "tuple[int, str]"]


def run_command(cmd: list, timeout: float = 5.0) -> tuple[int, str]:
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except FileNotFoundError:
        return 127, f"{cmd[0]}: not found"
    except (OSError, subprocess.TimeoutExpired) as exc:
        return 126, f"{cmd[0]}: {exc}"
    return proc.returncode, (proc.stdout or "") + (proc.stderr or "")


@dataclass
class CheckResult:
    id: str
    title: str
    status: str  # ok | warning | failure | not checked
    detail: str
    fix: str = ""
    # Parts of a check, each {"name", "status" (ok | missing), "detail"}: the confinement
    # check's protection layers (the System page lists them). Left out of to_dict() when empty.
    items: list = field(default_factory=list)

    def to_dict(self) -> dict:
        d = asdict(self)
        if not d["items"]:
            del d["items"]
        return d


@dataclass
class ConfinementProbe:
    """What the run sandbox did with a harmless controller (``/bin/true``): the launcher's
    report (``xrflab.server.runs.guest_spawn.GuestReport``) and who controllers run as."""

    report: Any  # GuestReport: mode, layers (name -> "" or why missing), notes, error
    identity: str  # guest_spawn.identity().note
    user: str = ""  # who ran the probe (the appliance's user on the System page)


@dataclass
class InitProbe:
    """What the FPGA INIT probe found: status ok/warning/failure/not checked and a text."""

    status: str
    detail: str


@dataclass
class Context:
    root: Path = Path("/")
    runner: Runner = run_command
    data_dir: str = DEFAULT_DATA_DIR
    loop_user: str = DEFAULT_LOOP_USER
    spi_device: str = SPI_DEVICE
    # A bench of several ico boards: every board's device, board 1 first ($XRF_SPI_DEVICES); ()
    # = one board, spi_device.
    spi_devices: tuple[str, ...] = field(default_factory=spi_devices_from_env)
    live: bool = True  # talk to the FPGA (only when SPI is there)
    now: Callable[[], float] = time.time
    disk_usage: Callable[[Path], tuple[int, int, int]] = shutil.disk_usage
    find_module: Callable[[str], bool] = lambda name: importlib.util.find_spec(name) is not None
    init_probe: Callable[[Context], InitProbe] | None = None  # default: probe_fpga_init
    # The run sandbox: the appliance's Settings (None: built from data_dir/spi_device), whether
    # runs may start with a layer missing (xrf serve --allow-unconfined), and the probe
    # (default: probe_confinement, which starts /bin/true in the sandbox; only when root is /).
    settings: Any = None
    allow_unconfined: bool | None = None  # None: settings' (or $XRF_ALLOW_UNCONFINED)
    guest_probe: Callable[[Context], ConfinementProbe] | None = None

    def path(self, p: str) -> Path:
        return self.root / p.lstrip("/")

    def read(self, p: str) -> str | None:
        try:
            return self.path(p).read_text(errors="replace")
        except OSError:
            return None

    def is_pi(self) -> bool:
        model = self.read("/proc/device-tree/model") or self.read("/sys/firmware/devicetree/base/model") or ""
        return "Raspberry Pi" in model

    def has_evl(self) -> bool:
        return self.path("/dev/evl").is_dir() or any(self.path(p).is_dir() for p in EVL_SYSFS)


# ---------------------------------------------------------------------------------------
# helpers


def parse_cpulist(text: str) -> set[int]:
    """'1,3-5' -> {1,3,4,5}; flags such as isolcpus' 'domain,managed_irq,' are ignored."""
    cpus: set[int] = set()
    for part in text.strip().split(","):
        part = part.strip()
        m = re.fullmatch(r"(\d+)-(\d+)(?::\d+/\d+)?", part)
        if m:
            cpus.update(range(int(m.group(1)), int(m.group(2)) + 1))
        elif part.isdigit():
            cpus.add(int(part))
    return cpus


def fmt_cpus(cpus: Iterable[int]) -> str:
    return ",".join(str(c) for c in sorted(cpus)) or "none"


def cmdline_params(cmdline: str) -> dict[str, str]:
    params: dict[str, str] = {}
    for word in cmdline.split():
        key, _, value = word.partition("=")
        params[key] = value
    return params


def _etc_entries(ctx: Context, name: str) -> list[list[str]]:
    text = ctx.read(f"/etc/{name}") or ""
    return [line.split(":") for line in text.splitlines() if line and not line.startswith("#")]


def user_gids(ctx: Context, user: str) -> tuple[int, set[int]] | None:
    """(uid, gids) of ``user`` from the root's /etc/passwd and /etc/group; None if unknown."""
    for f in _etc_entries(ctx, "passwd"):
        if len(f) >= 4 and f[0] == user:
            uid, gids = int(f[2]), {int(f[3])}
            for g in _etc_entries(ctx, "group"):
                if len(g) >= 4 and user in g[3].split(","):
                    gids.add(int(g[2]))
            return uid, gids
    return None


def group_name(ctx: Context, gid: int) -> str:
    for g in _etc_entries(ctx, "group"):
        if len(g) >= 3 and g[2] == str(gid):
            return g[0]
    return str(gid)


def can_rw(ctx: Context, path: Path, user: str) -> tuple[bool, str]:
    """Can ``user`` (from the root's passwd/group) read and write ``path``, by its mode bits?"""
    st = path.stat()
    mode = st.st_mode
    owner = f"{group_name(ctx, st.st_gid)} {oct(mode & 0o777)[2:]}"
    ids = user_gids(ctx, user)
    if ids is None:
        return bool(mode & 0o006 == 0o006), f"group {owner}; user {user} does not exist"
    uid, gids = ids
    if uid == 0:
        return True, f"group {owner}"
    if st.st_uid == uid:
        return bool(mode & 0o600 == 0o600), f"group {owner}"
    if st.st_gid in gids:
        return bool(mode & 0o060 == 0o060), f"group {owner}"
    return bool(mode & 0o006 == 0o006), f"group {owner}"


# ---------------------------------------------------------------------------------------
# checks


def check_evl(ctx: Context) -> CheckResult:
    cid, title = "evl", "EVL kernel and libevl ABI"
    if not ctx.has_evl():
        release = (ctx.read("/proc/sys/kernel/osrelease") or "").strip() or "this kernel"
        return CheckResult(
            cid,
            title,
            FAILURE if ctx.is_pi() else WARNING,
            f"{release} has no EVL core (/dev/evl and /sys/devices/virtual/evl missing): loops "
            "run on the posix backend (SCHED_FIFO), without out-of-band guarantees",
            "build and boot an EVL kernel (docs/install/evl-kernel.md); on a laptop or CI "
            "this is expected and the simulated bench works",
        )
    kernel_abi = None
    for p in EVL_SYSFS:
        text = ctx.read(f"/{p}/abi")
        if text and text.strip().isdigit():
            kernel_abi = int(text.strip())
            break
    lib = libevl_abi(ctx)
    if not ctx.path("/dev/evl/control").exists():
        return CheckResult(
            cid,
            title,
            FAILURE,
            "EVL core in sysfs but /dev/evl/control is missing",
            "check that devtmpfs is mounted and udev runs; reboot",
        )
    if lib is None:
        return CheckResult(
            cid,
            title,
            WARNING,
            f"EVL core present (kernel ABI {kernel_abi if kernel_abi is not None else 'unknown'}), "
            "but libevl is not installed in /usr/evl: rt_core is built with the posix backend only",
            "build libevl for this kernel and install it to /usr/evl (docs/install/pi.md, "
            "'libevl'), then re-run deploy/install",
        )
    prereq, built_level = lib
    if kernel_abi is None:
        return CheckResult(
            cid,
            title,
            WARNING,
            "EVL core present but its ABI is not readable (/sys/devices/virtual/evl/control/abi)",
            "run `/usr/evl/bin/evl check` (or any EVL test) to confirm libevl and the kernel agree",
        )
    need = prereq if prereq is not None else built_level
    if need is not None and kernel_abi < need:
        return CheckResult(
            cid,
            title,
            FAILURE,
            f"kernel EVL ABI {kernel_abi} is older than libevl needs ({need}): evl_init() fails with ENOEXEC",
            "rebuild libevl from a release matching this kernel (or update the kernel), "
            "install to /usr/evl, re-run deploy/install",
        )
    if built_level is not None and kernel_abi != built_level:
        return CheckResult(
            cid,
            title,
            WARNING,
            f"kernel EVL ABI {kernel_abi}, libevl was built against ABI {built_level}"
            + (f" (needs {prereq})" if prereq is not None else "")
            + ": works only if the kernel still honours that ABI",
            "rebuild libevl against this kernel's headers (meson -Duapi=<linux-evl tree>), "
            "install to /usr/evl, re-run deploy/install",
        )
    return CheckResult(
        cid,
        title,
        OK,
        f"EVL core present, kernel ABI {kernel_abi} matches libevl "
        f"({'needs ' + str(prereq) if prereq is not None else 'built against ' + str(built_level)})",
    )


def libevl_abi(ctx: Context) -> tuple[int | None, int | None] | None:
    """(EVL_ABI_PREREQ, EVL_ABI_LEVEL built against) from /usr/evl/include; None: no libevl."""
    inc = ctx.path("/usr/evl/include")
    if not (inc / "evl" / "evl.h").exists():
        return None
    prereq = level = None
    for rel in ("evl/version.h", "evl/evl.h"):
        m = re.search(r"#define\s+EVL_ABI_PREREQ\s+(\d+)", _read(inc / rel))
        if m:
            prereq = int(m.group(1))
            break
    for rel in ("evl/control-abi.h", "uapi/evl/control-abi.h", "uapi/evl/control.h", "evl/uapi/control.h"):
        m = re.search(r"#define\s+EVL_ABI_LEVEL\s+(\d+)", _read(inc / rel))
        if m:
            level = int(m.group(1))
            break
    return prereq, level


def _read(p: Path) -> str:
    try:
        return p.read_text(errors="replace")
    except OSError:
        return ""


def check_isolation(ctx: Context) -> CheckResult:
    cid, title = "isolcpus", "RT CPU isolated (isolcpus= + evl.oobcpus=)"
    cmdline = ctx.read("/proc/cmdline")
    if cmdline is None:
        return CheckResult(cid, title, SKIPPED, "/proc/cmdline not readable")
    params = cmdline_params(cmdline)
    iso = parse_cpulist(params.get("isolcpus", ""))
    oob = parse_cpulist(params.get("evl.oobcpus", ""))
    fix = (
        "append `isolcpus=3 evl.oobcpus=3` (see deploy/boot/cmdline.txt.snippet) to the one "
        "line of /boot/firmware/cmdline.txt, or run `sudo deploy/install --boot`; reboot"
    )
    if "evl.oob_cpus" in params and not oob:
        return CheckResult(
            cid,
            title,
            FAILURE,
            "cmdline has the stale spelling evl.oob_cpus=, which the EVL core ignores",
            "rename it to evl.oobcpus= in /boot/firmware/cmdline.txt; reboot",
        )
    evl = ctx.has_evl()
    if not iso:
        return CheckResult(
            cid, title, FAILURE if evl else WARNING, "no CPU is isolated (no isolcpus= on the kernel command line)", fix
        )
    if evl and not oob:
        return CheckResult(
            cid,
            title,
            FAILURE,
            f"isolcpus={fmt_cpus(iso)} but no evl.oobcpus=: the EVL core may run out-of-band work on every CPU",
            fix,
        )
    if evl and iso != oob:
        return CheckResult(
            cid,
            title,
            WARNING,
            f"isolcpus={fmt_cpus(iso)} and evl.oobcpus={fmt_cpus(oob)} name different CPUs",
            "give both the same CPU (e.g. 3) in /boot/firmware/cmdline.txt; reboot",
        )
    isolated = ctx.read("/sys/devices/system/cpu/isolated")
    if isolated is not None and parse_cpulist(isolated) != iso:
        return CheckResult(
            cid,
            title,
            WARNING,
            f"cmdline isolates {fmt_cpus(iso)} but the kernel reports isolated={fmt_cpus(parse_cpulist(isolated))}",
            "check the isolcpus= syntax (e.g. isolcpus=3) and that the CPU exists; reboot",
        )
    tail = f", evl.oobcpus={fmt_cpus(oob)}" if oob else " (no EVL core: evl.oobcpus not needed)"
    return CheckResult(cid, title, OK, f"isolcpus={fmt_cpus(iso)}{tail}; run loops with XRF_CPU={min(iso)}")


def check_governor(ctx: Context) -> CheckResult:
    cid, title = "governor", "CPU frequency governor"
    files = sorted(glob.glob(str(ctx.path("/sys/devices/system/cpu")) + "/cpu[0-9]*/cpufreq/scaling_governor"))
    if not files:
        return CheckResult(
            cid,
            title,
            WARNING,
            "no cpufreq information (virtual machine, or cpufreq not built in)",
            "nothing to do on a VM; on the Pi enable CONFIG_CPU_FREQ and the raspberrypi cpufreq driver",
        )
    wrong = {}
    for f in files:
        gov = _read(Path(f)).strip()
        if gov != "performance":
            wrong[Path(f).parents[1].name] = gov or "?"
    if wrong:
        shown = ", ".join(f"{cpu}={gov}" for cpu, gov in sorted(wrong.items()))
        return CheckResult(
            cid,
            title,
            FAILURE,
            f"not 'performance': {shown} (frequency scaling adds jitter)",
            "sudo systemctl enable --now xrf-cpufreq.service (installed by deploy/install)",
        )
    return CheckResult(cid, title, OK, f"performance on all {len(files)} CPUs")


THROTTLE_BITS = {0: "under-voltage", 1: "ARM frequency capped", 2: "throttled", 3: "soft temperature limit"}


def read_throttled(ctx: Context) -> tuple[int, str] | None:
    rc, out = ctx.runner(["vcgencmd", "get_throttled"])
    if rc == 0:
        m = re.search(r"throttled=(0x[0-9a-fA-F]+|\d+)", out)
        if m:
            return int(m.group(1), 0), "vcgencmd get_throttled"
    text = ctx.read("/" + THROTTLED_SYSFS)
    if text and text.strip():
        try:
            return int(text.strip(), 16), "/" + THROTTLED_SYSFS
        except ValueError:
            pass
    return None


def check_throttling(ctx: Context) -> CheckResult:
    cid, title = "throttling", "Under-voltage and thermal throttling"
    got = read_throttled(ctx)
    if got is None:
        return CheckResult(
            cid,
            title,
            SKIPPED if not ctx.is_pi() else WARNING,
            "no firmware throttling flags (vcgencmd missing and no get_throttled in sysfs)",
            "" if not ctx.is_pi() else "sudo apt install libraspberrypi-bin (vcgencmd)",
        )
    value, source = got
    now = [name for bit, name in THROTTLE_BITS.items() if value & (1 << bit)]
    since = [name for bit, name in THROTTLE_BITS.items() if value & (1 << (bit + 16))]
    power_fix = (
        "use the official 5.1 V / 3 A USB-C supply and a short cable; "
        "add a heatsink/fan if the temperature limit was hit (vcgencmd measure_temp)"
    )
    if now:
        return CheckResult(cid, title, FAILURE, f"now: {', '.join(now)} (0x{value:x}, {source})", power_fix)
    if since:
        return CheckResult(
            cid,
            title,
            WARNING,
            f"since boot: {', '.join(since)} (0x{value:x}, {source})",
            power_fix + "; then reboot and check again",
        )
    return CheckResult(cid, title, OK, f"no under-voltage or throttling now or since boot (0x{value:x})")


def check_spi(ctx: Context) -> CheckResult:
    """Every board's SPI device (one per ico board, board 1 first): there and usable by the loop."""
    devices = ctx.spi_devices or (ctx.spi_device,)
    cid, title = "spi", f"SPI device{'s' if len(devices) > 1 else ''} {', '.join(devices)}"
    named = [f"board {b + 1}: {d}" if len(devices) > 1 else d for b, d in enumerate(devices)]
    hows = []
    for device, name in zip(devices, named, strict=True):
        dev = ctx.path(device)
        if not dev.exists():
            return CheckResult(
                cid,
                title,
                FAILURE if ctx.is_pi() else WARNING,
                f"{name} does not exist" + ("" if ctx.is_pi() else " (not a Raspberry Pi: the bench is simulated)"),
                "add dtparam=spi=on to /boot/firmware/config.txt (deploy/boot/config.txt.snippet); reboot"
                + ("; each further board needs its chip select (docs/install/pi.md)" if len(devices) > 1 else ""),
            )
        ok, how = can_rw(ctx, dev, ctx.loop_user)
        if not ok:
            return CheckResult(
                cid,
                title,
                FAILURE,
                f"{name} ({how}) is not read/writable by {ctx.loop_user}",
                "install deploy/udev/60-xrf-lab.rules (deploy/install does), then "
                "`sudo udevadm control --reload-rules && sudo udevadm trigger`; "
                f"check `id {ctx.loop_user}` lists group spi",
            )
        hows.append(how)
    return CheckResult(
        cid, title, OK, f"{', '.join(named)} present, read/writable by {ctx.loop_user} ({', '.join(sorted(set(hows)))})"
    )


def find_selfcheck(ctx: Context) -> str | None:
    found = shutil.which("xrf-selfcheck") if str(ctx.root) == "/" else None
    if found:
        return found
    cache = os.environ.get("XRF_CACHE_DIR") if str(ctx.root) == "/" else None
    for base in filter(None, [cache, "/var/cache/xrf-lab", "/usr/local"]):
        hits = sorted(glob.glob(str(ctx.path(base)) + "/rt_core/*/bin/xrf-selfcheck")) + sorted(
            glob.glob(str(ctx.path(base)) + "/bin/xrf-selfcheck")
        )
        if hits:
            return hits[-1]
    return None


def probe_fpga_init(ctx: Context, timeout: float = 10.0) -> InitProbe:
    """Run the bench self-check only up to its INIT step, then stop it (SIGTERM: it aborts
    between frames and zeroes the outputs) - no motor or output step runs."""
    exe = find_selfcheck(ctx)
    if exe is None:
        return InitProbe(SKIPPED, "xrf-selfcheck not found (deploy/install builds it with rt_core)")
    transport = "evl-spidev" if ctx.has_evl() else "spidev"
    try:
        proc = subprocess.Popen(
            [exe, "--transport", transport, "--device", ctx.spi_device],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
    except OSError as exc:
        return InitProbe(SKIPPED, f"cannot run {exe}: {exc}")
    result = InitProbe(FAILURE, "no INIT result from xrf-selfcheck")
    deadline = time.monotonic() + timeout
    assert proc.stdout is not None
    try:
        for line in proc.stdout:
            try:
                ev = json.loads(line)
            except ValueError:
                continue
            if ev.get("event") == "step" and ev.get("id") in ("spi", "init"):
                status = {"pass": OK, "warn": WARNING, "skip": SKIPPED}.get(ev.get("status"), FAILURE)
                text = ev.get("text") or ev.get("title") or ""
                result = InitProbe(status, f"{ev['id']}: {text}".strip())
                if ev["id"] == "init" or status == FAILURE:
                    break
            if ev.get("event") in ("end", "error"):
                break
            if time.monotonic() > deadline:
                result = InitProbe(FAILURE, "xrf-selfcheck gave no INIT result in time")
                break
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return result


def check_fpga(ctx: Context, spi: CheckResult | None = None) -> CheckResult:
    cid, title = "fpga", "FPGA answers INIT"
    spi = spi or check_spi(ctx)
    if spi.status != OK:
        return CheckResult(cid, title, SKIPPED, "not checked: the SPI device is not usable (see the SPI check)")
    if not ctx.live:
        return CheckResult(cid, title, SKIPPED, "not checked (--no-live)")
    probe = (ctx.init_probe or probe_fpga_init)(ctx)
    fixes = {
        FAILURE: "check the ico board's power, that it is programmed (CDONE LED), and the SPI ribbon "
        "cable; then run the full self-check (educator page or `xrf selfcheck`)",
        WARNING: "run the full self-check (educator page or `xrf selfcheck`) and read its INIT step",
    }
    return CheckResult(cid, title, probe.status, probe.detail, fixes.get(probe.status, ""))


def check_clock(ctx: Context) -> CheckResult:
    cid, title = "clock", "Clock synchronised (NTP)"
    rc, out = ctx.runner(["timedatectl", "show", "-p", "NTPSynchronized", "--value"])
    synced = None
    if rc == 0 and out.strip() in ("yes", "no"):
        synced = out.strip() == "yes"
    if ctx.path("/run/systemd/timesync/synchronized").exists():
        synced = True
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(ctx.now()))
    if synced:
        return CheckResult(cid, title, OK, f"synchronised ({stamp})")
    fix = (
        "sudo timedatectl set-ntp true; make sure the Pi reaches an NTP server "
        "(campus networks: set NTP= in /etc/systemd/timesyncd.conf)"
    )
    if ctx.now() < SANE_EPOCH:
        return CheckResult(
            cid,
            title,
            FAILURE,
            f"not synchronised and the clock is wrong ({stamp}): run and log timestamps are meaningless",
            fix,
        )
    how = "timedatectl says no" if synced is False else "timedatectl not available"
    return CheckResult(cid, title, WARNING, f"not known to be synchronised ({how}; now {stamp})", fix)


def check_disk(ctx: Context) -> CheckResult:
    cid, title = "disk", f"Disk space for logs ({ctx.data_dir})"
    p = ctx.path(ctx.data_dir)
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        free = ctx.disk_usage(p)[2]
    except OSError as exc:
        return CheckResult(cid, title, SKIPPED, f"cannot stat {p}: {exc}")
    gb = free / 1000**3
    fix = (
        f"free space: delete old runs in the dashboard, or move {ctx.data_dir} to a larger "
        "disk (xrf serve --data, and the unit's ReadWritePaths=)"
    )
    if free < DISK_FAIL_BYTES:
        return CheckResult(cid, title, FAILURE, f"only {free / 1000**2:.0f} MB free: logging will stop", fix)
    if free < DISK_WARN_BYTES:
        return CheckResult(cid, title, WARNING, f"{gb:.2f} GB free (a long lossless log needs more)", fix)
    return CheckResult(cid, title, OK, f"{gb:.1f} GB free")


def check_ros2(ctx: Context) -> CheckResult:
    cid, title = "ros2", "ROS 2 (for the bridge)"
    distros = sorted(p.parent.name for p in ctx.path("/opt/ros").glob("*/setup.bash"))
    importable = ctx.find_module("rclpy")
    if importable:
        return CheckResult(cid, title, OK, "rclpy importable" + (f" (ROS 2 {', '.join(distros)})" if distros else ""))
    if distros:
        return CheckResult(
            cid,
            title,
            WARNING,
            f"ROS 2 {', '.join(distros)} installed but rclpy is not importable by the appliance",
            f"start the appliance with /opt/ros/{distros[-1]}/setup.bash sourced, or recreate "
            "its venv with --system-site-packages",
        )
    return CheckResult(
        cid,
        title,
        WARNING,
        "no ROS 2 (no rclpy, nothing in /opt/ros): the ROS 2 bridge is off",
        "optional: sudo apt install ros-jazzy-ros-base (Ubuntu 24.04), then restart xrf-lab",
    )


# What to do about a missing layer of the run sandbox (xrflab.guest.LAYERS).
LAYER_FIX = {
    "user": "give the appliance's user subordinate ids and the setuid helpers: `sudo apt install uidmap`, then "
    "`sudo deploy/install` (writes xrf:<uid of xrf-loop>:1 to /etc/subuid and the matching /etc/subgid lines); "
    "or run the appliance as root (development)",
    "mount": "enable unprivileged user namespaces: `sudo sysctl kernel.unprivileged_userns_clone=1` (Debian) or "
    "`sudo sysctl kernel.apparmor_restrict_unprivileged_userns=0` (Ubuntu 24.04); in a container, allow "
    "unshare (e.g. docker --security-opt seccomp=unconfined)",
}
for _layer in ("pid", "network", "ipc"):
    LAYER_FIX[_layer] = LAYER_FIX["mount"]
LAYER_FIX["memory"] = (
    "give the appliance a cgroup of its own to divide: cgroup v2 with `Delegate=memory pids cpuset` in "
    "xrf-lab.service (deploy/install), or run the appliance as root; on a Pi kernel the memory controller may "
    "need `cgroup_enable=memory` on the kernel command line"
)
LAYER_FIX["pids"] = LAYER_FIX["cpu"] = LAYER_FIX["memory"]
LAYER_FIX["disk"] = (
    "a non-root appliance needs the root helper that mounts its run folders: `sudo deploy/install` "
    "(xrf-run-disk.socket); as root it needs mkfs.ext4 and loop devices (modprobe loop)"
)
ALLOW_HINT = (
    "runs are refused until this is fixed (an educator may accept the risk with `xrf serve --allow-unconfined`)"
)


def probe_confinement(ctx: Context) -> ConfinementProbe:
    """Start /bin/true in the run sandbox exactly as a run would (``guest_spawn.probe``)."""
    import pwd

    from .server.runs import guest_spawn

    settings = ctx.settings
    if settings is None:
        kw: dict = {"data_dir": Path(ctx.data_dir), "spi_device": ctx.spi_device, "spi_devices": ctx.spi_devices}
        if ctx.allow_unconfined is not None:
            kw["allow_unconfined"] = ctx.allow_unconfined
        settings = Settings(**kw)
    ident = guest_spawn.identity(settings.run_user)
    report = guest_spawn.probe(settings)
    try:
        user = pwd.getpwuid(os.getuid()).pw_name
    except KeyError:
        user = str(os.getuid())
    return ConfinementProbe(report, ident.note, user)


def _allow_unconfined(ctx: Context) -> bool:
    if ctx.allow_unconfined is not None:
        return ctx.allow_unconfined
    if ctx.settings is not None:
        return bool(ctx.settings.allow_unconfined)
    return os.environ.get("XRF_ALLOW_UNCONFINED", "") in ("1", "true", "yes")


def check_confinement(ctx: Context) -> CheckResult:
    """Which run sandbox confines students' controllers here: the mode (root: a dedicated user;
    userns: a user namespace), who the controller runs as, and each layer holding or missing."""
    cid, title = "confinement", "Run sandbox (students' controllers confined)"
    probe_fn = ctx.guest_probe
    if probe_fn is None:
        if str(ctx.root) != "/":
            return CheckResult(
                cid,
                title,
                SKIPPED,
                "not checked: --root names a prepared tree; the sandbox is probed only on the machine itself",
            )
        probe_fn = probe_confinement
    try:
        probe = probe_fn(ctx)
    except ImportError as exc:
        return CheckResult(
            cid,
            title,
            SKIPPED,
            f"not checked: the appliance is not fully installed here ({exc})",
            "install the xrflab package with its dependencies (deploy/install without --no-deps)",
        )
    report = probe.report
    layers: dict = dict(report.layers or {})
    missing = {k: v for k, v in layers.items() if v}
    allowed = _allow_unconfined(ctx)
    items = [{"name": k, "status": "missing" if v else "ok", "detail": v} for k, v in layers.items()]
    who = f" (probed as {probe.user})" if probe.user else ""
    head = f"mode {report.mode}: {probe.identity}{who}"
    notes = "".join(f"; {n}" for n in (report.notes or []))
    if report.error and not missing:
        # Refused for another reason than a missing layer (no user namespace at all, the
        # launcher failing): no run can start, whatever the settings say.
        fix = LAYER_FIX["mount"]
        if "newuidmap" in report.error:
            fix = (
                "the setuid newuidmap/newgidmap did nothing: the service must not have NoNewPrivileges=yes, and "
                "/etc/subuid, /etc/subgid must list the ids (re-run `sudo deploy/install`)"
            )
        return CheckResult(
            cid,
            title,
            FAILURE,
            f"{head}; the sandbox could not start a controller: {report.error}",
            fix + "; see docs/developers/security.md, 'The run sandbox'",
            items,
        )
    if missing:
        text = "; ".join(f"{k} ({v})" for k, v in missing.items())
        holding = ", ".join(k for k, v in layers.items() if not v) or "none"
        fixes = []
        for k in missing:
            f = LAYER_FIX.get(k, "see docs/developers/security.md, 'The run sandbox'")
            if f not in fixes:
                fixes.append(f)
        if allowed:
            return CheckResult(
                cid,
                title,
                WARNING,
                f"{head}; controllers run WITHOUT: {text} (allowed by --allow-unconfined); holding: {holding}{notes}",
                "; ".join(fixes),
                items,
            )
        return CheckResult(
            cid,
            title,
            FAILURE,
            f"{head}; missing: {text}; holding: {holding}{notes}; {ALLOW_HINT}",
            "; ".join(fixes),
            items,
        )
    return CheckResult(cid, title, OK, f"{head}; all {len(layers)} layers hold ({', '.join(layers)}){notes}", "", items)


CHECKS: list[Callable[[Context], CheckResult]] = [
    check_evl,
    check_isolation,
    check_governor,
    check_throttling,
    check_spi,
    check_fpga,
    check_clock,
    check_disk,
    check_ros2,
    check_confinement,
]


def run_checks(root: Path = Path("/"), runner: Runner = run_command, **context) -> list[CheckResult]:
    """Every check, in order. ``context``: the other :class:`Context` fields (data_dir,
    loop_user, live, now, disk_usage, find_module, init_probe, settings, allow_unconfined,
    guest_probe)."""
    ctx = Context(root=Path(root), runner=runner, **context)
    results: list[CheckResult] = []
    spi = None
    for check in CHECKS:
        try:
            if check is check_fpga:
                r = check_fpga(ctx, spi)
            else:
                r = check(ctx)
        except Exception as exc:  # a broken check must not hide the others
            name = check.__name__.removeprefix("check_")
            r = CheckResult(
                name, name, FAILURE, f"the check itself failed: {exc!r}", "report this as a bug in xrflab.doctor"
            )
        if check is check_spi:
            spi = r
        results.append(r)
    return results


# ---------------------------------------------------------------------------------------
# CLI: registered in cli.py's EXTERNAL_SUBCOMMANDS

SYMBOL = {OK: "ok", WARNING: "WARN", FAILURE: "FAIL", SKIPPED: "--"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--root", type=Path, default=Path("/"), help="check the tree under this folder (tests)")
    parser.add_argument("--data", default=DEFAULT_DATA_DIR, help=f"data folder (default {DEFAULT_DATA_DIR})")
    parser.add_argument("--no-live", action="store_true", help="do not talk to the FPGA")
    parser.add_argument(
        "--allow-unconfined",
        action="store_true",
        default=None,
        help="judge the run sandbox as `xrf serve --allow-unconfined` would run: a missing "
        "protection layer is then a warning, not a failure",
    )


def run(args: argparse.Namespace) -> int:
    results = run_checks(
        args.root, data_dir=args.data, live=not args.no_live, allow_unconfined=getattr(args, "allow_unconfined", None)
    )
    if args.json:
        print(json.dumps([r.to_dict() for r in results], indent=2))
    else:
        for r in results:
            print(f"[{SYMBOL[r.status]:>4}] {r.title}: {r.detail}")
            for item in r.items:
                mark = "holds" if item["status"] == "ok" else f"MISSING: {item['detail']}"
                print(f"       {item['name']:<13} {mark}")
            if r.fix and r.status != OK:
                print(f"       fix: {r.fix}")
        counts = {s: sum(r.status == s for r in results) for s in STATUSES}
        print(
            f"\n{counts[OK]} ok, {counts[WARNING]} warning(s), {counts[FAILURE]} failure(s), "
            f"{counts[SKIPPED]} not checked"
        )
    return 1 if any(r.status == FAILURE for r in results) else 0
