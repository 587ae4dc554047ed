"""Bench profiles: what is wired where on a bench (RELbot, Jiwy), read by the self-check, the 3D
view and odometry.

Defaults ship in ``deploy/profiles/<name>.json``. Educators edit copies: ``save_profile()``
writes ``<data>/profiles/<name>.json``, which then overrides the default of the same name
(``delete_profile()`` goes back to the default). Everything loaded or saved is validated first;
a bad value raises ``ProfileError`` whose ``problems`` are ``FieldError``s: the field's path
(``channel 1.duty``, ``limits.pwm_limit``, ``""`` for the profile as a whole) and a sentence an
educator can act on.

This is the bench-profile schema's one home and its only validator. The native checker gets a
validated profile in a flat form (``xrflab.profile_flat``) and checks no ranges; the hard limits
both sides respect are defined once in C (``rt_core/include/xrf/selfcheck_limits.h``, read here
through ``xrflab.selfcheck_limits``).
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ._cffi_build import rt_core_dir, xmacro_named
from .errors import Invalid
from .selfcheck_limits import hard_limits

REPO_ROOT = Path(__file__).resolve().parents[2]
DEFAULTS_DIR = REPO_ROOT / "deploy" / "profiles"

NAME_RE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,47}$")


@dataclass(frozen=True)
class FieldError:
    """One problem with a profile: the field it is about (its path, e.g. ``channel 1.duty``;
    ``""`` for the profile as a whole) and what is wrong, in words an educator can act on."""

    field: str
    message: str

    def as_dict(self) -> dict[str, str]:
        return {"field": self.field, "message": self.message}


class ProfileError(Invalid, ValueError):
    """A profile that cannot be used; ``problems`` lists every problem found (``errors``: their
    sentences). An XrfError (422) whose typed detail is ``{"message", "errors": [{"field",
    "message"}, ...]}``: the profile editor marks each field."""

    typed_detail = True  # ProfileNotFound: a plain 404 message

    def __init__(self, problems: Sequence[FieldError | str], source: str = "") -> None:
        self.problems = [p if isinstance(p, FieldError) else FieldError("", p) for p in problems]
        self.source = source
        head = f"{source}: " if source else ""
        text = head + "; ".join(self.errors)
        detail = {"message": text, "errors": [p.as_dict() for p in self.problems]} if self.typed_detail else None
        super().__init__(text, detail=detail)

    @property
    def errors(self) -> list[str]:
        return [p.message for p in self.problems]


class ProfileNotFound(ProfileError):
    """No profile of that name (neither an edited copy nor a default): 404."""

    status = 404
    typed_detail = False


@dataclass(frozen=True)
class ProfileInfo:
    name: str
    title: str
    robot: str
    path: Path
    source: str  # "default" (deploy/profiles) or "edited" (data folder)

    def as_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "title": self.title,
            "robot": self.robot,
            "path": str(self.path),
            "source": self.source,
        }


def default_data_dir() -> Path:
    """The appliance's data folder: xrflab.server.settings.default_data_dir (stdlib only)."""
    from .server.settings import default_data_dir as rule

    return rule()


def profiles_dir(data_dir: Path | None = None) -> Path:
    """Where edited profiles live: <data>/profiles."""
    return Path(data_dir or default_data_dir()) / "profiles"


# ---- validation ---------------------------------------------------------------------------------


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and v == v


def _is_int(v: Any) -> bool:
    return _is_num(v) and float(v).is_integer()


def _path(where: str, key: str) -> str:
    """The field path of `key` inside `where` ("profile" is the top level)."""
    return key if where == "profile" else f"{where}.{key}"


