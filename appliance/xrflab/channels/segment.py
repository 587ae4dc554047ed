"""A loop's segment as a file: where it is, mapping it, checking its layout, telling whose it is.

A name is reused, an object is not (docs/developers/architecture.md, "Whose segment"): a loop
creates its segment under its name, replacing a dead loop's leftover. So what is mapped is
remembered by (device, inode) — its ``identity`` — and compared with what the name points to now,
and a segment is removed only when it is still the one its loop process made.
"""

from __future__ import annotations

import errno
import fcntl
import mmap
import os
import stat
import sys
import time
from pathlib import Path

from .binding import CData, ffi, lib
from .errors import ChannelsCorrupt, ChannelsError

SHM_DIR = Path("/dev/shm")
# The appliance's own name for a run's sealed segment (server/runs/launch.py: segment_link), a link
# directly in /dev/shm to the memfd it made: "<the run's /dev/shm folder>" + this.
SEGMENT_LINK_SUFFIX = "-segment"
SHM_SIZE: int = ffi.sizeof("struct xrf_shm")

# (st_dev, st_ino) of one segment object.
Identity = tuple[int, int]


def shm_path(name: str) -> Path:
    """/dev/shm/<name>. A run started by the appliance has ``<run folder>/<name>``: its loop sees
    that folder of the host's /dev/shm as its own /dev/shm (xrflab.guest)."""
    parts = name.split("/") if name else []
    if not 1 <= len(parts) <= 2 or any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"bad shared-memory name {name!r} (a plain name, or folder/name)")
    return SHM_DIR.joinpath(*parts)


def identity(path: Path) -> Identity | None:
    """The object ``path`` names now, or None when there is none."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def try_map(path: Path) -> tuple[mmap.mmap | None, Identity | None]:
    """Map the segment at ``path`` read-write, or (None, None) while it is missing or being sized."""
    try:
        # The run's /dev/shm folder is the loop's to fill (issue 26): its name is not followed if
        # the loop made it a link (to a file of the appliance's, mapped read-write), nor opened
        # if it is not a regular file. The one link followed is the appliance's own name for a
        # run's sealed segment (launch.segment_link): directly in /dev/shm, where no loop reaches.
        follow = path.parent == SHM_DIR and path.name.endswith(SEGMENT_LINK_SUFFIX)
        flags = os.O_RDWR | os.O_NONBLOCK | os.O_CLOEXEC | (0 if follow else os.O_NOFOLLOW)
        fd = os.open(path, flags)
    except FileNotFoundError:
        return None, None
    except OSError as exc:
        raise ChannelsError(f"{path}: not the loop's shared memory object ({exc.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ChannelsError(f"{path}: not the loop's shared memory object (not a regular file)")
        size = st.st_size
        if 0 < size < SHM_SIZE:
            # Not a loop still sizing it (ftruncate is immediate): a loop built against another
            # layout. Say so instead of waiting for an object that will never fit.
            raise ChannelsError(
                f"{path}: {size} bytes, this host expects {SHM_SIZE}: the controller was built "
                "against another rt_core; rebuild it"
            )
        if size < SHM_SIZE:
            return None, None
        return mmap.mmap(fd, SHM_SIZE, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE), (st.st_dev, st.st_ino)
    finally:
        os.close(fd)


def check_layout(path: Path, shm: CData) -> None:
    """Refuse a segment that is not ours or that a loop built against another channels.h made."""
    if shm.magic != lib.XRF_SHM_MAGIC:
        raise ChannelsError(f"{path}: not an XRF shared-memory object (magic {shm.magic:#x})")
    if shm.version != lib.XRF_SHM_VERSION:
        raise ChannelsError(
            f"{path}: layout version {shm.version}, this host speaks {lib.XRF_SHM_VERSION} "
            "(rebuild the controller against this rt_core)"
        )
    if shm.size != SHM_SIZE:
        raise ChannelsError(f"{path}: layout size {shm.size} bytes, expected {SHM_SIZE}")


def take_geometry(where: str | Path, shm: CData, mapped: int) -> CData:
    """The geometry of the segment's fixed rings (telemetry, monitor), checked once against this
    layout and the mapping's size, in our own memory (a ``struct xrf_shm_geom *``): the readers
    use it and never read a ring's slots or slot size from the segment again (channels.h,
    "reading a segment"). ChannelsCorrupt when the loop's ring headers say otherwise."""
    geom = ffi.new("struct xrf_shm_geom *")
    rc = lib.xrf_shm_check(shm, mapped, geom)
    if rc == -errno.EINVAL:
        raise ChannelsError(f"{where}: {mapped} bytes mapped, the layout needs {SHM_SIZE}")
    if rc != 0:
        # Read once more, for the message only: what the loop claims now.
        rings = ", ".join(
            f"{name} ring {int(getattr(shm, name).slots)} slots of {int(getattr(shm, name).slot_size)} bytes"
            for name in ("telem_ring", "monitor_ring")
        )
        raise ChannelsCorrupt(
            f"{where}: the segment's header or ring geometry is not this layout's ({rings}, "
            f"{int(shm.channels)} channels; the layout has "
            f"{lib.XRF_TELEM_SLOTS} x {ffi.sizeof('struct xrf_telemetry')} and "
            f"{lib.XRF_MONITOR_SLOTS} x {ffi.sizeof('struct xrf_monitor_line')}, 1..{lib.XRF_MAX_CHANNELS} channels)"
        )
    return geom


