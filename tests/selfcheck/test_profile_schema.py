"""The bench-profile schema has one validator, xrflab.profiles, with per-field errors.

REJECTED_BY_THE_OLD_C_PARSER lists every profile the checker's own JSON parser refused before
the validation moved to Python (rt_core/src/selfcheck.c up to issue 20: its pnum/pint/pbool/pstr
calls and explicit checks, one entry each), with the field the validator must name. Nothing it
refused may now reach the checker. No checker and no browser here: these run in milliseconds.
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from xrflab import profiles as prof
from xrflab.selfcheck_limits import hard_limits

REPO = Path(__file__).resolve().parents[2]
Mutation = Callable[[dict[str, Any]], Any]


def setting(*path: Any, value: Any) -> Mutation:
    def mutate(p: dict[str, Any]) -> None:
        obj = p
        for k in path[:-1]:
            obj = obj[k]
        obj[path[-1]] = value

    return mutate


def dropping(*path: Any) -> Mutation:
    def mutate(p: dict[str, Any]) -> None:
        obj = p
        for k in path[:-1]:
            obj = obj[k]
        del obj[path[-1]]

    return mutate


def spare(**fields: Any) -> Mutation:
    """Channel 3 of the RELbot profile (no motor) with these fields."""
    return lambda p: p["channels"][2].update(fields)


MAX = hard_limits()

# (what the old parser refused, mutation of the relbot profile, field the validator names)
REJECTED_BY_THE_OLD_C_PARSER: list[tuple[str, Mutation, str]] = [
    ("name not a string", setting("name", value=7), "name"),
    ("pwm_limit not a number", setting("limits", "pwm_limit", value="max"), "limits.pwm_limit"),
    ("pwm_limit above the hard limit", setting("limits", "pwm_limit", value=MAX.max_duty + 0.01), "limits.pwm_limit"),
    ("pwm_limit below 0", setting("limits", "pwm_limit", value=-0.1), "limits.pwm_limit"),
    ("period_us not a number", setting("pulse", "period_us", value=True), "pulse.period_us"),
    ("period_us below the minimum", setting("pulse", "period_us", value=MAX.min_period_us - 1), "pulse.period_us"),
    ("period_us above the maximum", setting("pulse", "period_us", value=MAX.max_period_us + 1), "pulse.period_us"),
    ("period_us not whole", setting("pulse", "period_us", value=1000.5), "pulse.period_us"),
    ("settle_ms above the hard limit", setting("pulse", "settle_ms", value=MAX.max_settle_ms + 1), "pulse.settle_ms"),
    ("settle_ms below 0", setting("pulse", "settle_ms", value=-1), "pulse.settle_ms"),
    ("settle_ms not whole", setting("pulse", "settle_ms", value=1.5), "pulse.settle_ms"),
    (
        "reset tolerance above 1000",
        setting("pulse", "reset_tolerance_counts", value=1001),
        "pulse.reset_tolerance_counts",
    ),
    ("reset tolerance below 0", setting("pulse", "reset_tolerance_counts", value=-1), "pulse.reset_tolerance_counts"),
    ("echo_frames 0", setting("link", "echo_frames", value=0), "link.echo_frames"),
    ("echo_frames above the hard limit", setting("link", "echo_frames", value=MAX.max_frames + 1), "link.echo_frames"),
    ("timing_frames 0", setting("link", "timing_frames", value=0), "link.timing_frames"),
    (
        "timing_frames above the hard limit",
        setting("link", "timing_frames", value=MAX.max_frames + 1),
        "link.timing_frames",
    ),
    ("timing_frames not a number", setting("link", "timing_frames", value="all"), "link.timing_frames"),
    ("warn_median_us negative", setting("link", "warn_median_us", value=-1), "link.warn_median_us"),
    ("warn_median_us above 1e6", setting("link", "warn_median_us", value=2e6), "link.warn_median_us"),
    ("fail_median_us above 1e6", setting("link", "fail_median_us", value=2e6), "link.fail_median_us"),
    ("fail_median_us not a number", setting("link", "fail_median_us", value=[1]), "link.fail_median_us"),
    ("warn_max_us above 1e7", setting("link", "warn_max_us", value=2e7), "link.warn_max_us"),
    ("channels not a list", setting("channels", value={"1": {}}), "channels"),
    ("a channels entry not an object", setting("channels", 1, value=[2]), "channels[1]"),
    ("a channels entry without channel", dropping("channels", 1, "channel"), "channels[1].channel"),
    ("channel 0", setting("channels", 1, "channel", value=0), "channels[1].channel"),
    # (the old parser's bound was one board's 4; a bench has up to XRF_MAX_CHANNELS now)
    (
        "channel past the most a bench has",
        setting("channels", 1, "channel", value=prof.max_channels() + 1),
        "channels[1].channel",
    ),
    ("channel not whole", setting("channels", 1, "channel", value=1.5), "channels[1].channel"),
    ("channel not a number", setting("channels", 1, "channel", value="2"), "channels[1].channel"),
    ("channel name not a string", setting("channels", 0, "name", value=1), "channel 1.name"),
    ("connector not a string", setting("channels", 0, "connector", value=3), "channel 1.connector"),
    ("motor not true/false", setting("channels", 0, "motor", value=1), "channel 1.motor"),
    ("loopback not true/false", setting("channels", 0, "loopback", value="no"), "channel 1.loopback"),
    ("direction 0", setting("channels", 0, "direction", value=0), "channel 1.direction"),
    ("direction 2", setting("channels", 0, "direction", value=2), "channel 1.direction"),
    ("direction -2", setting("channels", 0, "direction", value=-2), "channel 1.direction"),
    ("direction not whole", setting("channels", 0, "direction", value=0.5), "channel 1.direction"),
    ("direction not a number", setting("channels", 0, "direction", value="up"), "channel 1.direction"),
    ("duty above the hard limit", setting("channels", 0, "duty", value=MAX.max_duty + 0.05), "channel 1.duty"),
    ("duty negative", spare(duty=-0.1), "channel 3.duty"),
    ("duty not a number", setting("channels", 0, "duty", value="slow"), "channel 1.duty"),
    ("duty 0 on a motor channel", setting("channels", 0, "duty", value=0), "channel 1.duty"),
    (
        "duty above limits.pwm_limit on a motor channel",
        lambda p: (p["limits"].update(pwm_limit=0.1), p["channels"][0].update(duty=0.15)),
        "channel 1.duty",
    ),
    ("duration_ms 0", setting("channels", 0, "duration_ms", value=0), "channel 1.duration_ms"),
    (
        "duration_ms above the hard limit",
        setting("channels", 0, "duration_ms", value=MAX.max_pulse_ms + 1),
        "channel 1.duration_ms",
    ),
    ("duration_ms not whole", setting("channels", 0, "duration_ms", value=10.5), "channel 1.duration_ms"),
    ("min_counts 0", setting("channels", 0, "min_counts", value=0), "channel 1.min_counts"),
    ("min_counts above 1e7", setting("channels", 0, "min_counts", value=10**7 + 1), "channel 1.min_counts"),
    ("min_counts not whole", setting("channels", 0, "min_counts", value="lots"), "channel 1.min_counts"),
    ("max_counts negative", setting("channels", 0, "max_counts", value=-1), "channel 1.max_counts"),
    ("max_counts above 1e9", setting("channels", 0, "max_counts", value=10**9 + 1), "channel 1.max_counts"),
    ("max_counts below min_counts", setting("channels", 0, "max_counts", value=499), "channel 1.max_counts"),
    # The old parser compared against its default min_counts (50) when the profile gave none.
    ("max_counts below the default min_counts", spare(max_counts=10), "channel 3.min_counts"),
    ("inputs not a list", setting("channels", 0, "inputs", value={"pin": 1}), "channel 1.inputs"),
    ("an inputs entry not an object", setting("channels", 0, "inputs", value=[1]), "channel 1.inputs[0]"),
    ("an inputs entry without pin", dropping("channels", 0, "inputs", 1, "pin"), "channel 1.inputs[1].pin"),
    ("pin 0", setting("channels", 0, "inputs", 0, "pin", value=0), "channel 1.inputs[0].pin"),
    ("pin 3", setting("channels", 0, "inputs", 0, "pin", value=3), "channel 1.inputs[0].pin"),
    ("pin not a number", setting("channels", 0, "inputs", 0, "pin", value="one"), "channel 1.inputs[0].pin"),
    ("pin name not a string", setting("channels", 0, "inputs", 0, "name", value=False), "channel 1.inputs[0].name"),
    ("idle 2", setting("channels", 0, "inputs", 0, "idle", value=2), "channel 1.inputs[0].idle"),
    ("idle -1", setting("channels", 0, "inputs", 0, "idle", value=-1), "channel 1.inputs[0].idle"),
    ("idle not a number", setting("channels", 0, "inputs", 0, "idle", value="low"), "channel 1.inputs[0].idle"),
    ("idle not whole", setting("channels", 0, "inputs", 0, "idle", value=0.5), "channel 1.inputs[0].idle"),
    ("a profile that is not an object", lambda p: [p], ""),
]


def relbot() -> dict[str, Any]:
    return copy.deepcopy(prof.load_profile("relbot"))


@pytest.mark.parametrize(
    "mutate,field",
    [(m, f) for _, m, f in REJECTED_BY_THE_OLD_C_PARSER],
    ids=[what for what, _, _ in REJECTED_BY_THE_OLD_C_PARSER],
)
def test_every_profile_the_old_checker_refused_is_refused_with_its_field(mutate: Mutation, field: str) -> None:
    p = relbot()
    replaced = mutate(p)
    if isinstance(replaced, list):  # the mutation built a new document
        p = replaced
    with pytest.raises(prof.ProfileError) as info:
        prof.validate_profile(p)
    named = [e for e in info.value.problems if e.field == field]
    assert named, info.value.problems
    # The message is about that field (its last part, without an index, is in the sentence).
    last = field.rsplit(".", 1)[-1].split("[")[0] if field else ""
    assert all(last in e.message for e in named), named


def test_not_valid_json_is_a_problem_of_the_whole_file(tmp_path: Path) -> None:
    f = tmp_path / "broken.json"
    f.write_text('{"name": "broken",')
    with pytest.raises(prof.ProfileError) as info:
        prof.load_profile(f)
    assert [e.field for e in info.value.problems] == [""] and "not valid JSON" in info.value.problems[0].message


def test_the_fields_of_problems_found_together() -> None:
    p = relbot()
    p["channels"][0]["duty"] = 0.5
    p["channels"][1]["direction"] = 0
    p["link"]["echo_frames"] = 0
    p["mechanics"]["gear_ratio"] = -3
    with pytest.raises(prof.ProfileError) as info:
        prof.validate_profile(p)
    assert {e.field for e in info.value.problems} == {
        "channel 1.duty",
        "channel 2.direction",
        "link.echo_frames",
        "mechanics.gear_ratio",
    }
    assert str(info.value) == "; ".join(info.value.errors)


def test_hard_limits_come_from_the_c_header(tmp_path: Path) -> None:
    """The validator's limits are the header's, read through cffi, not a copy: with a header that
    says 150 ms, a 160 ms pulse is refused and a 140 ms one is not."""
    assert (MAX.max_duty, MAX.max_pulse_ms) == (0.2, 200)
    header = (REPO / "rt_core/include/xrf/selfcheck_limits.h").read_text()
    assert "#define XRF_SC_MAX_PULSE_MS 200" in header
    other = tmp_path / "rt_core" / "include" / "xrf"
    other.mkdir(parents=True)
    (other / "selfcheck_limits.h").write_text(header.replace("MAX_PULSE_MS 200", "MAX_PULSE_MS 150"))
    # the channel bound comes from this header (profiles.max_channels)
    (other / "channels.h").write_text((REPO / "rt_core/include/xrf/channels.h").read_text())
    script = """