class _Checker:
    def __init__(self) -> None:
        self.problems: list[FieldError] = []

    def err(self, field: str, msg: str) -> None:
        self.problems.append(FieldError(field, msg))

    def num(
        self,
        obj: dict,
        where: str,
        key: str,
        lo: float,
        hi: float,
        *,
        required: bool = False,
        integer: bool = False,
        lo_open: bool = False,
    ) -> Any:
        field = _path(where, key)
        if key not in obj or obj[key] is None:
            if required:
                self.err(field, f"{where}.{key} is missing")
            return None
        v = obj[key]
        if not (_is_int(v) if integer else _is_num(v)):
            self.err(field, f"{where}.{key} must be a {'whole number' if integer else 'number'} (got {v!r})")
            return None
        if v < lo or v > hi or (lo_open and v == lo):
            lo_txt = f"above {lo:g}" if lo_open else f"at least {lo:g}"
            self.err(field, f"{where}.{key} = {v:g} is out of range: it must be {lo_txt} and at most {hi:g}")
            return None
        return v

    def boolean(self, obj: dict, where: str, key: str) -> Any:
        if key in obj and obj[key] is not None and not isinstance(obj[key], bool):
            self.err(_path(where, key), f"{where}.{key} must be true or false (got {obj[key]!r})")
            return None
        return obj.get(key)

    def string(self, obj: dict, where: str, key: str, *, required: bool = False) -> Any:
        field = _path(where, key)
        if key not in obj or obj[key] is None:
            if required:
                self.err(field, f"{where}.{key} is missing")
            return None
        if not isinstance(obj[key], str):
            self.err(field, f"{where}.{key} must be text (got {obj[key]!r})")
            return None
        return obj[key]

    def section(self, obj: dict, key: str) -> dict:
        v = obj.get(key)
        if v is None:
            return {}
        if not isinstance(v, dict):
            self.err(key, f"{key} must be an object")
            return {}
        return v


def validate_profile(profile: Any, source: str = "") -> dict[str, Any]:
    """Check a profile (the parsed JSON); returns it unchanged or raises ProfileError with all
    problems found, each with its field."""
    lim = hard_limits()
    c = _Checker()
    if not isinstance(profile, dict):
        raise ProfileError([FieldError("", "a bench profile is a JSON object")], source)
    fmt = profile.get("format", 1)
    if fmt != 1:
        c.err("format", f"format {fmt!r} is not known (this version reads format 1)")
    name = c.string(profile, "profile", "name", required=True)
    if name is not None and not NAME_RE.match(name):
        c.err("name", f"name {name!r} must be lower-case letters, digits, '-' or '_' (at most 48)")
    c.string(profile, "profile", "title")
    c.string(profile, "profile", "robot")
    c.string(profile, "profile", "description")

    limits = c.section(profile, "limits")
    pwm_limit = c.num(limits, "limits", "pwm_limit", 0, lim.max_duty, lo_open=True)
    if pwm_limit is None:
        pwm_limit = lim.max_duty
    pulse = c.section(profile, "pulse")
    c.num(pulse, "pulse", "period_us", lim.min_period_us, lim.max_period_us, integer=True)
    c.num(pulse, "pulse", "settle_ms", 0, lim.max_settle_ms, integer=True)
    c.num(pulse, "pulse", "reset_tolerance_counts", 0, 1000, integer=True)
    link = c.section(profile, "link")
    c.num(link, "link", "spi_speed_hz", 1000, 200_000_000, integer=True)
    c.num(link, "link", "echo_frames", 1, lim.max_frames, integer=True)
    c.num(link, "link", "timing_frames", 1, lim.max_frames, integer=True)
    c.num(link, "link", "warn_median_us", 0, 1e6)
    c.num(link, "link", "fail_median_us", 0, 1e6)
    c.num(link, "link", "warn_max_us", 0, 1e7)
    if (
        _is_num(link.get("warn_median_us"))
        and _is_num(link.get("fail_median_us"))
        and link["fail_median_us"] < link["warn_median_us"]
    ):
        c.err("link.fail_median_us", "link.fail_median_us must not be below link.warn_median_us")

    chans = profile.get("channels", [])
    if not isinstance(chans, list):
        c.err("channels", "channels must be a list")
        chans = []
    seen: set[int] = set()
    for i, ch in enumerate(chans):
        if not isinstance(ch, dict):
            c.err(f"channels[{i}]", f"channels[{i}] must be an object")
            continue
        _check_channel(c, i, ch, seen, pwm_limit)

    _check_safety(c, c.section(profile, "safety"), chans)

    mech = c.section(profile, "mechanics")
    if mech:
        _check_mechanics(c, mech)
    if c.problems:
        raise ProfileError(c.problems, source)
    return profile


