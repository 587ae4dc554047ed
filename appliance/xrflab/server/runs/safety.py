"""Outputs safe when a loop is gone or hung: the Python face of rt_core's safety watcher.

The watcher itself is C (``rt_core/src/watch.c``, through the cffi binding): a thread woken by the
kernel when the loop process exits (a pidfd) or by a short timer that checks the loop's heartbeat.
It forces the outputs safe (the simulated board's ``forced_off``; on a real bench the FPGA RESET
frame built by ``ico.c`` and sent by ``spidev.c``, the loop's own code) and only then writes an
eventfd that the appliance's event loop reads. Nothing in this process (the asyncio loop, a GC
pause, the GIL) sits between a dead loop and safe outputs; the appliance learns of it afterwards.
"""

from __future__ import annotations

import errno
import os
from dataclasses import dataclass
from typing import Any

from ...channels import SAFE_REACTIONS, Channels, ffi, lib

SPI_SPEED_HZ = 31_000_000  # XRF2's ico-board clock
_REASONS = {
    lib.XRF_WATCH_WATCHING: "watching",
    lib.XRF_WATCH_EXIT: "exit",
    lib.XRF_WATCH_HANG: "hang",
    lib.XRF_WATCH_CANCELLED: "cancelled",
    lib.XRF_WATCH_HOST_GONE: "host_gone",
    lib.XRF_WATCH_LOOP_ENDED: "loop_ended",
}


@dataclass(frozen=True)
class WatchResult:
    reason: str  # watching | exit | hang | cancelled
    sim_forced: bool
    brake_channel: int  # the brake's channel the outputs were left with on (safe reaction brake); 0: none
    reset_status: int  # 0 sent, -errno failed, XRF_WATCH_RESET_NOT_TRIED
    rt_status: int  # 0: the watcher ran at SCHED_FIFO; -errno: refused (it ran SCHED_OTHER)
    kill_status: int
    event_ns: int  # CLOCK_MONOTONIC, the clock of time.monotonic_ns()
    safe_ns: int
    heartbeat_ns: int
    # hold (xrf/hold.h): when the arm was at rest with the outputs zero (0: not yet or not
    # holding), the largest joint drop until then (µrad), the law's phase (0: none), and 0 or
    # -errno (-EOPNOTSUPP: a real board, whose outputs were zeroed instead).
    rest_ns: int = 0
    drop_urad: int = 0
    hold_phase: int = 0
    hold_status: int = 0

    @property
    def acted(self) -> bool:
        return self.reason in ("exit", "hang")

    @property
    def reaction_ms(self) -> float:
        return (self.safe_ns - self.event_ns) / 1e6 if self.acted else 0.0

    def describe(self) -> str:
        """What was done to the outputs, for the run record and the alarm."""
        parts = []
        brake = f" but the brake on channel {self.brake_channel}" if self.brake_channel else ""
        if self.sim_forced and self.hold_phase:
            parts.append("arm held by the safety watcher, lowered to its rest pose")
        elif self.sim_forced:
            parts.append(f"sim outputs forced off{brake}")
        if self.hold_status == -errno.EOPNOTSUPP:
            parts.append("hold not done on a real board yet: outputs zeroed")
        if self.reset_status == 0:
            parts.append(
                f"brake frame sent (PWM zero, brake on channel {self.brake_channel})" if brake else "FPGA RESET sent"
            )
        elif self.reset_status != lib.XRF_WATCH_RESET_NOT_TRIED:
            parts.append(reset_message(self.reset_status))
        return "; ".join(parts) or "simulated board ended with the process"


def reset_message(status: int) -> str:
    if status == 0:
        return "FPGA RESET sent"
    if status == -errno.ENOENT:
        return "no spidev to reset"
    return f"FPGA RESET failed: {os.strerror(-status)}"


def fpga_reset(device: str) -> str:
    """Send RESET once now (the fallback when no watcher ran); returns what happened."""
    return reset_message(lib.xrf_fpga_reset(device.encode(), SPI_SPEED_HZ))


