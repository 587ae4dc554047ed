"""Counts -> angles / pose against hand-computed cases (xrflab.viz.kinematics), the recording
round trip and the replay built from it. No server, no viser: fast."""

from __future__ import annotations

import copy
import json
import math
import struct
from pathlib import Path

import pytest

from xrflab.profiles import load_profile
from xrflab.viz import kinematics as kin
from xrflab.viz.recorder import Recorder, load_recording, write_recording
from xrflab.viz.scene import build_replay, resolve_profile, setpoint_angles

JIWY = load_profile("jiwy")
RELBOT = load_profile("relbot")
STAGE = load_profile("stage")
# RELbot: counts per wheel turn = 4096 * 15.58 = 63815.68; wheel radius 0.0505 m; track 0.20 m.
COUNTS_PER_WHEEL_REV = 63815.68


def raw(count: int) -> int:
    """What a 14-bit counter shows for a continuous count."""
    return count % 16384


def feed(model, counts_per_channel, steps: int = 50):
    """Move each channel from 0 to its target count in `steps` equal steps (raw, wrapped)."""
    targets = list(counts_per_channel) + [0] * (4 - len(counts_per_channel))
    out = None
    for k in range(steps + 1):
        out = model.update([raw(round(t * k / steps)) for t in targets])
    return out


# ---- counters --------------------------------------------------------------------------------


def test_signed_and_wrap_deltas() -> None:
    assert kin.signed14(0) == 0 and kin.signed14(8191) == 8191
    assert kin.signed14(8192) == -8192 and kin.signed14(16383) == -1
    assert kin.wrap_delta(2, 16380) == 6  # forward across the wrap
    assert kin.wrap_delta(16383, 5) == -6  # backward across the wrap
    assert kin.wrap_delta(8000, 100) == 7900
    assert kin.wrap_delta(100, 8000) == -7900


def test_unwrapper_forward_and_backward() -> None:
    u = kin.Unwrapper()
    assert [u.update(r) for r in (0, 6000, 12000, 1616, 7616)] == [0, 6000, 12000, 18000, 24000]
    u = kin.Unwrapper()
    assert [u.update(r) for r in (0, 16000, 10000, 4000)] == [0, -384, -6384, -12384]
    u = kin.Unwrapper()
    assert u.update(16383) == -1  # first sample read as signed: just below zero, not +4 turns


# ---- Jiwy ------------------------------------------------------------------------------------


def test_jiwy_counts_per_radian() -> None:
    m = kin.PanTilt(JIWY)
    assert m.axes["pan"].rad_per_count == pytest.approx(2 * math.pi / 4096 / 19)
    assert m.axes["tilt"].rad_per_count == pytest.approx(2 * math.pi / 4096 / 19 * 0.25)


def test_jiwy_end_stops_after_wraps() -> None:
    # simulator.md: 90 deg pan = 19/4 motor turns = 19456 counts (reads 3072 after one wrap);
    # 45 deg tilt = 76/8 turns = 38912 counts (reads 6144 after two wraps).
    m = kin.PanTilt(JIWY)
    a = feed(m, [19456, 38912], steps=10)
    assert m.axes["pan"].unwrap.raw == 3072 and m.axes["tilt"].unwrap.raw == 6144
    assert a["pan"] == pytest.approx(math.pi / 2)
    assert a["tilt"] == pytest.approx(math.pi / 4)


def test_jiwy_reverse_direction() -> None:
    m = kin.PanTilt(JIWY)
    a = feed(m, [-19456, -38912], steps=10)
    assert a["pan"] == pytest.approx(-math.pi / 2)
    assert a["tilt"] == pytest.approx(-math.pi / 4)
    # and back through zero
    for k in range(10, -1, -1):
        a = m.update([raw(-1945 * k), raw(-3891 * k), 0, 0])
    assert a["pan"] == pytest.approx(0) and a["tilt"] == pytest.approx(0)


def test_jiwy_zero_offset_and_inverted_axis() -> None:
    p = copy.deepcopy(JIWY)
    p["mechanics"]["axes"]["pan"]["zero_offset_counts"] = 1000
    p["mechanics"]["axes"]["tilt"]["inverted"] = True
    m = kin.PanTilt(p)
    a = m.update([1000, 2000, 0, 0])
    assert a["pan"] == pytest.approx(0.0)
    assert a["tilt"] == pytest.approx(-2000 * 2 * math.pi / 4096 / 19 * 0.25)
    a = feed(m, [1000 + 19456, 0], steps=10)
    assert a["pan"] == pytest.approx(math.pi / 2)