def _check_channel(c: _Checker, i: int, ch: dict, seen: set[int], pwm_limit: float) -> None:
    lim = hard_limits()
    n = c.num(ch, f"channels[{i}]", "channel", 1, max_channels(), required=True, integer=True)
    where = f"channel {int(n)}" if n is not None else f"channels[{i}]"
    if n is not None:
        if n in seen:
            c.err(where, f"channel {int(n)} is listed twice")
        seen.add(int(n))
    c.string(ch, where, "name")
    c.string(ch, where, "connector")
    motor = c.boolean(ch, where, "motor")
    c.boolean(ch, where, "loopback")
    if "direction" in ch and ch["direction"] not in (1, -1) or isinstance(ch.get("direction"), bool):
        c.err(f"{where}.direction", f"{where}.direction must be 1 (positive PWM counts up) or -1 (counts down)")
    if "first_pulse" in ch and ch["first_pulse"] not in (1, -1) or isinstance(ch.get("first_pulse"), bool):
        c.err(
            f"{where}.first_pulse",
            f"{where}.first_pulse must be 1 (positive pulse first) or -1 (negative first: an axis parked "
            "on the stop positive PWM drives into)",
        )
    if motor:
        for key in ("duty", "duration_ms", "min_counts"):
            if key not in ch:
                c.err(f"{where}.{key}", f"{where}.{key} is missing (needed for a motor channel)")
    duty = c.num(ch, where, "duty", 0, lim.max_duty, lo_open=bool(motor))
    if duty is not None and duty > pwm_limit + 1e-12:
        c.err(f"{where}.duty", f"{where}.duty = {duty:g} is above limits.pwm_limit = {pwm_limit:g}")
    c.num(ch, where, "duration_ms", 1, lim.max_pulse_ms, integer=True)
    lo = c.num(ch, where, "min_counts", 1, 1e7, integer=True)
    hi = c.num(ch, where, "max_counts", 0, 1e9, integer=True)
    if lo is not None and hi and hi < lo:
        c.err(f"{where}.max_counts", f"{where}.max_counts ({hi}) is below min_counts ({lo})")
    elif hi and ch.get("min_counts") is None:
        # The bound is checked against min_counts, so it cannot stand alone (the checker's
        # default min_counts is not part of the schema).
        c.err(f"{where}.min_counts", f"{where}.min_counts is missing (needed with max_counts)")
    enc = ch.get("encoder")
    if enc is not None:
        if not isinstance(enc, dict):
            c.err(f"{where}.encoder", f"{where}.encoder must be an object")
        else:
            c.num(enc, f"{where}.encoder", "counts_per_rev", 1, 1e7, integer=True, lo_open=False)
            c.boolean(enc, f"{where}.encoder", "inverted")
    ins = ch.get("inputs")
    if ins is None:
        return
    if not isinstance(ins, list):
        c.err(f"{where}.inputs", f"{where}.inputs must be a list")
        return
    pins: set[int] = set()
    for j, pin in enumerate(ins):
        w = f"{where}.inputs[{j}]"
        if not isinstance(pin, dict):
            c.err(w, f"{where}.inputs: each entry must be an object")
            continue
        p = c.num(pin, w, "pin", 1, 2, required=True, integer=True)
        if p in pins:
            c.err(f"{w}.pin", f"{where}: input pin {int(p)} is listed twice")
        if p is not None:
            pins.add(int(p))
        c.string(pin, w, "name")
        if pin.get("idle") not in (None, 0, 1) or isinstance(pin.get("idle"), bool):
            c.err(f"{w}.idle", f"{where}.inputs pin {pin.get('pin')}: idle must be 0, 1 or null (not checked)")


def max_channels() -> int:
    """The most channels a bench has: XRF_MAX_CHANNELS of xrf/channels.h, read from its text as
    the safe reactions are (validating a profile needs no compiled binding)."""
    text = (rt_core_dir() / "include" / "xrf" / "channels.h").read_text()
    m = re.search(r"^#define XRF_MAX_CHANNELS\s+(\d+)", text, re.MULTILINE)
    if not m:
        raise RuntimeError("xrf/channels.h defines no XRF_MAX_CHANNELS")
    return int(m.group(1))


def _safe_reactions() -> dict[str, int]:
    # watch.h's XRF_SAFE_REACTIONS, read from the header's text: validating a profile needs no
    # compiled binding (channels.SAFE_REACTIONS is the same list through it).
    return xmacro_named("watch.h", "XRF_SAFE_REACTIONS")


