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
import time
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
    # -errno when the outputs were zeroed instead of holding (hold_message), with the channel
    # (1-based) a check failed on (0: none).
    rest_ns: int = 0
    drop_urad: int = 0
    hold_phase: int = 0
    hold_status: int = 0
    hold_channel: int = 0
    hold_gap_us: int = 0  # -ETIME/-EPROTO: the two count samples' distance in time (µs)
    # A hang: the watcher's look at the loop's threads before the kill (XRF_DIAG_* records,
    # server/runs/hang_diag.py reads them); b"" otherwise.
    diagnosis: bytes = b""

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
        if self.hold_phase and not self.hold_status:
            parts.append("arm held by the safety watcher, lowered to its rest pose")
        elif self.sim_forced:
            parts.append(f"sim outputs forced off{brake}")
        if self.hold_status:
            parts.append(hold_message(self.hold_status, self.hold_channel, self.hold_gap_us))
        if self.hold_phase and self.reset_status == 0:
            parts.append("then FPGA RESET sent")
        elif self.reset_status == 0:
            parts.append(
                f"brake frame sent (PWM zero, brake on channel {self.brake_channel})" if brake else "FPGA RESET sent"
            )
        elif self.reset_status != lib.XRF_WATCH_RESET_NOT_TRIED:
            parts.append(reset_message(self.reset_status))
        return "; ".join(parts) or "simulated board ended with the process"


def hold_message(status: int, channel: int = 0, gap_us: int = 0) -> str:
    """Why a `hold` zeroed the outputs instead (watch.h's hold_status; the channel a check
    failed on; the failed count check's samples' distance in time, µs)."""
    on = f" (channel {channel}, samples {gap_us / 1000:.1f} ms apart)" if channel and gap_us else ""
    on = on or (f" (channel {channel})" if channel else "")
    why = {
        -errno.EOPNOTSUPP: "no arm model for this bench",
        -errno.ERANGE: f"the pose from the encoder counts is outside the joint's limits{on}: "
        "the arm was not parked at its rest pose when the run started, or the counts are wrong",
        -errno.EPROTO: f"an encoder count jumped further than the joint can move{on}: the counters "
        "were reset or read garbage, so the arm's pose is unknown",
        -errno.ETIME: f"the encoders{on} went unsampled too long to follow their wraps",
    }.get(status, f"the boards failed: {os.strerror(-status)}{on}")
    return f"hold not possible ({why}): outputs zeroed"


def reset_message(status: int) -> str:
    if status == 0:
        return "FPGA RESET sent"
    if status == -errno.ENOENT:
        return "no spidev to reset"
    return f"FPGA RESET failed: {os.strerror(-status)}"


def fpga_reset(device: str) -> str:
    """Send RESET once now (the fallback when no watcher ran); returns what happened."""
    return reset_message(lib.xrf_fpga_reset(device.encode(), SPI_SPEED_HZ))