def test_setpoint_fields_of_the_jiwy_example() -> None:
    assert setpoint_angles({"pan_setpoint": 0.5, "tilt_setpoint": -0.2}) == {"pan": 0.5, "tilt": -0.2}
    assert setpoint_angles({"steer_left": 1.0}) == {}


# ---- RELbot ----------------------------------------------------------------------------------


def test_relbot_straight_line_forward_and_backward() -> None:
    # 32000 counts = 32000 / 63815.68 wheel turns = 3.150667 rad = 0.159109 m at r = 0.0505 m.
    # Forward: left counts up, right (mirrored, inverted) counts down.
    m = kin.DiffDrive(RELBOT)
    p = feed(m, [32000, -32000])
    assert p.x == pytest.approx(0.159109, abs=1e-6)
    assert p.y == pytest.approx(0.0, abs=1e-12) and p.theta == pytest.approx(0.0, abs=1e-12)
    assert m.wheel["left"] == pytest.approx(3.150667, abs=1e-6)
    assert m.wheel["right"] == pytest.approx(3.150667, abs=1e-6)
    m = kin.DiffDrive(RELBOT)
    p = feed(m, [-32000, 32000])
    assert p.x == pytest.approx(-0.159109, abs=1e-6) and p.theta == pytest.approx(0.0, abs=1e-12)


def test_relbot_turn_on_the_spot() -> None:
    # theta = (dr - dl) / track; a quarter turn: each wheel pi/2 * 0.1 m = 0.157080 m
    # = 3.110494 rad = 31591.8 counts. Left backwards (counts down), right forwards (counts down).
    m = kin.DiffDrive(RELBOT)
    p = feed(m, [-31592, -31592])
    assert p.theta == pytest.approx(math.pi / 2, abs=1e-4)
    assert p.x == pytest.approx(0.0, abs=1e-12) and p.y == pytest.approx(0.0, abs=1e-12)
    # the other way: clockwise
    m = kin.DiffDrive(RELBOT)
    assert feed(m, [31592, 31592]).theta == pytest.approx(-math.pi / 2, abs=1e-4)


def test_relbot_full_turn_on_the_spot() -> None:
    m = kin.DiffDrive(RELBOT)
    p = feed(m, [-4 * 31592, -4 * 31592], steps=200)
    assert p.theta == pytest.approx(2 * math.pi, abs=4e-4)
    assert math.hypot(p.x, p.y) < 1e-9


def test_relbot_full_circle() -> None:
    # A circle of radius 0.5 m, counter-clockwise: centre travel 2*pi*0.5 = pi m, and
    # dr - dl = 2*pi*track = 0.4*pi m: dl = 0.8*pi m, dr = 1.2*pi m; in counts
    # 0.8*pi / (2*pi*0.0505) * 63815.68 = 505470.7 and 0.6/0.0505 * 63815.68 = 758206.1.
    m = kin.DiffDrive(RELBOT)
    left, right = 505470.7, 758206.1
    half = None
    steps = 2000
    for k in range(steps + 1):
        p = m.update([raw(round(left * k / steps)), raw(-round(right * k / steps)), 0, 0])
        if k == steps // 2:
            half = (p.x, p.y, p.theta)
    assert half[0] == pytest.approx(0.0, abs=2e-3) and half[1] == pytest.approx(1.0, abs=2e-3)
    assert half[2] == pytest.approx(math.pi, abs=1e-3)
    assert p.theta == pytest.approx(2 * math.pi, abs=1e-3)
    assert math.hypot(p.x, p.y) < 2e-3
    assert len(m.trail) > 100  # the trail followed the circle


def test_relbot_reset_odometry_keeps_counting() -> None:
    m = kin.DiffDrive(RELBOT)
    feed(m, [32000, -32000])
    m.reset_pose()
    assert (m.pose.x, m.pose.y, m.pose.theta) == (0.0, 0.0, 0.0) and m.trail == [(0.0, 0.0)]
    for k in range(1, 11):  # 32000 more counts, in steps well under half the counter range
        p = m.update([raw(32000 + 3200 * k), raw(-32000 - 3200 * k), 0, 0])
    assert p.x == pytest.approx(0.159109, abs=1e-6)