import copy, json, sys
from xrflab import profiles as prof
p = copy.deepcopy(prof.load_profile("relbot"))
out = []
for ms in (140, 160):
    p["channels"][0]["duration_ms"] = ms
    try:
        prof.validate_profile(p)
        out.append([])
    except prof.ProfileError as exc:
        out.append([e.field for e in exc.problems])
print(json.dumps(out))
"""
    env = dict(
        os.environ,
        XRF_RT_CORE=str(tmp_path / "rt_core"),
        PYTHONPATH=str(REPO / "appliance") + os.pathsep + os.environ.get("PYTHONPATH", ""),
    )
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=60)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout) == [[], ["channel 1.duration_ms"]]


def test_every_shipped_profile_validates() -> None:
    files = sorted((REPO / "deploy/profiles").glob("*.json"))
    assert len(files) >= 2
    for f in files:
        p = prof.validate_profile(json.loads(f.read_text()), str(f))
        assert p["name"] == f.stem, f
    assert {i.name for i in prof.list_profiles(data_dir=Path("/nonexistent"))} == {f.stem for f in files}


# The safety section (safety.reaction: what the safety watcher does on an exit or a hang).
BAD_SAFETY: list[tuple[str, dict[str, Any], str]] = [
    ("a reaction the watcher does not know", {"reaction": "drop"}, "safety.reaction"),
    ("a reaction that is not text", {"reaction": 1}, "safety.reaction"),
    ("brake without its channel", {"reaction": "brake"}, "safety.brake_channel"),
    ("a brake channel beyond the board", {"reaction": "brake", "brake_channel": 5}, "safety.brake_channel"),
    ("a brake channel with reaction zero", {"reaction": "zero", "brake_channel": 3}, "safety.brake_channel"),
    ("a brake on a motor's channel", {"reaction": "brake", "brake_channel": 1}, "safety.brake_channel"),
]


@pytest.mark.parametrize("safety,field", [(s, f) for _, s, f in BAD_SAFETY], ids=[w for w, _, _ in BAD_SAFETY])
def test_a_safe_reaction_the_watcher_cannot_carry_out_is_refused_with_its_field(safety: dict, field: str) -> None:
    p = relbot()
    p["safety"] = safety
    with pytest.raises(prof.ProfileError) as info:
        prof.validate_profile(p)
    assert [e for e in info.value.problems if e.field == field], info.value.problems


def test_the_safe_reaction_defaults_to_zero_and_brake_carries_its_channel() -> None:
    p = relbot()
    assert "safety" not in p
    assert prof.safe_reaction(p) == prof.SafeReaction("zero", 0, 0)
    p["safety"] = {"reaction": "brake", "brake_channel": 3}  # channel 3: RELbot's spare
    prof.validate_profile(p)
    assert prof.safe_reaction(p) == prof.SafeReaction("brake", 1, 3)


def test_the_reactions_a_profile_may_name_are_the_headers() -> None:
    """The validator reads watch.h's XRF_SAFE_REACTIONS from its text (no compiled binding
    needed); the binding's SAFE_REACTIONS is the same list."""
    from xrflab.channels import SAFE_REACTIONS

    assert prof._safe_reactions() == SAFE_REACTIONS
    assert prof.safe_reaction(None).number == SAFE_REACTIONS["zero"]


