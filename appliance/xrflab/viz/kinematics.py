"""Encoder counts -> joint angles (Jiwy), a floor pose (RELbot), a carriage position (linear
stage), axes homed on their switches (production cell) or an arm's joints and its mecanum base's
pose (youBot), from a bench profile.

Pure Python, no numpy (the counter range comes from rt_core's ico.h through the cffi binding):
the same code runs live (fed by the appliance's telemetry) and in replay
(fed by a run's recording), and the tests check it against hand-computed cases.

Counters. The ico board's counters are 14-bit and wrap at 16384. A counter is unwrapped by taking
the difference between successive samples modulo 16384 into [-8192, 8191] (the course code's rule:
a jump of more than half the range is a wrap). That is right as long as a shaft turns less than
half the range (2 motor revolutions at 4096 counts/rev) between two samples we look at; the
recorder keeps samples at least every 5 ms, which leaves a wide margin on both robots.
The first sample is read as a signed 14-bit number (16383 = -1), so a counter that was zeroed
and then moved backwards a little starts negative, not near +4 turns.

Profile fields used (``mechanics`` of deploy/profiles/*.json):
- both: ``counts_per_rev`` (at the motor shaft), ``gear_ratio`` (motor turns per output turn);
- pan_tilt: ``axes.<pan|tilt>.channel``, ``belt_ratio`` (camera turn per gearbox output turn),
  ``zero_offset_counts`` (count at which the axis is at 0), ``inverted``, ``limits_deg``;
- differential_drive: ``wheel_diameter``, ``track_width`` (m), ``left_channel``, ``right_channel``,
  ``left_encoder_inverted``, ``right_encoder_inverted`` (true: the counter counts down when the
  wheel rolls forward, the RELbot's mirrored right motor);
- linear_stage: ``channel``, ``lead_m`` (carriage travel per screw turn), ``encoder_inverted``,
  ``limits_m`` ([low, high], m);
- cell: ``axes`` (each ``channel``, ``joint``, ``per_motor_rev``, ``limits``, ``home_pin``);
- youbot: ``joints`` (each ``channel``, ``name``, ``gear_ratio``, ``zero_deg`` (the angle at
  count 0, the rest pose), ``limits_deg``, ``inverted``), ``base`` (``wheel_channels`` FL, FR,
  RL, RR, ``gear_ratio``, ``wheel_diameter``, ``half_wheel_base``, ``half_track``), ``links``
  (m, for drawing).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .. import plants

# The board's counter range, from ico.h through the cffi binding (XRF_ICO_ENC_MODULO, 16384).
COUNTER_RANGE = plants.enc_modulo()
HALF_RANGE = COUNTER_RANGE // 2


class KinematicsError(ValueError):
    """The profile does not describe a robot the 3D view can draw."""


def signed14(raw: int) -> int:
    """A raw 14-bit count read as signed: 0..8191 as is, 8192..16383 as -8192..-1."""
    raw = int(raw) % COUNTER_RANGE
    return raw - COUNTER_RANGE if raw >= HALF_RANGE else raw


def wrap_delta(new: int, old: int) -> int:
    """The change from `old` to `new` raw counts, across a wrap: in [-8192, 8191]."""
    return signed14(int(new) - int(old))


class Unwrapper:
    """Raw 14-bit counts in, a continuous count out (an int that never wraps)."""

    def __init__(self) -> None:
        self.raw: int | None = None
        self.count = 0

    def update(self, raw: int) -> int:
        if self.raw is None:
            self.count = signed14(raw)
        else:
            self.count += wrap_delta(raw, self.raw)
        self.raw = int(raw) % COUNTER_RANGE
        return self.count

    def update_many(self, raw: np.ndarray) -> np.ndarray:
        """`update` for each of a column of raw counts in order, in one numpy pass (the 3D view's
        samples handed over in bulk: issue 30 item 4); the continuous count after each, as int64.
        The same integers as `update` one by one."""
        raw = np.asarray(raw, dtype=np.int64) % COUNTER_RANGE
        if len(raw) == 0:
            return np.zeros(0, dtype=np.int64)
        if self.raw is None:
            start = signed14(int(raw[0]))
            steps = np.diff(raw)
        else:
            start = self.count
            steps = np.diff(raw, prepend=self.raw)
        steps %= COUNTER_RANGE
        steps[steps >= HALF_RANGE] -= COUNTER_RANGE  # wrap_delta, every step at once
        counts = np.cumsum(steps) + start
        if self.raw is None:
            counts = np.concatenate(([start], counts))
        self.count = int(counts[-1])
        self.raw = int(raw[-1])
        return counts

    def reset(self) -> None:
        self.raw = None
        self.count = 0


def update_many(model: Any, enc: np.ndarray) -> None:
    """A model (PanTilt, DiffDrive, LinearStage, Youbot) through every row of `enc` (samples x
    channels, raw counts) in order: its own `update_many` where it has one (one numpy pass),
    else `update` row by row."""
    bulk = getattr(model, "update_many", None)
    if bulk is not None:
        bulk(enc)
        return
    for row in enc.tolist():
        model.update(row)


# Rows of counts a Backlog keeps at most before it runs them through its model anyway (~80 s of a
# 50 Hz telemetry ring; 32 KB for 4 channels of uint16, 72 KB for the youBot's 9).
BACKLOG_MAX = 4096


class Backlog:
    """A model's samples (rows of raw counts), kept while nobody looks at the model and run
    through it in one `update_many` when someone does (`apply`: the 3D view's frame) or once
    BACKLOG_MAX rows are kept. With nobody watching, the view's model took each reader batch
    every few seconds as it came: a dozen numpy calls on cold caches for a few hundred rows, a
    tenth of the idle appliance's event loop (issue 30 item 4, session 16). The same rows in the
    same order, so the same pose and trail as taking them batch by batch (DiffDrive.update_many
    integrates in order; tests/viz/test_viz_bulk.py)."""

    def __init__(self) -> None:
        self._parts: list[np.ndarray] = []
        self.rows = 0

    def add(self, model: Any, enc: np.ndarray) -> bool:
        """Keep `enc` (samples x channels; copied: a reader batch's columns are views of ring
        slots); True when the backlog was run through `model` now (BACKLOG_MAX reached)."""
        self._parts.append(np.array(enc))
        self.rows += len(enc)
        return self.rows >= BACKLOG_MAX and self.apply(model)

    def apply(self, model: Any) -> bool:
        """Every row kept so far through `model` (None: dropped), in order; True when there were any."""
        if not self._parts:
            return False
        rows = self._parts[0] if len(self._parts) == 1 else np.concatenate(self._parts)
        self.drop()
        if model is not None:
            update_many(model, rows)
        return True

    def drop(self) -> None:
        """Forget the rows kept (the model they were for was replaced)."""
        self._parts, self.rows = [], 0


def _mechanics(profile: dict[str, Any]) -> dict[str, Any]:
    mech = profile.get("mechanics") if isinstance(profile, dict) else None
    if not isinstance(mech, dict) or not mech:
        name = profile.get("name", "?") if isinstance(profile, dict) else "?"
        raise KinematicsError(
            f"bench profile {name!r} has no 'mechanics' section: the 3D view needs "
            "counts per revolution, gear ratio and the robot's geometry"
        )
    return mech


# ---- Jiwy: pan/tilt --------------------------------------------------------------------------


@dataclass
class Axis:
    name: str
    channel: int  # 1..4
    rad_per_count: float  # camera rad per motor count, sign included
    zero_offset: int = 0
    limits: tuple[float, float] = (-math.inf, math.inf)  # rad
    unwrap: Unwrapper = field(default_factory=Unwrapper)

    def angle_of(self, count: int) -> float:
        """Camera angle (rad) for a continuous (unwrapped) count."""
        return (count - self.zero_offset) * self.rad_per_count

    def counts_of(self, angle: float) -> float:
        """The inverse of angle_of (tests, setpoint ghosts)."""
        return angle / self.rad_per_count + self.zero_offset


class PanTilt:
    """Jiwy: two revolute axes, camera angle = (count - zero) * 2π / cpr / gear * belt."""

    kind = "pan_tilt"

    def __init__(self, profile: dict[str, Any]) -> None:
        mech = _mechanics(profile)
        if mech.get("kind") != "pan_tilt":
            raise KinematicsError(f"mechanics.kind is {mech.get('kind')!r}, not pan_tilt")
        cpr = float(mech["counts_per_rev"])
        gear = float(mech["gear_ratio"])
        axes = mech.get("axes") or {}
        self.axes: dict[str, Axis] = {}
        for name in ("pan", "tilt"):
            a = axes.get(name)
            if not isinstance(a, dict):
                raise KinematicsError(f"mechanics.axes.{name} is missing")
            sign = -1.0 if a.get("inverted") else 1.0
            lim = a.get("limits_deg")
            limits = (math.radians(lim[0]), math.radians(lim[1])) if lim else (-math.inf, math.inf)
            self.axes[name] = Axis(
                name=name,
                channel=int(a["channel"]),
                rad_per_count=sign * 2 * math.pi / cpr / gear * float(a["belt_ratio"]),
                zero_offset=int(a.get("zero_offset_counts") or 0),
                limits=limits,
            )
        self.angles = {name: 0.0 for name in self.axes}

    def update(self, enc: Sequence[int]) -> dict[str, float]:
        """One sample of raw counts (enc[0] = channel 1); returns {pan, tilt} in rad."""
        for name, axis in self.axes.items():
            self.angles[name] = axis.angle_of(axis.unwrap.update(enc[axis.channel - 1]))
        return dict(self.angles)

    def update_many(self, enc: np.ndarray) -> None:
        """`update` for every row of `enc` (samples x channels) in order: only the last angles
        are kept, the counts unwrapped through every sample."""
        if len(enc):
            for name, axis in self.axes.items():
                count = int(axis.unwrap.update_many(enc[:, axis.channel - 1])[-1])
                self.angles[name] = axis.angle_of(count)

    def reset(self) -> None:
        for axis in self.axes.values():
            axis.unwrap.reset()
        self.angles = {name: 0.0 for name in self.axes}

    def state(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "joints": dict(self.angles),
            "counts": {n: a.unwrap.count for n, a in self.axes.items()},
        }


# ---- RELbot: differential drive odometry -----------------------------------------------------


@dataclass
class Pose:
    x: float = 0.0
    y: float = 0.0
    theta: float = 0.0


class DiffDrive:
    """RELbot: wheel odometry from the two encoders (unicycle model, midpoint heading).

    Per sample: dl, dr = wheel travel (m, + = forward); ds = (dl + dr) / 2; dθ = (dr - dl) / track;
    x += ds·cos(θ + dθ/2); y += ds·sin(θ + dθ/2); θ += dθ. The same integration as the simulated
    plant, so on the simulated bench the odometry follows the true pose up to the counts' resolution
    (the wheels do not slip there; on the floor they do, and the odometry drifts).
    """

    kind = "differential_drive"

    def __init__(self, profile: dict[str, Any], trail_len: int = 600, trail_step_m: float = 0.005) -> None:
        mech = _mechanics(profile)
        if mech.get("kind") != "differential_drive":
            raise KinematicsError(f"mechanics.kind is {mech.get('kind')!r}, not differential_drive")
        cpr = float(mech["counts_per_rev"])
        gear = float(mech["gear_ratio"])
        self.wheel_radius = float(mech["wheel_diameter"]) / 2
        self.track = float(mech["track_width"])
        self.left_channel = int(mech["left_channel"])
        self.right_channel = int(mech["right_channel"])
        rad_per_count = 2 * math.pi / cpr / gear  # wheel rad per motor count
        self.left_rad_per_count = -rad_per_count if mech.get("left_encoder_inverted") else rad_per_count
        self.right_rad_per_count = -rad_per_count if mech.get("right_encoder_inverted") else rad_per_count
        self.left = Unwrapper()
        self.right = Unwrapper()
        self.pose = Pose()
        self.wheel = {"left": 0.0, "right": 0.0}  # rad at the wheel since the first sample, + = forward
        self.trail_len = trail_len
        self.trail_step_m = trail_step_m
        self.trail: list[tuple[float, float]] = [(0.0, 0.0)]
        self._last: tuple[int, int] | None = None

    def update(self, enc: Sequence[int]) -> Pose:
        cl = self.left.update(enc[self.left_channel - 1])
        cr = self.right.update(enc[self.right_channel - 1])
        if self._last is not None:
            dl = (cl - self._last[0]) * self.left_rad_per_count * self.wheel_radius
            dr = (cr - self._last[1]) * self.right_rad_per_count * self.wheel_radius
            self.step(dl, dr)
        self._last = (cl, cr)
        self.wheel = {"left": cl * self.left_rad_per_count, "right": cr * self.right_rad_per_count}
        return self.pose

    def update_many(self, enc: np.ndarray) -> None:
        """`update` for every row of `enc` (samples x channels) in order, the integration in
        numpy: the same sums in the same order as `step` (cumulative sums are sequential), so the
        pose differs from `update`'s at most by the last bits of cos and sin; the trail takes the
        same points."""
        if len(enc) == 0:
            return
        cl = self.left.update_many(enc[:, self.left_channel - 1])
        cr = self.right.update_many(enc[:, self.right_channel - 1])
        if self._last is not None:
            cl_all = np.concatenate(([self._last[0]], cl))
            cr_all = np.concatenate(([self._last[1]], cr))
        else:
            cl_all, cr_all = cl, cr
        self._last = (int(cl[-1]), int(cr[-1]))
        self.wheel = {"left": int(cl[-1]) * self.left_rad_per_count, "right": int(cr[-1]) * self.right_rad_per_count}
        if len(cl_all) < 2:
            return
        dl = np.diff(cl_all) * self.left_rad_per_count * self.wheel_radius
        dr = np.diff(cr_all) * self.right_rad_per_count * self.wheel_radius
        p = self.pose
        ds = (dl + dr) / 2
        dth = (dr - dl) / self.track
        theta = np.cumsum(np.concatenate(([p.theta], dth)))  # theta before each step, and after the last
        mid = theta[:-1] + dth / 2
        xs = np.cumsum(np.concatenate(([p.x], ds * np.cos(mid))))[1:]
        ys = np.cumsum(np.concatenate(([p.y], ds * np.sin(mid))))[1:]
        p.x, p.y, p.theta = float(xs[-1]), float(ys[-1]), float(theta[-1])
        lx, ly = self.trail[-1]
        if float(np.hypot(xs - lx, ys - ly).max()) < self.trail_step_m:
            return  # (nearly) still: no point of the trail to add, as step would find
        for x, y in zip(xs.tolist(), ys.tolist()):
            if math.hypot(x - lx, y - ly) >= self.trail_step_m:
                self.trail.append((x, y))
                lx, ly = x, y
        if len(self.trail) > self.trail_len:
            del self.trail[: len(self.trail) - self.trail_len]

    def step(self, dl: float, dr: float) -> None:
        """Integrate wheel travels dl, dr (m, + = forward)."""
        p = self.pose
        ds = (dl + dr) / 2
        dth = (dr - dl) / self.track
        mid = p.theta + dth / 2
        p.x += ds * math.cos(mid)
        p.y += ds * math.sin(mid)
        p.theta += dth
        lx, ly = self.trail[-1]
        if math.hypot(p.x - lx, p.y - ly) >= self.trail_step_m:
            self.trail.append((p.x, p.y))
            if len(self.trail) > self.trail_len:
                del self.trail[: len(self.trail) - self.trail_len]

    def reset_pose(self) -> None:
        """Reset odometry: the robot is at (0, 0), heading +x, from now on (counters keep counting)."""
        self.pose = Pose()
        self.trail = [(0.0, 0.0)]

    def reset(self) -> None:
        self.left.reset()
        self.right.reset()
        self._last = None
        self.wheel = {"left": 0.0, "right": 0.0}
        self.reset_pose()

    def state(self) -> dict[str, Any]:
        p = self.pose
        return {
            "kind": self.kind,
            "pose": {"x": p.x, "y": p.y, "theta": p.theta},
            "wheels": dict(self.wheel),
            "trail_points": len(self.trail),
        }


# ---- linear stage: one prismatic axis ----------------------------------------------------------


class LinearStage:
    """A carriage on a lead screw: position = (count - zero) * lead / cpr / gear (m), + = away
    from the motor (``encoder_inverted``: the counter counts down that way)."""

    kind = "linear_stage"

    def __init__(self, profile: dict[str, Any]) -> None:
        mech = _mechanics(profile)
        if mech.get("kind") != "linear_stage":
            raise KinematicsError(f"mechanics.kind is {mech.get('kind')!r}, not linear_stage")
        sign = -1.0 if mech.get("encoder_inverted") else 1.0
        self.channel = int(mech["channel"])
        self.m_per_count = sign * float(mech["lead_m"]) / float(mech["counts_per_rev"]) / float(mech["gear_ratio"])
        lim = mech.get("limits_m")
        self.limits = (float(lim[0]), float(lim[1])) if lim else (-0.1, 0.1)
        self.unwrap = Unwrapper()
        self.position = 0.0

    def update(self, enc: Sequence[int]) -> float:
        """One sample of raw counts (enc[0] = channel 1); returns the position in m."""
        self.position = self.unwrap.update(enc[self.channel - 1]) * self.m_per_count
        return self.position

    def update_many(self, enc: np.ndarray) -> None:
        """`update` for every row of `enc` (samples x channels) in order."""
        if len(enc):
            self.position = int(self.unwrap.update_many(enc[:, self.channel - 1])[-1]) * self.m_per_count

    def reset(self) -> None:
        self.unwrap.reset()
        self.position = 0.0

    def state(self) -> dict[str, Any]:
        return {"kind": self.kind, "position": self.position, "counts": self.unwrap.count}


class Cell:
    """A production cell: axes each a motor with a relative encoder and a home switch. The
    counters say nothing of where an axis is, so the view homes as the controller does: an axis's
    zero is the count at which its home switch (``din``, when given) closed; until then it is
    drawn from where it was at the view's reset, and reported not homed."""

    kind = "cell"

    def __init__(self, profile: dict[str, Any]) -> None:
        mech = _mechanics(profile)
        if mech.get("kind") != "cell":
            raise KinematicsError(f"mechanics.kind is {mech.get('kind')!r}, not cell")
        cpr = float(mech["counts_per_rev"]) * float(mech["gear_ratio"])
        self.names = [str(a["name"]) for a in mech["axes"]]
        self.joints = [str(a["joint"]) for a in mech["axes"]]
        self.channels = [int(a["channel"]) for a in mech["axes"]]
        self.per_count = [float(a["per_motor_rev"]) / cpr for a in mech["axes"]]
        # din index of each axis's home switch: pins are channel1_1, channel1_2, ... (ico.h)
        self.home_din = [2 * (int(a["channel"]) - 1) + int(a["home_pin"]) - 1 for a in mech["axes"]]
        self.limits = [(float(a["limits"][0]), float(a["limits"][1])) for a in mech["axes"]]
        self.reset()

    def update(self, enc: Sequence[int], din: Sequence[int] | None = None) -> list[float]:
        """One sample of raw counts (enc[0] = channel 1) and, if known, the input pins; returns
        each axis's position (rad or m) from its switch edge once homed."""
        for i, ch in enumerate(self.channels):
            count = self.unwrap[i].update(enc[ch - 1])
            closed = bool(din[self.home_din[i]]) if din is not None and len(din) > self.home_din[i] else False
            if closed and not self._was_closed[i]:
                self.zero[i] = count  # the switch's edge: this axis's zero
                self.homed[i] = True
            self._was_closed[i] = closed
            self.positions[i] = (count - self.zero[i]) * self.per_count[i]
        return self.positions

    def reset(self) -> None:
        self.unwrap = [Unwrapper() for _ in self.channels]
        self.zero = [0] * len(self.channels)
        self.homed = [False] * len(self.channels)
        self._was_closed = [False] * len(self.channels)
        self.positions = [0.0] * len(self.channels)

    def state(self) -> dict[str, Any]:
        return {"kind": self.kind, "positions": list(self.positions), "homed": list(self.homed)}


# ---- youBot: a 5-joint arm on a mecanum base ---------------------------------------------------


@dataclass
class ArmJoint:
    name: str
    channel: int  # 1..9
    rad_per_count: float  # joint rad per motor count, sign included
    zero: float  # joint angle (rad) where the counter read 0: the pose the arm was parked in
    limits: tuple[float, float]
    unwrap: Unwrapper = field(default_factory=Unwrapper)


class Youbot:
    """A youBot-like mobile manipulator: five arm joints (J1 base yaw, J2..J4 pitch, J5 wrist
    roll), each angle = ``zero_deg`` + count · 2π / cpr / gear (the counters are relative: they
    read 0 where the arm was parked at power-up, its rest pose), and a base on four mecanum
    wheels (front-left, front-right, rear-left, rear-right) whose odometry integrates the mecanum
    forward kinematics with the midpoint heading:

        vx = r/4 · (φFL + φFR + φRL + φRR),  vy = r/4 · (−φFL + φFR + φRL − φRR),
        ω  = r / (4 (lx + ly)) · (−φFL + φFR − φRL + φRR)

    (φ wheel travel in rad, + = rolling forward; rollers in the usual X layout; lx, ly half the
    wheel base and half the track), the same as the simulated plant (plant_youbot.c).

    A sample shorter than the highest channel (telemetry of a 4-channel bench) moves what it has
    and leaves the rest where it was: the view never reads past what it was sent.
    """

    kind = "youbot"

    def __init__(self, profile: dict[str, Any]) -> None:
        mech = _mechanics(profile)
        if mech.get("kind") != "youbot":
            raise KinematicsError(f"mechanics.kind is {mech.get('kind')!r}, not youbot")
        cpr = float(mech["counts_per_rev"])
        self.joints = []
        for j in mech["joints"]:
            sign = -1.0 if j.get("inverted") else 1.0
            lim = j.get("limits_deg") or (-180.0, 180.0)
            self.joints.append(
                ArmJoint(
                    name=str(j["name"]),
                    channel=int(j["channel"]),
                    rad_per_count=sign * 2 * math.pi / cpr / float(j["gear_ratio"]),
                    zero=math.radians(float(j.get("zero_deg") or 0.0)),
                    limits=(math.radians(lim[0]), math.radians(lim[1])),
                )
            )
        base = mech["base"]
        self.wheel_channels = [int(c) for c in base["wheel_channels"]]
        self.wheel_rad_per_count = 2 * math.pi / cpr / float(base["gear_ratio"])
        self.wheel_radius = float(base["wheel_diameter"]) / 2
        self.lx = float(base["half_wheel_base"])
        self.ly = float(base["half_track"])
        self.links = {k: float(v) for k, v in (mech.get("links") or {}).items()}
        self._last_wheels: list[int] | None = None
        self.reset()

    def update(self, enc: Sequence[int]) -> list[float]:
        """One sample of raw counts (enc[0] = channel 1); returns the five joint angles (rad)."""
        n = len(enc)
        for i, j in enumerate(self.joints):
            if j.channel <= n:
                self.angles[i] = j.zero + j.unwrap.update(enc[j.channel - 1]) * j.rad_per_count
        if all(ch <= n for ch in self.wheel_channels):
            counts = [u.update(enc[ch - 1]) for u, ch in zip(self.wheel_unwrap, self.wheel_channels)]
            if self._last_wheels is not None:
                self.step([(c - o) * self.wheel_rad_per_count for c, o in zip(counts, self._last_wheels)])
            self._last_wheels = counts
        return self.angles

    def step(self, dphi: Sequence[float]) -> None:
        """Integrate the wheels' turns dphi (rad at each wheel, + = forward; FL, FR, RL, RR)."""
        fl, fr, rl, rr = dphi
        r = self.wheel_radius
        dx = r / 4 * (fl + fr + rl + rr)
        dy = r / 4 * (-fl + fr + rl - rr)
        dth = r / (4 * (self.lx + self.ly)) * (-fl + fr - rl + rr)
        p = self.pose
        mid = p.theta + dth / 2
        p.x += dx * math.cos(mid) - dy * math.sin(mid)
        p.y += dx * math.sin(mid) + dy * math.cos(mid)
        p.theta += dth

    def reset(self) -> None:
        for j in self.joints:
            j.unwrap.reset()
        self.angles = [j.zero for j in self.joints]
        self.wheel_unwrap = [Unwrapper() for _ in self.wheel_channels]
        self._last_wheels = None
        self.pose = Pose()

    def state(self) -> dict[str, Any]:
        p = self.pose
        return {
            "kind": self.kind,
            "joints": dict(zip((j.name for j in self.joints), self.angles)),
            "pose": {"x": p.x, "y": p.y, "theta": p.theta},
        }


Kinematics = PanTilt | DiffDrive | LinearStage | Cell | Youbot
# mechanics.kind -> its model: the 3D view draws a profile whose kind is here.
KINDS: dict[str, type[PanTilt] | type[DiffDrive] | type[LinearStage] | type[Cell] | type[Youbot]] = {
    PanTilt.kind: PanTilt,
    DiffDrive.kind: DiffDrive,
    LinearStage.kind: LinearStage,
    Cell.kind: Cell,
    Youbot.kind: Youbot,
}


def from_profile(profile: dict[str, Any]) -> Kinematics:
    """The kinematics a profile describes; KinematicsError if it does not describe one."""
    kind = _mechanics(profile).get("kind")
    model = KINDS.get(kind) if isinstance(kind, str) else None
    if model is None:
        raise KinematicsError(f"mechanics.kind {kind!r} is not one the 3D view can draw ({', '.join(KINDS)})")
    return model(profile)