def test_stage_position_across_wraps_and_its_sign() -> None:
    """Linear stage: 8 mm per 4096 counts, direct drive; 50000 counts (3 wraps) = 97.65625 mm."""
    m = kin.from_profile(STAGE)
    assert isinstance(m, kin.LinearStage) and m.limits == (-0.1, 0.1)
    assert feed(m, [50000]) == pytest.approx(50000 * 0.008 / 4096, abs=1e-12)
    assert m.state() == {"kind": "linear_stage", "position": m.position, "counts": 50000}
    back = copy.deepcopy(STAGE)
    back["mechanics"]["encoder_inverted"] = True
    assert feed(kin.LinearStage(back), [-4096]) == pytest.approx(0.008)
    m.reset()
    assert m.position == 0.0 and m.update([raw(-10), 0, 0, 0]) == pytest.approx(-10 * 0.008 / 4096)


def test_every_plant_has_a_profile_the_3d_view_draws() -> None:
    """A plant of rt_core's table has a default profile of its name, for its robot, with
    kinematics the 3D view knows (what resolve_profile picks on the simulated bench)."""
    from xrflab import plants

    for name in plants.names():
        profile, found, message = resolve_profile(name, real_bench=False, data_dir=Path("/nonexistent"))
        assert profile is not None and found == name and message == "", (name, message)
        assert profile["robot"] == name and kin.from_profile(profile).kind in kin.KINDS


def test_profile_without_mechanics_is_refused() -> None:
    p = copy.deepcopy(RELBOT)
    del p["mechanics"]
    with pytest.raises(kin.KinematicsError, match="mechanics"):
        kin.from_profile(p)


