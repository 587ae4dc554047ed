"""The one cffi binding of rt_core's channels.h, as every module of this package uses it.

``_cffi_build`` compiles channels.h's cffi part together with rt_core's own C files; ``ffi`` and
``lib`` here are that compiled module, loaded once. Nothing in this package writes a layout,
a constant or a ring operation down again: it reads them from ``lib`` and ``ffi``.
"""

from __future__ import annotations

from typing import Any, TypeAlias

from .. import _cffi_build

_binding = _cffi_build.load()
ffi = _binding.ffi
lib = _binding.lib

# A cffi cdata object (a pointer into the segment, a struct the C side filled): cffi has no static
# types for its fields, so this names the gap once instead of a bare Any at every signature.
CData: TypeAlias = Any


def c_str(ptr: CData) -> str:
    """A C string from the segment or from a C function, as text (bad UTF-8 replaced, not fatal)."""
    return str(ffi.string(ptr).decode("utf-8", "replace"))
