"""Builds the cffi binding of rt_core's channels (API mode) on first use and caches it.

The cdef is the text between the ``/* cffi-begin */`` and ``/* cffi-end */`` markers of each of
``HEADERS`` (``channels.h``: the layout and rings; ``watch.h``: the safety watcher; ``plants.h``:
the simulated plants) and the extension compiles rt_core's own C files (``SOURCES`` and every
``plant_*.c``), so Python uses the very layout, ring code, ico-board frames and plant table the
loop uses: nothing is written down twice.

The compiled module lives in ``$XRF_CACHE_DIR/<hash>/`` (default ``~/.cache/xrf-lab/cffi/<hash>/``)
where the hash covers those headers and sources, this script and the Python ABI. A file lock keeps
concurrent first imports (tests in parallel, the appliance and a CLI) from building over each
other.
"""

from __future__ import annotations

import fcntl
import hashlib
import importlib.util
import os
import re
import sys
import sysconfig
from pathlib import Path
from types import ModuleType

MODULE_NAME = "_xrf_channels"
CDEF_BEGIN = "/* cffi-begin */"
CDEF_END = "/* cffi-end */"

# Host-side helpers that channels.h does not need to offer the C runtime: plain Python attribute
# access compiles to ordinary loads and stores, which is not enough for the words that publish
# something (ready, ring heads) on a weakly ordered CPU such as the Pi's.
HELPERS_CDEF = """
uint32_t xrfpy_load_u32(const uint32_t *p);
uint64_t xrfpy_load_u64(const uint64_t *p);
void xrfpy_store_u32(uint32_t *p, uint32_t v);
void xrfpy_store_i64(int64_t *p, int64_t v);
"""
# ico.h's protocol constants Python needs, by name only: "..." makes cffi take each value from the
# compiled header (ico.h has no cffi markers; if it gains them, drop the line from here).
# hold.h's phases likewise (server/runs/watch_record.py names them in xrf-watch's record).
CONSTANTS_CDEF = """
#define XRF_ICO_ENC_MODULO ...
#define XRF_HOLD_PHASE_HOLD ...
#define XRF_HOLD_PHASE_CLOSING ...
#define XRF_HOLD_PHASE_REST ...
"""
HELPERS_SOURCE = """
uint32_t xrfpy_load_u32(const uint32_t *p) { return __atomic_load_n(p, __ATOMIC_ACQUIRE); }
uint64_t xrfpy_load_u64(const uint64_t *p) { return __atomic_load_n(p, __ATOMIC_ACQUIRE); }
void xrfpy_store_u32(uint32_t *p, uint32_t v) { __atomic_store_n(p, v, __ATOMIC_RELEASE); }
void xrfpy_store_i64(int64_t *p, int64_t v) { __atomic_store_n(p, v, __ATOMIC_RELEASE); }
"""


def rt_core_dir() -> Path:
    """rt_core beside the package (``<repo>/appliance/xrflab`` -> ``<repo>/rt_core``)."""
    override = os.environ.get("XRF_RT_CORE")
    if override:
        return Path(override).resolve()
    return Path(__file__).resolve().parents[2] / "rt_core"


# params.h/params.c: the parameter block (live tuning); first, because channels.h's struct xrf_shm
# holds one.
# logformat.c: the log file's segment header, which the host log writer writes and the reader
# reads with the loop's own definition (logformat.h comes after channels.h: it names
# struct xrf_log_meta).
# channels.c: rings, seqlock, commands. watch.c: the safety watcher, which sends the FPGA RESET
# through ico.c's frame builder and spidev.c's transport (the loop's own code for both).
# plants.c: the plant table, whose rows are in the plant files (PLANT_SOURCES, found by name so a
# new plant needs no edit here). The plant code is pure arithmetic: nothing of it runs in Python
# but the table's names and sizes.
# sim.h/sim_board.c: the simulated board as a transport the watcher's real-bench path can be
# given (xrf_watch_start_on), so that path is tested frame by frame without hardware.
HEADERS = ("params.h", "channels.h", "logformat.h", "watch.h", "plants.h", "sim.h")
SOURCES = (
    "params.c",
    "channels.c",
    "logformat.c",
    "watch.c",
    "hold.c",
    "ico.c",
    "spidev.c",
    "plants.c",
    "sim_board.c",
)
PLANT_SOURCES = "plant_*.c"


def _sources() -> tuple[list[Path], list[Path]]:
    rt = rt_core_dir()
    headers = [rt / "include" / "xrf" / name for name in HEADERS]
    sources = [rt / "src" / name for name in SOURCES] + sorted((rt / "src").glob(PLANT_SOURCES))
    for path in headers + sources:
        if not path.is_file():
            raise FileNotFoundError(
                f"{path} not found: xrflab.channels needs rt_core beside the package (or XRF_RT_CORE pointing at it)"
            )
    return headers, sources