def _check_safety(c: _Checker, safety: dict, chans: list) -> None:
    """safety.reaction: what the safety watcher does to the outputs when the loop dies or hangs
    (docs/developers/safety.md); `brake` needs the channel whose digital output engages it."""
    if not safety:
        return
    reaction = c.string(safety, "safety", "reaction")
    known = _safe_reactions()
    if reaction is not None and reaction not in known:
        c.err("safety.reaction", f"safety.reaction {reaction!r} is not one of {', '.join(known)}")
        return
    brake = c.num(safety, "safety", "brake_channel", 1, 4, integer=True, required=reaction == "brake")
    if brake is not None and reaction != "brake":
        c.err("safety.brake_channel", "safety.brake_channel only means something with safety.reaction 'brake'")
    if brake is not None and any(
        isinstance(ch, dict) and ch.get("channel") == brake and ch.get("motor") for ch in chans
    ):
        c.err(
            "safety.brake_channel",
            f"safety.brake_channel {brake} is a motor's channel: its digital output is the motor's",
        )


@dataclass(frozen=True)
class SafeReaction:
    """What the safety watcher does for a bench (the profile's safety section): the number of
    watch.h's XRF_SAFE_REACTIONS and, for `brake`, its channel (1..4; 0 otherwise)."""

    name: str
    number: int
    brake_channel: int
    # `hold` on a real bench (docs/developers/safety.md): the robot whose plant row's arm model
    # the watcher drives, the encoders' counts per motor turn (mechanics.counts_per_rev: the
    # same scale the 3D view uses) and the wiring, bit n for channel n + 1: encoder.inverted,
    # and direction -1 (a positive PWM counts down).
    # (Not part of what the reaction is: equal reactions compare equal whatever the wiring.)
    robot: str = field(default="", compare=False)
    counts_per_rev: int = field(default=0, compare=False)
    enc_inverted: int = field(default=0, compare=False)
    pwm_reversed: int = field(default=0, compare=False)


def safe_reaction(profile: dict[str, Any] | None) -> SafeReaction:
    """A validated profile's safe reaction; `zero` where it names none (or there is no profile)."""
    safety = (profile or {}).get("safety") or {}
    name = safety.get("reaction") or "zero"
    number = _safe_reactions()[name] if safety else 0  # zero is 0: the header says so too
    inverted = reversed_ = 0
    for ch in (profile or {}).get("channels") or []:
        bit = 1 << (int(ch["channel"]) - 1)
        inverted |= bit if (ch.get("encoder") or {}).get("inverted") else 0
        reversed_ |= bit if ch.get("direction") == -1 else 0
    return SafeReaction(
        name,
        number,
        int(safety.get("brake_channel") or 0),
        robot=str((profile or {}).get("robot") or ""),
        counts_per_rev=int(((profile or {}).get("mechanics") or {}).get("counts_per_rev") or 0),
        enc_inverted=inverted,
        pwm_reversed=reversed_,
    )


def bench_profile_name(plant: str, real_bench: bool) -> str:
    """The bench profile in force: on a real bench the one the appliance was started with
    (XRF_BENCH_PROFILE; "" when none), on a simulated one the plant's own."""
    return os.environ.get("XRF_BENCH_PROFILE", "") if real_bench else plant


