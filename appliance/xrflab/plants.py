"""The simulated plants, as rt_core's plant table (``rt_core/src/plants.c``) lists them.

This is the only list of plants on the Python side, and it is not written here: it is read
through the cffi binding (``_cffi_build``, ``xrf/plants.h``) from the table the simulated board
itself indexes. The CLI's ``--sim`` choices, the appliance's ``/api/plants`` and run requests, the
self-check's default and the dashboard's plant menu all come from ``names()``; adding a plant to
the C table adds it everywhere (docs/developers/adding-a-robot.md).

``enc_modulo()`` is the ico board's counter range (``XRF_ICO_ENC_MODULO`` in ``xrf/ico.h``).

The binding is loaded on first use, not at import: every ``xrf`` call imports the argument
parsers that use ``arg_type``.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from functools import lru_cache
from typing import Any


def _binding() -> Any:
    from . import _cffi_build

    return _cffi_build.load()


def enc_modulo() -> int:
    """The ico board's encoder counters wrap at this count (XRF_ICO_ENC_MODULO)."""
    return int(_binding().lib.XRF_ICO_ENC_MODULO)


@dataclass(frozen=True)
class Plant:
    """One row of the plant table: what a host needs to know, no behaviour."""

    id: int  # XRF_SIM id (xrf_sim_open), the row's position from 1
    name: str  # XRF_SIM=<name>; the bench profile and the example of the same name
    title: str
    axes: int  # motor channels wired, 1..axes
    state: tuple[str, ...]  # the plant state's values as "name unit", in mirror order
    channels: int = 4  # the bench it stands on (its row in plants.c), axes..XRF_MAX_CHANNELS

    def as_dict(self) -> dict[str, object]:
        return {
            "id": self.id,
            "name": self.name,
            "title": self.title,
            "axes": self.axes,
            "state": list(self.state),
            "channels": self.channels,
        }


@lru_cache(maxsize=1)
def plants() -> tuple[Plant, ...]:
    """Every plant, in table order."""
    b = _binding()
    _ffi, _lib = b.ffi, b.lib
    out = []
    info = _ffi.new("struct xrf_plant_info *")
    for plant_id in range(1, _lib.xrf_plant_count() + 1):
        if _lib.xrf_plant_describe(plant_id, info) != 0:
            raise RuntimeError(f"rt_core's plant table has no row {plant_id}")
        state = _ffi.string(info.state).decode()
        out.append(
            Plant(
                id=int(info.id),
                name=_ffi.string(info.name).decode(),
                title=_ffi.string(info.title).decode(),
                axes=int(info.axes),
                channels=int(info.channels),
                state=tuple(s.strip() for s in state.split(",") if s.strip()),
            )
        )
    return tuple(out)


def names() -> tuple[str, ...]:
    """The plant names, in table order (the first is the default plant)."""
    return tuple(p.name for p in plants())


def get(name: str) -> Plant:
    """The plant of this name; KeyError naming the known ones otherwise."""
    for p in plants():
        if p.name == name:
            return p
    raise KeyError(f"no simulated plant {name!r}; have: {', '.join(names())}")


def check_name(name: str) -> str:
    """`name` if it is a plant's name, else ValueError (for request models and argument parsers)."""
    if name not in names():
        raise ValueError(f"unknown simulated plant {name!r}; have: {', '.join(names())}")
    return name


def arg_type(value: str) -> str:
    """argparse ``type=`` for a ``--sim`` option: a plant's name (usage error otherwise)."""
    try:
        return check_name(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
