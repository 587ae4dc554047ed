"""Settings of one appliance process: where data lives, which bench, how hard to supervise.

Plain dataclass, no settings framework: the values come from ``xrf serve``'s options (or a test),
and every knob has a default a newcomer never needs to change.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

# The repository root, found from this file: appliance/xrflab/server/settings.py.
REPO_ROOT = Path(__file__).resolve().parents[3]


# A root appliance's data folder, as on the Pi (deploy/install --data). Not /root/.local/share:
# /root is 0700, and the build user (xrf-build) must pass down to a project's build folder.
SYSTEM_DATA_DIR = Path("/var/lib/xrf-lab")


def default_data_dir() -> Path:
    """Root: /var/lib/xrf-lab. Anyone else: the XDG data dir (like platformdirs' user_data_dir,
    without the dependency), ~/.local/share/xrf-lab."""
    if os.geteuid() == 0:
        return SYSTEM_DATA_DIR
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "xrf-lab"


def spi_devices_from_env() -> tuple[str, ...]:
    """$XRF_SPI_DEVICES: the SPI devices to the ico boards, comma-separated, board 1 first; () when
    unset (then just Settings.spi_device)."""
    return tuple(d.strip() for d in os.environ.get("XRF_SPI_DEVICES", "").split(",") if d.strip())


def real_bench_present(spi_device: str | None = None) -> bool:
    """A real bench needs the EVL core and an SPI device to the ico board (default Settings.spi_device);
    else we simulate."""
    return Path("/dev/evl").exists() and Path(spi_device or Settings.spi_device).exists()


@dataclass(frozen=True)
class Settings:
    """Every default of the appliance is written here once; code elsewhere that needs one without an
    instance reads the class attribute (``Settings.sim``, ``Settings.port``, ``Settings.spi_device``),
    and ``xrf serve``'s options take their defaults and help from these fields (server/cli/serve.py).
    tests/lint/test_written_once.py fails on a copy of these values elsewhere in the code."""

    data_dir: Path = field(default_factory=default_data_dir)
    # Plant of the simulated board when a build does not name one (an example named after a plant
    # runs on it). The plants are rt_core's plant table's (xrflab.plants). Also the bench profile a
    # self-check uses when none is named (`xrf selfcheck`, the room's self-check command).
    sim: str = "relbot"
    host: str = "127.0.0.1"
    port: int = 8000
    # None = detect (real only with /dev/evl and the spidev present); False forces simulation.
    real_bench: bool | None = None
    spi_device: str = "/dev/spidev0.0"  # the SPI device to the ico board (also `xrf doctor`, `xrf selfcheck`)
    # A bench of several ico boards (channels.h: board b carries channels 4b+1..4b+4; the youBot's 9
    # need 3): one SPI device per board, board 1 first ($XRF_SPI_DEVICES, `xrf serve --spi-devices`;
    # docs/install/pi.md for the chip selects). () = one board, spi_device; given, board 1's is
    # spi_device too.
    spi_devices: tuple[str, ...] = field(default_factory=spi_devices_from_env)

    frontend_dir: Path = REPO_ROOT / "frontend"
    projects_dir: Path = REPO_ROOT / "student_projects"

    # Telemetry to browsers, decimated from the loop's write rate: telemetry_hz samples a second,
    # telemetry_per_message of them in one message (oldest first; the page plays them out at
    # their own spacing): each message costs the appliance a wake-up and a socket write per
    # dashboard (most of what one dashboard costs it: the wake-up's cold caches more than the
    # Python), so 6 cuts both to a sixth for the same 30 samples a second (5 messages), at the
    # price of five sample periods (167 ms) more before the oldest sample of a message reaches a
    # browser (issue 30 item 4: the appliance's CPU on a Pi; it was 2, 15 messages, in session 11,
    # and 4, 7.5 messages, in session 12).
    telemetry_hz: float = 30.0
    telemetry_per_message: int = 6
    # The rerun web viewer's files are prepared (copied from `rerun --serve-web`, neutralised,
    # gzipped: a child of ~100 MB for some seconds) once per rerun version: at the appliance's
    # start, when it is smallest, rather than at the first live viewer, beside a run and its
    # recording (issue 30 item 4: the 250 MB budget). Test appliances leave it to the first viewer.
    prepare_viewer_at_start: bool = True
    timing_period_s: float = 1.0

    # Supervision. The loop pauses itself when our heartbeat is older than host_timeout_ms
    # (the appliance died or hangs); we call the loop hung when its heartbeat is older than
    # hang_timeout_ms while the process lives.
    # How often the host heartbeat is written: by the safety watcher's thread where it runs (it
    # detects hangs in C; the event loop tells it once a second that it is alive,
    # server/runs/watch.py), else by the event loop (which then also checks for hangs, 50 ms apart).
    host_heartbeat_period_s: float = 0.2
    host_timeout_ms: int = 1000
    host_timeout_action: str = "pause"
    # Where the safety watcher runs, its thread (SCHED_FIFO, in this process) beats the host
    # heartbeat as long as the event loop was alive within this grace: the loop pauses within
    # host_timeout_ms of this process dying, and only after this long of an event loop that does
    # not run (a starved or stuck appliance), not after one busy second (a browser starting).
    host_stall_grace_ms: int = 5000
    hang_timeout_ms: int = 200
    # SCHED_FIFO priority of the safety watcher thread (server/runs/safety.py): above any priority a guest
    # may take (its RLIMIT_RTPRIO is kept below this one, guest.py), so a controller's own
    # real-time threads cannot starve it; off the guest's CPUs as well (run_watch.start_watcher).
    # Where real time is refused it runs SCHED_OTHER and says so in the run's record.
    watch_priority: int = 90
    open_timeout_s: float = 10.0
    stop_state_timeout_s: float = 2.0  # stop -> STOPPED, quit -> exit
    signal_timeout_s: float = 2.0  # SIGINT -> exit, SIGTERM -> exit, then SIGKILL
    # Where bundled projects are built; None = <data_dir>/builds. Tests share one across servers.
    builds_root: Path | None = None
    # Environment passed to every loop process on top of ours (e.g. XRF_FREQ in benchmarks).
    loop_env: dict[str, str] = field(default_factory=dict)
    # The run sandbox (xrflab.guest, docs/developers/security.md "The run sandbox"). A run starts
    # only with every protection layer in place, unless an educator allowed otherwise
    # (`xrf serve --allow-unconfined`, $XRF_ALLOW_UNCONFINED=1); the dashboard then says which is missing.
    allow_unconfined: bool = field(
        default_factory=lambda: os.environ.get("XRF_ALLOW_UNCONFINED", "") in ("1", "true", "yes")
    )
    run_user: str = "xrf-run"  # as root: the user controllers run as (created on first use)
    # What the kernel bounds for each run (server/runs/limits.py; docs/developers/security.md, "Resources
    # the kernel bounds"). Defaults fit a 2 GB Pi 4 running the appliance and ROS 2 beside a run.
    run_memory_mb: int = 1024  # memory cgroup: its processes, its /dev/shm and /tmp together
    run_pids: int = 256  # pids cgroup: processes and threads of the run
    run_disk_mb: int = 2048  # its run folder: a file system of this size, from the first byte
    run_files: int = 65536  # ...holding at most this many files and folders
    runs_total_mb: int = 8192  # every run folder kept on disk together (checked at each start)
    # A non-root appliance has its run folders mounted by this root helper (server/runs/disk_helper.py,
    # deploy/systemd/xrf-run-disk.socket); a root appliance mounts them itself.
    run_disk_helper: str = "/run/xrf-lab/run-disk.sock"
    # The CPUs a run's processes may use (cpuset, "3" or "2-3"); "" = the isolated CPUs
    # (isolcpus=), else $XRF_CPU of loop_env, else the last CPU.
    loop_cpus: str = ""
    # RLIMIT_RTTIME: a real-time thread of the run that runs this long without blocking gets
    # SIGXCPU (the run ends with `cpu`), SIGKILL at twice this.
    rt_time_ms: int = 500

    # WebSocket fan-out.
    max_frame_bytes: int = 64 * 1024
    client_queue_telemetry: int = 16  # telemetry messages kept per client before dropping oldest (~2 s)
    client_queue_max: int = 2048  # any messages; beyond this the client is disconnected
    slow_client_s: float = 3.0  # dropping continuously this long -> disconnect
    # Kernel send buffer per connection (SO_SNDBUF on the listening socket, inherited by each
    # accepted one). Bounded on purpose: with Linux autotuning a stalled browser could soak up
    # megabytes of stale telemetry in the kernel before our queue ever noticed it was slow.
    send_buffer_bytes: int = 256 * 1024

    # Accounts and the bench lease (docs/developers/security.md). Origins besides the page's own
    # (same origin = the Host header) allowed to call the API and open the WebSocket with a cookie.
    allow_origins: tuple[str, ...] = ()
    session_max_s: float = 12 * 3600  # a login lasts at most this long
    session_idle_s: float = 2 * 3600  # ...and ends after this long unused
    # Login failures (accounts.LoginGuard): per account and client (address or device cookie)
    # within login_window_s, then that client is locked out of that account...
    login_max_failures: int = 5
    login_max_failures_address: int = 20  # ...per client address, any accounts (a lab's NAT is many students)
    login_max_failures_account: int = 50  # ...per account from all clients: then locked for clients it does not know
    login_window_s: float = 60.0  # failures are counted over this long
    login_lock_s: float = (
        60.0  # then the account/address is locked this long; doubles with each further lock, up to 15 min
    )
    lease_idle_s: float = 600.0  # the bench lease is released after this long without driving
    # Addresses of reverse proxies whose X-Forwarded-For/-Proto are believed (`xrf serve
    # --trusted-proxy`); empty = those headers are ignored and the client is the TCP peer.
    trusted_proxies: tuple[str, ...] = ()
    # Request bodies (server/security/body_limit.py): JSON routes take at most this much; archive uploads have
    # their own limit (projects/archive.py Limits.max_upload) and this ceiling above it.
    max_body_bytes: int = 256 * 1024
    max_upload_body_bytes: int = (64 << 20) + (1 << 20)

    # The ROS 2 bridge (docs/ros2/bridge.md, "Run by the appliance"): started with every loop run
    # when on (also $XRF_ROS_BRIDGE=1; the dashboard toggle changes it until the next restart).
    ros_bridge: bool = field(default_factory=lambda: os.environ.get("XRF_ROS_BRIDGE", "") in ("1", "true", "yes"))
    ros_bridge_user: str = ""  # whose bench lease ROS 2 commands obey; "" = the user who started the run
    ros_bridge_priority: int = 10  # SCHED_FIFO, below the loop's; only used when permitted
    ros_bridge_stop_timeout_s: float = 8.0  # SIGTERM -> exit (the bridge's own watchdog is 5 s), then SIGKILL

    def __post_init__(self) -> None:
        if self.spi_devices:  # board 1's device is the one every single-board path uses
            object.__setattr__(self, "spi_device", self.spi_devices[0])

    def spi_bench(self) -> tuple[str, ...]:
        """Every board's SPI device, board 1 first."""
        return self.spi_devices or (self.spi_device,)

    def bench_is_real(self) -> bool:
        return real_bench_present(self.spi_device) if self.real_bench is None else self.real_bench

    @property
    def runs_db(self) -> Path:
        return self.data_dir / "runs.sqlite3"

    @property
    def accounts_db(self) -> Path:
        return self.data_dir / "accounts.sqlite3"

    @property
    def audit_db(self) -> Path:
        return self.data_dir / "audit.sqlite3"

    @property
    def runs_dir(self) -> Path:
        return self.data_dir / "runs"

    @property
    def builds_dir(self) -> Path:
        return self.builds_root or self.data_dir / "builds"