def _check_mechanics(c: _Checker, mech: dict) -> None:
    c.num(mech, "mechanics", "counts_per_rev", 1, 1e7, required=True, integer=True)
    c.num(mech, "mechanics", "gear_ratio", 0, 1e4, required=True, lo_open=True)
    kind = mech.get("kind")
    if kind == "differential_drive":
        c.num(mech, "mechanics", "wheel_diameter", 0, 2.0, required=True, lo_open=True)
        c.num(mech, "mechanics", "track_width", 0, 5.0, required=True, lo_open=True)
        for key in ("left_channel", "right_channel"):
            c.num(mech, "mechanics", key, 1, 4, required=True, integer=True)
        for key in ("left_encoder_inverted", "right_encoder_inverted"):
            c.boolean(mech, "mechanics", key)
    elif kind == "pan_tilt":
        axes = mech.get("axes")
        if not isinstance(axes, dict) or not axes:
            c.err("mechanics.axes", "mechanics.axes must name each axis (pan, tilt)")
            return
        for axis, a in axes.items():
            w = f"mechanics.axes.{axis}"
            if not isinstance(a, dict):
                c.err(w, f"{w} must be an object")
                continue
            c.num(a, w, "channel", 1, 4, required=True, integer=True)
            c.num(a, w, "belt_ratio", 0, 100, required=True, lo_open=True)
            c.num(a, w, "zero_offset_counts", -1e9, 1e9, integer=True)
            lim = a.get("limits_deg")
            if lim is not None and not (
                isinstance(lim, list) and len(lim) == 2 and all(_is_num(x) for x in lim) and lim[0] < lim[1]
            ):
                c.err(f"{w}.limits_deg", f"{w}.limits_deg must be [low, high] in degrees")
    elif kind == "linear_stage":
        c.num(mech, "mechanics", "channel", 1, 4, required=True, integer=True)
        c.num(mech, "mechanics", "lead_m", 0, 1.0, required=True, lo_open=True)
        c.boolean(mech, "mechanics", "encoder_inverted")
        lim = mech.get("limits_m")
        if lim is not None and not (
            isinstance(lim, list) and len(lim) == 2 and all(_is_num(x) for x in lim) and lim[0] < lim[1]
        ):
            c.err("mechanics.limits_m", "mechanics.limits_m must be [low, high] in m")
    elif kind == "cell":
        _check_cell_axes(c, mech.get("axes"))
    elif kind == "youbot":
        _check_youbot(c, mech)
    elif kind is not None:
        c.err(
            "mechanics.kind",
            f"mechanics.kind {kind!r} is not known (differential_drive, pan_tilt, linear_stage, cell or youbot)",
        )


def _check_cell_axes(c: _Checker, axes: Any) -> None:
    """A production cell's axes: each a motor channel driving a revolute (rad) or prismatic (m)
    joint, `per_motor_rev` load units per motor revolution (the gear or screw lead folded in),
    the travel from the home switch's edge, and the input pin of its home switch."""
    if not isinstance(axes, list) or not 1 <= len(axes) <= 4:
        c.err("mechanics.axes", "mechanics.axes must be a list of 1 to 4 axes")
        return
    channels: set[int] = set()
    for i, ax in enumerate(axes):
        w = f"mechanics.axes[{i}]"
        if not isinstance(ax, dict):
            c.err(w, f"{w} must be an object")
            continue
        ch = c.num(ax, w, "channel", 1, 4, required=True, integer=True)
        if ch is not None and int(ch) in channels:
            c.err(f"{w}.channel", f"{w}: channel {int(ch)} is used by another axis")
        if ch is not None:
            channels.add(int(ch))
        c.string(ax, w, "name")
        if ax.get("joint") not in ("revolute", "prismatic"):
            c.err(f"{w}.joint", f"{w}.joint must be revolute or prismatic")
        c.num(ax, w, "per_motor_rev", 0, 10.0, required=True, lo_open=True)
        c.num(ax, w, "home_pin", 1, 2, required=True, integer=True)
        lim = ax.get("limits")
        if not (isinstance(lim, list) and len(lim) == 2 and all(_is_num(x) for x in lim) and lim[0] < lim[1]):
            c.err(f"{w}.limits", f"{w}.limits must be [low, high] (rad or m from the home switch)")