# An X-macro list in the cffi part (channels.h's XRF_STATES, XRF_CMDS): `#define XRF_<LIST>S(X)`
# with one `X(NAME, ...)` per line continued by backslashes. cffi cannot parse a function-like
# macro, and the C side makes XRF_<LIST>_<NAME> and XRF_<LIST>_COUNT from the list.
XMACRO_RE = re.compile(r"^#define (XRF_[A-Z0-9_]+)S\(X\)((?:[^\n]*\\\n)*[^\n]*)$", re.MULTILINE)
XMACRO_ITEM_RE = re.compile(r"\bX\(\s*([A-Z][A-Z0-9_]*)\s*,")


def xmacro_constants(match: re.Match[str]) -> str:
    """The cdef for one X-macro list: its constants by name, each value ("...") taken from the
    compiled header, so the list itself is read once, from the header."""
    prefix, body = match.group(1), match.group(2)
    names = XMACRO_ITEM_RE.findall(body)
    if not names:
        raise ValueError(f"{prefix}S(X) lists no X(NAME, ...) item")
    return "".join(f"#define {prefix}_{name} ...\n" for name in [*names, "COUNT"])


XMACRO_NAMED_RE = re.compile(r'\bX\(\s*([A-Z][A-Z0-9_]*)\s*,\s*"([^"]*)"\s*,\s*(-?\d+)\s*\)')


def xmacro_named(header: str, list_name: str) -> dict[str, int]:
    """An X(NAME, "name", number) list of a header of rt_core as {name: number}, read from its
    text: for what needs the list without the compiled binding (validating a bench profile)."""
    text = (rt_core_dir() / "include" / "xrf" / header).read_text()
    for match in XMACRO_RE.finditer(text):
        if match.group(1) + "S" == list_name:
            return {name: int(number) for _, name, number in XMACRO_NAMED_RE.findall(match.group(2))}
    raise ValueError(f"{header} defines no {list_name}(X) list")


def extract_cdef(header_text: str) -> str:
    """The part of a header meant for cffi, its X-macro lists turned into constants."""
    start = header_text.find(CDEF_BEGIN)
    end = header_text.find(CDEF_END)
    if start < 0 or end < start:
        raise ValueError(f"header lacks the {CDEF_BEGIN} ... {CDEF_END} markers")
    return XMACRO_RE.sub(xmacro_constants, header_text[start + len(CDEF_BEGIN) : end])


def build_hash() -> str:
    headers, sources = _sources()
    digest = hashlib.sha256()
    for path in (*headers, *sources, Path(__file__).resolve()):
        digest.update(path.read_bytes())
    # The same home directory may serve several interpreters; an extension fits only one ABI.
    digest.update(sys.implementation.cache_tag.encode())
    digest.update(sysconfig.get_platform().encode())
    return digest.hexdigest()[:16]


def cache_dir() -> Path:
    base = os.environ.get("XRF_CACHE_DIR")
    root = Path(base) if base else Path.home() / ".cache" / "xrf-lab" / "cffi"
    return root / build_hash()


def _compile_into(target: Path) -> None:
    import cffi  # imported here: only a first build needs the compiler side of cffi

    headers, sources = _sources()
    ffi = cffi.FFI()
    for header in headers:
        ffi.cdef(extract_cdef(header.read_text()))
    ffi.cdef(HELPERS_CDEF)
    ffi.cdef(CONSTANTS_CDEF)
    ffi.set_source(
        MODULE_NAME,
        "".join(f'#include "xrf/{h.name}"\n' for h in headers)
        + '#include "xrf/ico.h"\n#include "xrf/hold.h"\n'
        + HELPERS_SOURCE,
        sources=[str(s) for s in sources],
        include_dirs=[str(headers[0].parent.parent)],
        extra_compile_args=["-O2", "-std=gnu11"],
        libraries=["pthread", "m"],
    )
    ffi.compile(tmpdir=str(target), verbose=False)


def _find_extension(directory: Path) -> Path | None:
    for candidate in sorted(directory.glob(MODULE_NAME + "*.so")):
        return candidate
    return None


def load() -> ModuleType:
    """Import the compiled binding, building it first if this source version has none yet."""
    if MODULE_NAME in sys.modules:
        return sys.modules[MODULE_NAME]
    target = cache_dir()
    target.mkdir(parents=True, exist_ok=True)
    done_marker = target / "complete"
    if not done_marker.exists():
        with open(target.parent / (target.name + ".lock"), "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            # Another process may have finished the build while this one waited for the lock.
            if not done_marker.exists():
                _compile_into(target)
                done_marker.write_text("ok\n")
    extension = _find_extension(target)
    if extension is None:
        raise ImportError(f"cffi build in {target} produced no {MODULE_NAME} extension")
    spec = importlib.util.spec_from_file_location(MODULE_NAME, extension)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sys.modules[MODULE_NAME] = module
    return module


if __name__ == "__main__":
    print(load().__file__)