def test_no_profile_gives_a_message(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv("XRF_BENCH_PROFILE", raising=False)
    profile, name, message = resolve_profile("relbot", real_bench=True, data_dir=tmp_path)
    assert profile is None and "no profile" in message
    profile, name, message = resolve_profile("nosuchplant", real_bench=False, data_dir=tmp_path)
    assert profile is None and "nosuchplant" in message
    profile, name, message = resolve_profile("jiwy", real_bench=False, data_dir=tmp_path)
    assert profile is not None and message == ""


# ---- recording and replay --------------------------------------------------------------------


def test_recorder_thins_to_200_hz_and_keeps_the_last_sample(tmp_path: Path) -> None:
    rec = Recorder(tmp_path, {"plant": "jiwy"})
    kept = [rec.add(t * 1_000_000, t, [t % 16384, 0, 0, 0]) for t in range(0, 101)]  # 1 kHz, 100 ms
    rec.close()
    assert sum(kept) == 21  # t = 0, 5, ..., 100 ms
    r = load_recording(tmp_path)
    assert len(r) == 21 and r.t_ns[-1] == 100_000_000 and r.enc[-1] == (100, 0, 0, 0)


def test_replay_of_a_recorded_circle_and_jiwy(tmp_path: Path) -> None:
    left, right, steps = 505470.7, 758206.1, 2000
    samples = [
        (k * 5_000_000, (raw(round(left * k / steps)), raw(-round(right * k / steps)), 0, 0)) for k in range(steps + 1)
    ]
    write_recording(
        tmp_path / "1",
        {"profile": RELBOT, "profile_name": "relbot"},
        samples,
        [{"t_ns": 0, "setpoint": {"steer_left": 1.0}}],
    )
    r = build_replay(1, tmp_path / "1")
    assert r.kind == "differential_drive" and r.duration == pytest.approx(10.0)
    x, y, th = r.poses[r.index(5.0)]
    assert (x, y) == (pytest.approx(0.0, abs=2e-3), pytest.approx(1.0, abs=2e-3))
    assert r.setpoint_at(1.0) == {"steer_left": 1.0}

    samples = [(k * 5_000_000, (raw(k * 1945), raw(-k * 3891), 0, 0)) for k in range(11)]
    write_recording(
        tmp_path / "2",
        {"profile": JIWY, "profile_name": "jiwy"},
        samples,
        [{"t_ns": 20_000_000, "setpoint": {"pan_setpoint": 0.5}}],
    )
    r = build_replay(2, tmp_path / "2")
    pan, tilt = r.joints[-1]
    assert pan == pytest.approx(19450 * 2 * math.pi / 4096 / 19)
    assert tilt == pytest.approx(-38910 * 2 * math.pi / 4096 / 19 * 0.25)
    assert r.setpoint_at(0.01) == {} and r.setpoint_at(0.03) == {"pan_setpoint": 0.5}

    write_recording(tmp_path / "3", {"profile": None, "message": "no profile"}, samples)
    r = build_replay(3, tmp_path / "3")
    assert r.kind == "" and "no profile" in r.message


def test_a_nine_channel_recording_replays_j5_and_the_wheels(tmp_path: Path) -> None:
    """A youBot run records the bench's 9 encoders (format 2, 30-byte records), so its replay
    turns J5 (channel 5) and drives the base (wheels on channels 6-9), hand-computed as above."""
    samples = [
        (0, _counts(0, 0, 0, 0, 0, 0, 0, 0, 0)),
        (5_000_000, _counts(0, 0, 0, 0, -2048, 2048, 2048, 2048, 2048)),
        (10_000_000, _counts(0, 0, 0, 0, -4096, 4096, 4096, 4096, 4096)),
    ]
    write_recording(tmp_path / "1", {"profile": _youbot_profile(), "profile_name": "youbot"}, samples, channels=9)
    rec = load_recording(tmp_path / "1")
    assert rec.meta["format"] == 2 and rec.meta["channels"] == 9 and rec.meta["record"] == "<qI9H"
    assert (tmp_path / "1" / "viz" / "telemetry.bin").stat().st_size == 3 * 30
    assert rec.enc[-1] == tuple(_counts(0, 0, 0, 0, -4096, 4096, 4096, 4096, 4096))
    r = build_replay(1, tmp_path / "1")
    assert r.kind == "youbot"
    assert r.arm[-1][4] == pytest.approx(-2 * math.pi / 71)
    assert r.poses[-1] == pytest.approx((0.05 * 2 * math.pi / 26, 0.0, 0.0))


def test_recording_formats_and_a_meta_the_loop_rewrote(tmp_path: Path) -> None:
    """A format-1 recording (before the channel count) still reads as 4 encoders; a meta.json
    whose channel count is outside 1..XRF_MAX_CHANNELS (the run folder is the loop's to write)
    is refused, never used to size a record; a short sample is padded, a long one cut."""
    rec = Recorder(tmp_path / "a", {"plant": "jiwy"}, channels=3)
    rec.add(0, 0, [1, 2])
    rec.add(10_000_000, 1, [1, 2, 3, 4, 5])
    rec.close()
    assert load_recording(tmp_path / "a").enc == [(1, 2, 0), (1, 2, 3)]
    old = tmp_path / "old" / "viz"
    old.mkdir(parents=True)
    (old / "meta.json").write_text('{"format": 1, "record": "<qI4H"}')
    (old / "telemetry.bin").write_bytes(struct.pack("<qI4H", 7, 1, 10, 20, 30, 40))
    r = load_recording(tmp_path / "old")
    assert r.t_ns == [7] and r.enc == [(10, 20, 30, 40)]
    for bad in (0, 13, 100000, "9", True, None):
        (old / "meta.json").write_text(json.dumps({"format": 2, "channels": bad, "record": "<qI100000H"}))
        with pytest.raises(ValueError, match="channels"):
            load_recording(tmp_path / "old")
    with pytest.raises(ValueError):
        Recorder(tmp_path / "b", {}, channels=13)
    # A count within bounds but below what the recorded profile draws (Jiwy's tilt is channel 2):
    # a clear refusal, not an index error.
    write_recording(tmp_path / "c", {"profile": JIWY}, [(0, (1,))], channels=1)
    with pytest.raises(ValueError, match="1 channels, fewer than its profile draws"):
        build_replay(3, tmp_path / "c")


def test_cell_homes_on_the_switch_edge() -> None:
    """The production cell's view: positions from each axis's home-switch edge once the switch
    closed, hand-computed (table 2π/50 rad, press 4 mm per motor revolution of 4096 counts)."""
    m = kin.from_profile(load_profile("cell"))
    assert m.kind == "cell" and m.names == ["table", "press", "feeder"]
    din = [0] * 8
    m.update([100, 200, 300, 0], din)
    assert m.homed == [False, False, False]
    # The table moves down 50 counts onto its switch (channel 1, pin 1 = din[0]).
    m.update([50, 200, 300, 0], [1, 0, 0, 0, 0, 0, 0, 0])
    assert m.homed == [True, False, False] and m.positions[0] == 0.0
    # It moves up 4096 counts (one motor revolution); the unhomed press is drawn from the
    # counter's zero (the board's RESET), as the other kinds are.
    pos = m.update([50 + 4096, 200 + 4096, 300, 0], din)
    assert pos[0] == pytest.approx(2 * math.pi / 50)
    assert pos[1] == pytest.approx((200 + 4096) * 0.004 / 4096) and m.homed[1] is False
    m.reset()
    assert m.positions == [0.0, 0.0, 0.0] and m.homed == [False, False, False]


def _youbot_profile() -> dict:
    # The figures of deploy/profiles/youbot.json (the simulated plant's), written out here so
    # the hand computation below reads them.
    joints = [("J1", 156, 0.0), ("J2", 156, -65.0), ("J3", 100, 151.0), ("J4", 71, -102.5), ("J5", 71, 0.0)]
    return {
        "name": "youbot",
        "mechanics": {
            "kind": "youbot",
            "counts_per_rev": 4096,
            "gear_ratio": 1,
            "joints": [
                {"channel": k + 1, "name": n, "gear_ratio": g, "zero_deg": z} for k, (n, g, z) in enumerate(joints)
            ],
            "base": {
                "wheel_channels": [6, 7, 8, 9],
                "gear_ratio": 26,
                "wheel_diameter": 0.1,
                "half_wheel_base": 0.236,
                "half_track": 0.15,
            },
        },
    }


def _counts(*c: int) -> list[int]:
    return [x % kin.COUNTER_RANGE for x in c]


def test_youbot_arm_from_its_rest_pose_and_mecanum_odometry() -> None:
    """The youBot's view, hand-computed: a joint is its rest-pose angle (the counters read 0
    where the arm was parked) plus counts · 2π / 4096 / gear; the base's pose integrates the
    mecanum kinematics (wheel radius 0.05 m, 26:1, lx + ly = 0.386 m)."""
    m = kin.from_profile(_youbot_profile())
    assert m.kind == "youbot" and [j.name for j in m.joints] == ["J1", "J2", "J3", "J4", "J5"]
    rest = [0.0, math.radians(-65), math.radians(151), math.radians(-102.5), 0.0]
    assert m.update([0] * 9) == pytest.approx(rest)
    # J2 (gear 156) up three motor revolutions, J5 (gear 71) back one, in steps the unwrapping
    # follows (less than half the counter range each).
    m.update(_counts(0, 6144, 0, 0, -2048, 0, 0, 0, 0))
    q = m.update(_counts(0, 12288, 0, 0, -4096, 0, 0, 0, 0))
    assert q[1] == pytest.approx(math.radians(-65) + 3 * 2 * math.pi / 156)
    assert q[4] == pytest.approx(-2 * math.pi / 71) and q[0] == 0.0
    dphi = 2 * math.pi / 26  # one motor revolution at the wheel
    # All four wheels forward one motor revolution: straight ahead by r·dphi.
    m.update(_counts(0, 12288, 0, 0, -4096, 4096, 4096, 4096, 4096))
    assert (m.pose.x, m.pose.y, m.pose.theta) == pytest.approx((0.05 * dphi, 0.0, 0.0))
    # -FL +FR +RL -RR: sideways to the left (+y) by r·dphi, no turn.
    m.update(_counts(0, 12288, 0, 0, -4096, 0, 8192, 8192, 0))
    assert (m.pose.x, m.pose.y, m.pose.theta) == pytest.approx((0.05 * dphi, 0.05 * dphi, 0.0))
    # -FL +FR -RL +RR: turning on the spot, counter-clockwise by r·dphi / (lx + ly).
    m.update(_counts(0, 12288, 0, 0, -4096, -4096, 12288, 4096, 4096))
    assert m.pose.theta == pytest.approx(0.05 * dphi / 0.386)
    assert (m.pose.x, m.pose.y) == pytest.approx((0.05 * dphi, 0.05 * dphi))
    # A 4-channel sample (a bench without the wheels' channels) moves J1..J4 only.
    pose = (m.pose.x, m.pose.y, m.pose.theta)
    q = m.update(_counts(4096, 12288, 0, 0))
    assert q[0] == pytest.approx(2 * math.pi / 156) and q[4] == pytest.approx(-2 * math.pi / 71)
    assert (m.pose.x, m.pose.y, m.pose.theta) == pose
    m.reset()
    assert m.angles == pytest.approx(rest) and (m.pose.x, m.pose.y) == (0.0, 0.0)