def _result(r: Any, brake_channel: int) -> WatchResult:
    """From a ``struct xrf_watch_result *``; brake_channel: the watcher's (0 unless it brakes)."""
    acted = r.reason in (lib.XRF_WATCH_EXIT, lib.XRF_WATCH_HANG)
    return WatchResult(
        reason=_REASONS.get(r.reason, str(r.reason)),
        sim_forced=bool(r.sim_forced),
        brake_channel=brake_channel if acted else 0,
        reset_status=r.reset_status,
        rt_status=r.rt_status,
        kill_status=r.kill_status,
        event_ns=r.event_ns,
        safe_ns=r.safe_ns,
        heartbeat_ns=r.heartbeat_ns,
        rest_ns=r.rest_ns,
        drop_urad=r.drop_urad,
        hold_phase=r.hold_phase,
        hold_status=r.hold_status,
    )


class SafetyWatcher:
    """One run's watcher. ``fileno()`` turns readable once it has acted (exit or hang).

    ``channels`` must stay mapped until ``stop()`` returned (the thread reads the heartbeat and
    writes ``forced_off`` in it)."""

    def __init__(
        self,
        pid: int,
        channels: Channels | None,
        *,
        hang_timeout_ms: int,
        check_ms: int,
        force_sim: bool,
        spi_device: str = "",
        rt_priority: int = 0,
        avoid_cpus: frozenset[int] | set[int] = frozenset(),
        safe_reaction: str = "zero",
        brake_channel: int = 0,
        plant: int = 0,
    ) -> None:
        if safe_reaction not in SAFE_REACTIONS:
            raise ValueError(f"unknown safe reaction {safe_reaction!r} (known: {', '.join(SAFE_REACTIONS)})")
        self._channels = channels  # kept referenced: the mapping must outlive the thread
        self._efd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
        cfg = ffi.new("struct xrf_watch_config *")
        cfg.pid = pid
        cfg.hang_timeout_ns = hang_timeout_ms * 1_000_000
        cfg.check_ns = check_ms * 1_000_000
        cfg.rt_priority = rt_priority
        cfg.force_sim = int(force_sim)
        device = spi_device.encode()
        if len(device) >= len(cfg.spi_device):
            raise ValueError(f"spi device path too long: {spi_device!r}")
        cfg.spi_device = device
        cfg.spi_speed_hz = SPI_SPEED_HZ
        cfg.notify_fd = self._efd
        cfg.avoid_cpus = sum(1 << c for c in avoid_cpus if 0 <= c < 64)
        cfg.safe_reaction = SAFE_REACTIONS[safe_reaction]
        cfg.brake_channel = brake_channel
        cfg.plant = plant
        self.safe_reaction = safe_reaction
        self.brake_channel = brake_channel
        out = ffi.new("struct xrf_watch **")
        shm = channels.shm if channels is not None else ffi.NULL
        r = lib.xrf_watch_start(shm, cfg, out)
        if r == -errno.EINVAL and safe_reaction == "brake":
            os.close(self._efd)
            raise ValueError(f"safe reaction 'brake' needs a brake channel 1..4 (got {brake_channel})")
        if r == -errno.EINVAL and safe_reaction == "hold":
            os.close(self._efd)
            raise ValueError(f"safe reaction 'hold' needs a simulated plant with an arm model (plant id {plant})")
        if r < 0:
            os.close(self._efd)
            raise OSError(-r, f"safety watcher for pid {pid}: {os.strerror(-r)}")
        self._w = out[0]
        self._final: WatchResult | None = None

    def _brake(self) -> int:
        return self.brake_channel if self.safe_reaction == "brake" else 0

    def fileno(self) -> int:
        return self._efd

    def result(self) -> WatchResult | None:
        """The result once the watcher acted (or was stopped); None while it watches."""
        if self._final is not None:
            return self._final
        c = ffi.new("struct xrf_watch_result *")
        if lib.xrf_watch_result(self._w, c) == lib.XRF_WATCH_WATCHING:
            return None
        return _result(c, self._brake())

    def stop(self) -> WatchResult:
        """End the watcher (joins its thread: call off the event loop). A loop that has already
        exited is still made safe first, and a `hold` under way is carried out to the arm's rest
        pose (seconds: the law bounds it). Idempotent."""
        if self._final is None:
            c = ffi.new("struct xrf_watch_result *")
            lib.xrf_watch_stop(self._w, c)
            self._final = _result(c, self._brake())
            os.close(self._efd)
            self._channels = None
        return self._final