def _check_youbot(c: _Checker, mech: dict) -> None:
    """A mobile manipulator (viz/kinematics.py, Youbot): five arm joints, each a motor channel
    with its gear and the angle its counter's 0 stands for (the rest pose it was parked in), and
    a base on four mecanum wheels (front-left, front-right, rear-left, rear-right)."""
    top = max_channels()
    used: set[int] = set()

    def channel(d: dict, w: str) -> None:
        ch = c.num(d, w, "channel", 1, top, required=True, integer=True)
        if ch is not None and int(ch) in used:
            c.err(f"{w}.channel", f"{w}: channel {int(ch)} is used twice")
        if ch is not None:
            used.add(int(ch))

    joints = mech.get("joints")
    if not isinstance(joints, list) or len(joints) != 5:
        c.err("mechanics.joints", "mechanics.joints must list the arm's 5 joints (J1 .. J5)")
    if not isinstance(joints, list):
        joints = []
    for i, j in enumerate(joints):
        w = f"mechanics.joints[{i}]"
        if not isinstance(j, dict):
            c.err(w, f"{w} must be an object")
            continue
        channel(j, w)
        c.string(j, w, "name")
        c.num(j, w, "gear_ratio", 0, 1e4, required=True, lo_open=True)
        c.num(j, w, "zero_deg", -360, 360)
        c.boolean(j, w, "inverted")
        lim = j.get("limits_deg")
        if lim is not None and not (
            isinstance(lim, list) and len(lim) == 2 and all(_is_num(x) for x in lim) and lim[0] < lim[1]
        ):
            c.err(f"{w}.limits_deg", f"{w}.limits_deg must be [low, high] in degrees")
    base = mech.get("base")
    if not isinstance(base, dict):
        c.err("mechanics.base", "mechanics.base must describe the mecanum base (wheel_channels, ...)")
        return
    wheels = base.get("wheel_channels")
    if not isinstance(wheels, list) or len(wheels) != 4:
        c.err("mechanics.base.wheel_channels", "mechanics.base.wheel_channels must be 4 channels (FL, FR, RL, RR)")
    else:
        for k, ch in enumerate(wheels):
            channel({"channel": ch}, f"mechanics.base.wheel_channels[{k}]")
    c.num(base, "mechanics.base", "gear_ratio", 0, 1e4, required=True, lo_open=True)
    c.num(base, "mechanics.base", "wheel_diameter", 0, 2.0, required=True, lo_open=True)
    c.num(base, "mechanics.base", "half_wheel_base", 0, 5.0, required=True, lo_open=True)
    c.num(base, "mechanics.base", "half_track", 0, 5.0, required=True, lo_open=True)


# ---- finding, loading, saving -------------------------------------------------------------------


def _read(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ProfileError([f"cannot read it: {exc.strerror or exc}"], str(path)) from None
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ProfileError([f"not valid JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})"], str(path)) from None
    return validate_profile(obj, str(path))


def find_profile(name_or_path: str | Path, data_dir: Path | None = None) -> Path:
    """The file for a profile name (edited copy first, then the default) or a path as given."""
    s = str(name_or_path)
    if s.endswith(".json") or "/" in s or os.sep in s:
        p = Path(s).expanduser()
        if not p.exists():
            raise ProfileError(["no such file"], s)
        return p
    for folder in (profiles_dir(data_dir), DEFAULTS_DIR):
        p = folder / f"{s}.json"
        if p.exists():
            return p
    known = ", ".join(i.name for i in list_profiles(data_dir)) or "none"
    raise ProfileNotFound([f"no bench profile named {s!r} (known: {known})"])


def load_profile(name_or_path: str | Path, data_dir: Path | None = None) -> dict[str, Any]:
    """Load and validate a profile by name or path."""
    return _read(find_profile(name_or_path, data_dir))


def list_profiles(data_dir: Path | None = None) -> list[ProfileInfo]:
    """Every profile by name; an edited copy hides the default of the same name. Files that do
    not validate are left out (load them by path to see why)."""
    found: dict[str, ProfileInfo] = {}
    for folder, source in ((DEFAULTS_DIR, "default"), (profiles_dir(data_dir), "edited")):
        if not folder.is_dir():
            continue
        for p in sorted(folder.glob("*.json")):
            try:
                obj = _read(p)
            except ProfileError:
                continue
            found[p.stem] = ProfileInfo(p.stem, obj.get("title", p.stem), obj.get("robot", ""), p, source)
    return [found[k] for k in sorted(found)]


def save_profile(profile: dict[str, Any], data_dir: Path | None = None) -> Path:
    """Validate and write an edited profile to <data>/profiles/<name>.json (atomic replace)."""
    validate_profile(profile)
    folder = profiles_dir(data_dir)
    folder.mkdir(parents=True, exist_ok=True)
    dest = folder / f"{profile['name']}.json"
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".profile-", suffix=".json")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(profile, f, indent=2)
            f.write("\n")
        os.replace(tmp, dest)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return dest


def delete_profile(name: str, data_dir: Path | None = None) -> bool:
    """Remove an edited copy (the default comes back). True if there was one."""
    if not NAME_RE.match(name):
        raise ProfileError([f"bad profile name {name!r}"])
    try:
        (profiles_dir(data_dir) / f"{name}.json").unlink()
        return True
    except FileNotFoundError:
        return False
