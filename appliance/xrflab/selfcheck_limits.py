"""The bench self-check's hard limits, from their one definition: the integer ``#define`` lines of
``rt_core/include/xrf/selfcheck_limits.h`` between its cffi markers, read through cffi (ABI mode:
integer constants need no compiled extension, so validating a profile needs no compiler).

The native checker clamps to the same constants whatever it is given; ``xrflab.profiles``
validates bench profiles against them with per-field errors.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

from ._cffi_build import extract_cdef, rt_core_dir

HEADER = "selfcheck_limits.h"


@dataclass(frozen=True)
class HardLimits:
    max_duty: float  # |duty| of a pulse, fraction of full scale
    max_pulse_ms: int
    max_settle_ms: int
    max_frames: int  # echo and timing frames
    min_period_us: int  # frame period of the timed steps
    max_period_us: int


@lru_cache(maxsize=1)
def hard_limits() -> HardLimits:
    import cffi  # here, not at import: `xrf` builds its parser from modules that import this one

    ffi = cffi.FFI()
    ffi.cdef(extract_cdef((rt_core_dir() / "include" / "xrf" / HEADER).read_text()))
    lib = ffi.dlopen(None)  # only constants are read: no symbol is looked up
    return HardLimits(
        max_duty=lib.XRF_SC_MAX_DUTY_PERMILLE / 1000.0,
        max_pulse_ms=lib.XRF_SC_MAX_PULSE_MS,
        max_settle_ms=lib.XRF_SC_MAX_SETTLE_MS,
        max_frames=lib.XRF_SC_MAX_FRAMES,
        min_period_us=lib.XRF_SC_MIN_PERIOD_US,
        max_period_us=lib.XRF_SC_MAX_PERIOD_US,
    )
