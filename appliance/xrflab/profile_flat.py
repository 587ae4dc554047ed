"""A validated bench profile in the flat form the native checker reads: one ``key=value`` per
line, keys the JSON paths (``limits.pwm_limit``, ``channel.1.duty``, ``channel.1.pin.2.idle``),
handed to ``xrf-selfcheck --profile -`` on its stdin.

Only what the checker uses is written and only what the profile sets: the checker's own
defaults fill the rest (rt_core/tools/selfcheck/selfcheck.c). The checker parses the form and
nothing else (profile_flat.c): it rejects an unknown key or a malformed value, but knows no
ranges; validation is ``xrflab.profiles.validate_profile``'s alone.
"""

from __future__ import annotations

from typing import Any

# The JSON fields the checker reads; the C side lists the same keys (profile_flat.c).
SECTION_KEYS = (
    "limits.pwm_limit",
    "pulse.period_us",
    "pulse.settle_ms",
    "pulse.reset_tolerance_counts",
    "link.echo_frames",
    "link.timing_frames",
    "link.warn_median_us",
    "link.fail_median_us",
    "link.warn_max_us",
)
CHANNEL_KEYS = (
    "name",
    "connector",
    "motor",
    "direction",
    "first_pulse",
    "duty",
    "duration_ms",
    "min_counts",
    "max_counts",
    "loopback",
)
NOT_CHECKED = -1  # an input pin's idle level when the profile gives none (null)


def _text(value: str) -> str:
    """A backslash as \\\\ and a control character as \\xHH: one value stays one line."""
    out = []
    for ch in value:
        if ch == "\\":
            out.append("\\\\")
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\x{ord(ch):02x}")
        else:
            out.append(ch)
    return "".join(out)


def _value(value: Any) -> str:
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, str):
        return _text(value)
    if isinstance(value, int) or (isinstance(value, float) and value.is_integer() and abs(value) < 2**53):
        return str(int(value))  # whole numbers as integers: the checker's integer fields want them so
    return repr(float(value))  # repr round-trips a double exactly


def flat_form(profile: dict[str, Any]) -> str:
    """The lines for a profile that ``validate_profile`` accepted."""
    lines = [f"# bench profile {profile.get('name', '')}: validated by xrflab.profiles, for xrf-selfcheck"]

    def put(key: str, value: Any) -> None:
        if value is not None:
            lines.append(f"{key}={_value(value)}")

    put("name", profile.get("name"))
    for key in SECTION_KEYS:
        section, field = key.split(".")
        put(key, (profile.get(section) or {}).get(field))
    for ch in profile.get("channels") or []:
        n = int(ch["channel"])
        for field in CHANNEL_KEYS:
            put(f"channel.{n}.{field}", ch.get(field))
        for pin in ch.get("inputs") or []:
            p = int(pin["pin"])
            put(f"channel.{n}.pin.{p}.name", pin.get("name"))
            idle = pin.get("idle")
            put(f"channel.{n}.pin.{p}.idle", NOT_CHECKED if idle is None else int(idle))
    return "\n".join(lines) + "\n"