def _result(r: Any, brake_channel: int, diagnosis: bytes = b"") -> WatchResult:
    """From a ``struct xrf_watch_result *``; brake_channel: the watcher's (0 unless it brakes)."""
    acted = r.reason in (lib.XRF_WATCH_EXIT, lib.XRF_WATCH_HANG)
    return WatchResult(
        diagnosis=diagnosis,
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
        hold_channel=r.hold_channel,
        hold_gap_us=r.hold_gap_us,
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
        spi_device: str | tuple[str, ...] = "",
        rt_priority: int = 0,
        avoid_cpus: frozenset[int] | set[int] = frozenset(),
        safe_reaction: str = "zero",
        brake_channel: int = 0,
        plant: int = 0,
        enc_counts_per_rev: int = 0,
        enc_inverted: int = 0,
        pwm_reversed: int = 0,
        bench: Any = None,
        host_beat_ms: int = 0,
        host_grace_ms: int = 0,
    ) -> None:
        """spi_device: the bench's SPI devices, one per ico board (board 1 first), on a real bench.
        plant/enc_*/pwm_reversed: the arm `hold` drives (its plant row's model) and, on a real
        bench, the profile's encoder counts per motor turn and wiring (watch.h). bench: instead of
        spi_device, a transport the watcher takes over (tests: a simulated board,
        xrf_sim_follow). host_beat_ms/host_grace_ms: the watcher beats the segment's host heartbeat
        that often while ``host_alive()`` was called within the grace (watch.h)."""
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
        device = (spi_device if isinstance(spi_device, str) else ",".join(spi_device)).encode()
        if len(device) >= len(cfg.spi_device):
            raise ValueError(f"spi device path too long: {spi_device!r}")
        cfg.spi_device = device
        cfg.spi_speed_hz = SPI_SPEED_HZ
        cfg.notify_fd = self._efd
        cfg.avoid_cpus = sum(1 << c for c in avoid_cpus if 0 <= c < 64)
        cfg.safe_reaction = SAFE_REACTIONS[safe_reaction]
        cfg.brake_channel = brake_channel
        cfg.plant = plant
        cfg.enc_counts_per_rev = enc_counts_per_rev
        cfg.enc_inverted = enc_inverted
        cfg.pwm_reversed = pwm_reversed
        cfg.host_beat_ns = host_beat_ms * 1_000_000
        cfg.host_grace_ns = host_grace_ms * 1_000_000
        self.safe_reaction = safe_reaction
        self.brake_channel = brake_channel
        out = ffi.new("struct xrf_watch **")
        shm = channels.shm if channels is not None else ffi.NULL
        r = lib.xrf_watch_start_on(shm, cfg, bench if bench is not None else ffi.NULL, out)
        if r == -errno.EINVAL and safe_reaction == "brake":
            os.close(self._efd)
            raise ValueError(f"safe reaction 'brake' needs a brake channel 1..4 (got {brake_channel})")
        if r == -errno.EINVAL and safe_reaction == "hold":
            os.close(self._efd)
            raise ValueError(
                f"safe reaction 'hold' needs a simulated plant with an arm model (plant id {plant})"
                if force_sim
                else f"safe reaction 'hold' on a real bench needs a plant with an arm model (plant id {plant}), "
                f"the joints' encoder counts per revolution (got {enc_counts_per_rev}) and boards that reach its joints"
            )
        if r < 0:
            os.close(self._efd)
            raise OSError(-r, f"safety watcher for pid {pid}: {os.strerror(-r)}")
        self._w = out[0]
        self._final: WatchResult | None = None
        self._diag: bytes | None = None

    def _brake(self) -> int:
        return self.brake_channel if self.safe_reaction == "brake" else 0

    def fileno(self) -> int:
        return self._efd

    def host_alive(self) -> None:
        """The event loop is alive now: the watcher keeps the host heartbeat beating for the
        grace after this (one atomic store)."""
        lib.xrf_watch_host_alive(self._w, time.monotonic_ns())

    def hold_ready(self) -> tuple[int, int]:
        """A real bench's `hold`: (0, 0) while the watcher can hold the arm from the counts it
        follows, else (the hold_status a fault now gets, the channel); -ENOENT: not that case."""
        channel = ffi.new("int32_t *")
        return lib.xrf_watch_hold_ready(self._w, channel), channel[0]

    def result(self) -> WatchResult | None:
        """The result once the watcher acted (or was stopped); None while it watches."""
        if self._final is not None:
            return self._final
        c = ffi.new("struct xrf_watch_result *")
        if lib.xrf_watch_result(self._w, c) == lib.XRF_WATCH_WATCHING:
            return None
        return _result(c, self._brake(), self._diagnosis(c))

    def _diagnosis(self, c: Any) -> bytes:
        """The hang's diagnosis records (the watcher is done and not yet freed), once."""
        if self._diag is None and c.reason == lib.XRF_WATCH_HANG:
            buf = ffi.new("uint8_t[]", lib.XRF_WATCH_DIAG_BYTES)
            n = lib.xrf_watch_diagnosis(self._w, buf, lib.XRF_WATCH_DIAG_BYTES)
            self._diag = bytes(ffi.buffer(buf, n))
        return self._diag or b""

    def stop(self) -> WatchResult:
        """End the watcher (joins its thread: call off the event loop). A loop that has already
        exited is still made safe first, and a `hold` under way is carried out to the arm's rest
        pose (seconds: the law bounds it). Idempotent."""
        if self._final is None:
            c = ffi.new("struct xrf_watch_result *")
            if lib.xrf_watch_result(self._w, c) != lib.XRF_WATCH_WATCHING:
                self._diagnosis(c)  # before the watcher is freed
            lib.xrf_watch_stop(self._w, c)
            self._final = _result(c, self._brake(), self._diag or b"")
            os.close(self._efd)
            self._channels = None
        return self._final