# F_SEAL_* (linux/fcntl.h): Python's fcntl has them from 3.8 on Linux.
SEALS = fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | fcntl.F_SEAL_SEAL


def create_sealed(label: str, channels: int | None = None) -> int:
    """A new segment for a loop the appliance starts: a memfd of the layout's size whose size is
    sealed (no shrink, no growth, no further seals), so the loop -- which maps it read-write --
    cannot truncate it under the appliance's mapping (SIGBUS on the next read). The loop gets
    the descriptor (XRF_SHM_FD) instead of creating /dev/shm/<name> itself. Close-on-exec: pass
    it on explicitly. `label`: its name in /proc/<pid>/fd (memfd:<label>). `channels`: the
    bench's channel count, written into the header (xrf_shm.channels), which the loop keeps;
    None leaves it to the loop (its plant's count)."""
    if channels is not None and not 1 <= channels <= lib.XRF_MAX_CHANNELS:
        raise ChannelsError(f"a bench has 1..{lib.XRF_MAX_CHANNELS} channels, not {channels}")
    fd = os.memfd_create(label, os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
    try:
        os.ftruncate(fd, SHM_SIZE)
        if channels is not None:
            offset = ffi.offsetof("struct xrf_shm", "channels")
            os.pwrite(fd, int(channels).to_bytes(4, sys.byteorder), offset)
        fcntl.fcntl(fd, fcntl.F_ADD_SEALS, SEALS)
    except BaseException:
        os.close(fd)
        raise
    return fd


def is_sealed(fd: int) -> bool:
    """The descriptor's size is sealed as create_sealed seals it."""
    try:
        return fcntl.fcntl(fd, fcntl.F_GET_SEALS) & SEALS == SEALS
    except OSError:  # not a memfd (a tmpfs file from shm_open)
        return False


def map_fd(fd: int, where: str | Path) -> mmap.mmap:
    """Map the segment behind descriptor `fd` (a run's sealed memfd: the appliance made it and
    fixed its size, so no one can shrink it under the mapping)."""
    size = os.fstat(fd).st_size
    if size < SHM_SIZE:
        raise ChannelsError(f"{where}: {size} bytes, the layout needs {SHM_SIZE}")
    return mmap.mmap(fd, SHM_SIZE, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)


def wait_ready(where: str | Path, mapping: mmap.mmap, wait_s: float) -> None:
    """Wait up to wait_s for the loop to initialise the mapped segment and publish ``ready``,
    its layout checked."""
    deadline = time.monotonic() + wait_s
    shm = ffi.from_buffer("struct xrf_shm *", mapping)
    try:
        while True:
            if lib.xrfpy_load_u32(ffi.addressof(shm, "magic")) == 0:
                waiting_for = "the loop to initialise it"
            else:
                check_layout(Path(str(where)), shm)
                if lib.xrfpy_load_u32(ffi.addressof(shm, "ready")):
                    return
                waiting_for = "the loop to mark it ready"
            if time.monotonic() >= deadline:
                raise ChannelsError(f"{where}: gave up after {wait_s:g} s waiting for {waiting_for}")
            time.sleep(0.01)
    finally:
        del shm


def attach(path: Path, wait_s: float) -> tuple[mmap.mmap, Identity | None]:
    """Map the segment at ``path`` once its loop has published ``ready`` (waiting up to wait_s),
    its layout checked; the mapping and the identity of the object mapped."""
    deadline = time.monotonic() + wait_s
    waiting_for = "the shared memory object to appear"
    while True:
        mapping, ident = try_map(path)
        if mapping is not None:
            shm = ffi.from_buffer("struct xrf_shm *", mapping)
            magic = lib.xrfpy_load_u32(ffi.addressof(shm, "magic"))
            if magic == 0:
                waiting_for = "the loop to initialise it"
            else:
                check_layout(path, shm)
                if lib.xrfpy_load_u32(ffi.addressof(shm, "ready")):
                    return mapping, ident
                waiting_for = "the loop to mark it ready"
            del shm
            mapping.close()
        if time.monotonic() >= deadline:
            raise ChannelsError(f"{path}: gave up after {wait_s:g} s waiting for {waiting_for}")
        time.sleep(0.01)


def remove_if_owned(name: str, pid: int) -> bool:
    """Unlink /dev/shm/<name> if it is the segment of loop process `pid` (`xrf run` after its
    controller exited: nothing needs the final state any more, the summary is printed; readers
    still attached keep their mapping). A segment a newer loop made under the name is left."""
    path = shm_path(name)
    mapping, ident = try_map(path)
    if mapping is None:
        return False
    try:
        shm = ffi.from_buffer("struct xrf_shm *", mapping)
        owned = shm.magic == lib.XRF_SHM_MAGIC and shm.info.pid == pid
        del shm
    finally:
        mapping.close()
    if owned and identity(path) == ident:
        try:
            path.unlink()
        except FileNotFoundError:
            return False
        return True
    return False