def _youbot_mechanics() -> dict[str, Any]:
    return {
        "kind": "youbot",
        "counts_per_rev": 4096,
        "gear_ratio": 1,
        "joints": [{"channel": k, "name": f"J{k}", "gear_ratio": 100, "zero_deg": 0} for k in range(1, 6)],
        "base": {
            "wheel_channels": [6, 7, 8, 9],
            "gear_ratio": 26,
            "wheel_diameter": 0.1,
            "half_wheel_base": 0.236,
            "half_track": 0.15,
        },
    }


def _mechanics_problems(mech: dict[str, Any]) -> set[str]:
    c = prof._Checker()
    prof._check_mechanics(c, mech)
    return {e.field for e in c.problems}


def test_youbot_mechanics_fields(monkeypatch: pytest.MonkeyPatch) -> None:
    """The youBot's mechanics (viz/kinematics.py Youbot): five joints and a four-wheel base on
    channels the bench has (XRF_MAX_CHANNELS of channels.h), each channel once."""
    monkeypatch.setattr(prof, "max_channels", lambda: 4)  # one ico board: no channel 5..9
    assert {"mechanics.joints[4].channel", "mechanics.base.wheel_channels[0].channel"} <= _mechanics_problems(
        _youbot_mechanics()
    )
    monkeypatch.setattr(prof, "max_channels", lambda: 12)  # three boards
    assert _mechanics_problems(_youbot_mechanics()) == set()
    bad = _youbot_mechanics()
    del bad["joints"][4]
    bad["base"]["wheel_channels"] = [6, 7, 8, 1]
    bad["base"]["half_track"] = 0
    assert _mechanics_problems(bad) == {
        "mechanics.joints",
        "mechanics.base.wheel_channels[3].channel",
        "mechanics.base.half_track",
    }
    del bad["base"]
    assert "mechanics.base" in _mechanics_problems(bad)


@pytest.mark.parametrize("value", [0, 2, -2, True, 0.5, "back"])
def test_first_pulse_is_a_sign(value: Any) -> None:
    """first_pulse (the sign of a motor check's first pulse) is 1 or -1; anything else is named."""
    p = copy.deepcopy(prof.load_profile("relbot"))
    p["channels"][0]["first_pulse"] = value
    with pytest.raises(prof.ProfileError) as info:
        prof.validate_profile(p)
    named = [e for e in info.value.problems if e.field == "channel 1.first_pulse"]
    assert named and "must be 1" in named[0].message, info.value.problems
    p["channels"][0]["first_pulse"] = -1
    assert prof.validate_profile(p)["channels"][0]["first_pulse"] == -1
