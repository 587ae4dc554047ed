"""A run folder that is a file system of its own: the kernel bounds what a run writes, from the
first byte, whoever writes it and in however many files.

Before the launcher starts, the run folder ``<data>/runs/<id>`` gets a sparse image
``<data>/run-images/<id>.img`` (``run_disk_mb``), made with mkfs.ext4 (at most ``run_files``
inodes) and mounted on it through a loop device (nosuid, nodev). The run, and the appliance's
own writers, see an ordinary folder; when it is full, write() says ENOSPC and nothing more lands
on the data folder's disk. A small part of it (`reserve_bytes`) is reserved for the appliance
(ext4's reserved blocks, root's by default): the host log writer can still drain the loop's log
ring after the controller filled its share, so the run's log stays whole up to the limit.

Why an image per run and not project quota or tmpfs (docs/developers/security.md, "Resources the
kernel bounds"): project quota needs a file system prepared for it (and this CI kernel has no
CONFIG_QFMT_V2 nor XFS quota), and in a root appliance the controller owns its files in the
initial user namespace, so it could move them to another project (FS_IOC_FSSETXATTR); tmpfs would
count the run's files as RAM on a 2 GB Pi. A file system's size is the one bound nothing inside
it can change.

When the run has ended (`release`), what it holds is copied to the folder underneath the mount
(found through a clone of the parent mount, ``open_tree``, so this works after a restart too),
without following a link and skipping what is not a file, folder or symlink; then the mount is
detached, the loop device frees itself (autoclear) and the image is deleted. What is left is an
ordinary run folder with everything the run wrote up to its limit. A restarted appliance
finishes what a killed one left (`sweep`): mounted run images, and images that lost their mount
(a reboot), are copied out and removed.

Needs CAP_SYS_ADMIN (root). Everything here is the standard library, ctypes and mkfs.ext4.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import os
import stat
import struct
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

from ... import guest
from ...runfolder import folder_bytes

IMAGES = "run-images"  # beside runs/ in the data folder
BLOCK = 4096
LOOP_CTL_GET_FREE = 0x4C82
LOOP_CONFIGURE = 0x4C0A
LO_FLAGS_AUTOCLEAR = 4
SYS_OPEN_TREE = 428  # the same number on every architecture (added after the tables were unified)
OPEN_TREE_CLONE = 1
OPEN_TREE_CLOEXEC = os.O_CLOEXEC
AT_EMPTY_PATH = 0x1000
MAX_DEPTH = 64  # folders nested deeper than this are not copied out (counted as skipped)


class DiskError(Exception):
    """The run's file system could not be set up; the message says why."""


@dataclass(frozen=True)
class DiskSpec:
    size_bytes: int
    files: int
    uid: int  # owner of the run folder (the appliance)
    gid: int  # its group (the loop's, so it may write: guest_spawn.prepare_dirs)
    reserve_for: int = 0  # the uid that may use the reserved blocks (the appliance)

    @property
    def reserve_bytes(self) -> int:
        """Reserved for the appliance (its host log writer), out of the run's reach: 5 %,
        between 1 MiB and 64 MiB."""
        return min(64 << 20, max(1 << 20, self.size_bytes // 20))


@dataclass
class Usage:
    size: int  # bytes the run may use in all (the file system less its own overhead)
    used: int
    available: int  # what the run itself may still write (the appliance's reserve excluded)
    files_left: int

    @property
    def full(self) -> bool:
        """No room left for the run: no inode, or less than 1 MiB (0.5 % of a large one) that
        ext4 would still give it (its allocator keeps a little back: the write that failed
        with ENOSPC leaves a few hundred KiB shown as available)."""
        return self.available < max(1 << 20, self.size // 200) or self.files_left <= 0


def image_for(data_dir: Path, run_id: int | str) -> Path:
    return data_dir / IMAGES / f"{run_id}.img"


def usage(run_dir: Path) -> Usage:
    st = os.statvfs(run_dir)
    size = st.f_blocks * st.f_frsize
    return Usage(size, (st.f_blocks - st.f_bfree) * st.f_frsize, st.f_bavail * st.f_frsize, st.f_favail)


def _mkfs(image: Path, spec: DiskSpec) -> None:
    blocks = spec.size_bytes // BLOCK
    reserve_pct = 100.0 * spec.reserve_bytes / spec.size_bytes
    cmd = [
        "mkfs.ext4",
        "-q",
        "-F",
        "-b",
        str(BLOCK),
        "-N",
        str(spec.files),
        "-m",
        f"{reserve_pct:.3f}",
        "-J",
        "size=4",  # the smallest journal ext4 takes with 4 KiB blocks
        # Nothing written ahead: the image stays sparse (noinit_itable at mount keeps it so).
        "-E",
        f"lazy_itable_init=1,lazy_journal_init=1,nodiscard,root_owner={spec.uid}:{spec.gid}",
        str(image),
        str(blocks),
    ]
    env = {"PATH": "/usr/sbin:/sbin:/usr/bin:/bin"}
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=60, env=env)
    if r.returncode != 0:
        raise DiskError(f"mkfs.ext4 failed: {(r.stderr or r.stdout).strip()[:300]}")
    if spec.reserve_for:  # ext4 gives its reserve to root unless told (mke2fs has no option for it)
        r = subprocess.run(
            ["tune2fs", "-u", str(spec.reserve_for), str(image)], capture_output=True, text=True, timeout=60, env=env
        )
        if r.returncode != 0:
            raise DiskError(f"tune2fs failed: {(r.stderr or r.stdout).strip()[:300]}")


def _loop_attach(image_fd: int) -> tuple[int, str]:
    """A free loop device backed by `image_fd`, freed by the kernel when its last user goes
    (LO_FLAGS_AUTOCLEAR: the mount, or our descriptor if the mount fails). (fd, /dev/loopN)."""
    ctl = os.open("/dev/loop-control", os.O_RDWR | os.O_CLOEXEC)
    try:
        for _ in range(16):  # another process may take the free device first: ask again
            n = fcntl.ioctl(ctl, LOOP_CTL_GET_FREE)
            path = f"/dev/loop{n}"
            fd = os.open(path, os.O_RDWR | os.O_CLOEXEC)
            info = bytearray(232)  # struct loop_info64
            struct.pack_into("<I", info, 52, LO_FLAGS_AUTOCLEAR)  # lo_flags
            config = struct.pack("<II", image_fd, 0) + bytes(info) + bytes(64)
            try:
                fcntl.ioctl(fd, LOOP_CONFIGURE, config)
                return fd, path
            except OSError as exc:
                os.close(fd)
                if exc.errno != errno.EBUSY:
                    raise
        raise DiskError("no free loop device")
    finally:
        os.close(ctl)


def open_dir(parent: int, name: str) -> int:
    """The folder `name` in `parent` (a descriptor), never through a symlink."""
    return os.open(name, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=parent)


def attach(runs: int, name: str, image: Path, spec: DiskSpec) -> None:
    """Make `image` (in a folder only we write) and mount it on the folder `name` in `runs`."""
    image.parent.mkdir(mode=0o700, exist_ok=True)
    try:
        with open(image, "xb") as f:
            f.truncate(spec.size_bytes)
        _mkfs(image, spec)
        mount_image(image, runs, name)
    except (OSError, subprocess.SubprocessError, DiskError) as exc:
        with contextlib.suppress(OSError):
            image.unlink()
        raise DiskError(f"cannot make the run's file system: {exc}") from exc


def mount_image(image: Path, runs: int, name: str) -> None:
    image_fd = os.open(image, os.O_RDWR | os.O_CLOEXEC | os.O_NOFOLLOW)
    try:
        loop_fd, device = _loop_attach(image_fd)
    finally:
        os.close(image_fd)
    try:
        target = open_dir(runs, name)
        try:
            guest.mount(device, f"/proc/self/fd/{target}", "ext4", guest.MS_NOSUID | guest.MS_NODEV, "noinit_itable")
        finally:
            os.close(target)
    finally:
        os.close(loop_fd)  # the mount holds the device now (or, failed, autoclear frees it)
    root = open_dir(runs, name)
    try:
        with contextlib.suppress(OSError):
            os.rmdir("lost+found", dir_fd=root)  # mkfs's, empty; not the run's
    finally:
        os.close(root)


def mounted(runs: int, name: str) -> bool:
    """The folder `name` in `runs` is the root of another file system (the run's)."""
    try:
        st = os.stat(name, dir_fd=runs, follow_symlinks=False)
    except OSError:
        return False
    return stat.S_ISDIR(st.st_mode) and st.st_dev != os.fstat(runs).st_dev


def is_mounted(run_dir: Path) -> bool:
    try:
        runs = os.open(run_dir.parent, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    except OSError:
        return False
    try:
        return mounted(runs, run_dir.name)
    finally:
        os.close(runs)


def _underneath(runs: int, name: str) -> int:
    """A descriptor of the folder the run's mount covers: opened in a clone of the runs folder
    (a bind mount of it without submounts: OPEN_TREE_CLONE without AT_RECURSIVE)."""
    libc = ctypes.CDLL(None, use_errno=True)
    tree = libc.syscall(
        ctypes.c_long(SYS_OPEN_TREE),
        ctypes.c_int(runs),
        b"",
        ctypes.c_uint(OPEN_TREE_CLONE | OPEN_TREE_CLOEXEC | AT_EMPTY_PATH),
    )
    if tree < 0:
        e = ctypes.get_errno()
        raise OSError(e, f"open_tree: {os.strerror(e)}")
    try:
        return open_dir(tree, name)
    finally:
        os.close(tree)


@dataclass
class CopyStats:
    files: int = 0
    folders: int = 0
    links: int = 0
    bytes: int = 0
    skipped: list[str] = field(default_factory=list)  # what was not copied, and why (the first few)
    skipped_count: int = 0

    def skip(self, name: str, why: str) -> None:
        self.skipped_count += 1
        if len(self.skipped) < 20:
            self.skipped.append(f"{name}: {why}")


def _copy_file(src: int, dst: int, size: int, budget: int) -> int:
    """Copy the data of `src` to `dst` keeping holes (SEEK_DATA/SEEK_HOLE); at most `budget`
    bytes. Returns the bytes copied."""
    done, pos = 0, 0
    while pos < size and done < budget:
        try:
            start = os.lseek(src, pos, os.SEEK_DATA)
        except OSError as exc:
            if exc.errno == errno.ENXIO:  # only a hole is left
                break
            raise
        end = os.lseek(src, start, os.SEEK_HOLE)
        os.lseek(dst, start, os.SEEK_SET)
        at = start
        while at < end and done < budget:
            n = os.sendfile(dst, src, at, min(end - at, 1 << 24, budget - done))
            if n <= 0:
                break
            at += n
            done += n
        pos = end
    os.ftruncate(dst, size)
    return done


def copy_tree(src_root: int, dst_root: int, budget: int) -> CopyStats:
    """Copy what is in `src_root` into `dst_root` (both folder descriptors): folders, regular
    files (their data, holes kept) and symlinks (as links, never followed); nothing else. Owner:
    `dst_root`'s; modes without set-id bits, readable by that owner. At most `budget` bytes of
    file data (a file linked many times counts each time)."""
    stats = CopyStats()
    owner = os.fstat(dst_root)
    work: list[tuple[int, int, str, int]] = [(os.dup(src_root), os.dup(dst_root), "", 0)]
    while work:
        src, dst, where, depth = work.pop()
        try:
            for name in sorted(os.listdir(src)):
                shown = f"{where}{name}"
                try:
                    st = os.stat(name, dir_fd=src, follow_symlinks=False)
                    mode = stat.S_IMODE(st.st_mode) & 0o770
                    if stat.S_ISDIR(st.st_mode):
                        if depth + 1 > MAX_DEPTH:
                            stats.skip(shown, f"nested deeper than {MAX_DEPTH} folders")
                            continue
                        with contextlib.suppress(FileExistsError):
                            os.mkdir(name, 0o700, dir_fd=dst)
                        s = os.open(name, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=src)
                        d = os.open(name, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=dst)
                        os.fchown(d, owner.st_uid, owner.st_gid)
                        os.fchmod(d, mode | 0o700)
                        work.append((s, d, shown + "/", depth + 1))
                        stats.folders += 1
                    elif stat.S_ISREG(st.st_mode):
                        if stats.bytes >= budget:
                            stats.skip(shown, "over what the run's file system held")
                            continue
                        s = os.open(name, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, dir_fd=src)
                        try:
                            if not stat.S_ISREG(os.fstat(s).st_mode):
                                stats.skip(shown, "changed while copied")
                                continue
                            d = os.open(
                                name,
                                os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC,
                                0o600,
                                dir_fd=dst,
                            )
                            try:
                                os.fchown(d, owner.st_uid, owner.st_gid)
                                os.fchmod(d, mode | 0o600)
                                stats.bytes += _copy_file(s, d, st.st_size, budget - stats.bytes)
                            finally:
                                os.close(d)
                        finally:
                            os.close(s)
                        os.utime(name, ns=(st.st_atime_ns, st.st_mtime_ns), dir_fd=dst, follow_symlinks=False)
                        stats.files += 1
                    elif stat.S_ISLNK(st.st_mode):
                        target = os.readlink(name, dir_fd=src)
                        os.symlink(target, name, dir_fd=dst)
                        os.chown(name, owner.st_uid, owner.st_gid, dir_fd=dst, follow_symlinks=False)
                        stats.links += 1
                    else:
                        stats.skip(shown, "not a file, folder or symlink")
                except OSError as exc:
                    stats.skip(shown, exc.strerror or str(exc))
        finally:
            os.close(src)
            os.close(dst)
    return stats


def release(runs: int, name: str, image: Path) -> CopyStats | None:
    """The run has ended: keep what its file system holds in the folder underneath, then
    detach the mount and delete the image. None when the folder had no mount of its own."""
    stats = None
    if mounted(runs, name):
        src = open_dir(runs, name)
        try:
            st = os.fstatvfs(src)
            dst = _underneath(runs, name)
            try:
                stats = copy_tree(src, dst, budget=(st.f_blocks - st.f_bfree) * st.f_frsize + (1 << 20))
            finally:
                os.close(dst)
            # Through the descriptor: the path is not looked up again (it is the appliance's).
            if guest._libc.umount2(f"/proc/self/fd/{src}".encode(), ctypes.c_int(guest.MNT_DETACH)) != 0:
                e = ctypes.get_errno()
                raise OSError(e, f"umount {name}: {os.strerror(e)}")
        finally:
            os.close(src)
    with contextlib.suppress(FileNotFoundError):
        image.unlink()
    return stats


def _backing_files() -> dict[str, str]:
    """/dev/loopN -> its backing file, for every loop device in use."""
    out = {}
    with contextlib.suppress(OSError):
        for dev in Path("/sys/block").iterdir():
            if dev.name.startswith("loop"):
                with contextlib.suppress(OSError):
                    out[f"/dev/{dev.name}"] = (dev / "loop" / "backing_file").read_text().strip()
    return out


def mounted_runs(runs_dir: Path, images_dir: Path) -> dict[str, Path]:
    """Run folder name -> image, for every run image of `images_dir` mounted in `runs_dir` now."""
    backing = _backing_files()
    out: dict[str, Path] = {}
    prefix = str(images_dir) + "/"
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/mountinfo").read_text().splitlines():
            left, _, right = line.partition(" - ")
            fields, rest = left.split(), right.split()
            if len(fields) < 5 or len(rest) < 2:
                continue
            point = Path(fields[4].replace("\\040", " "))
            image = backing.get(rest[1], "").removesuffix(" (deleted)")
            if point.parent == runs_dir and image.startswith(prefix):
                out[point.name] = Path(image)
    return out


def sweep(runs_dir: Path, images_dir: Path, live: set[str]) -> list[str]:
    """Finish what a killed appliance left of its run file systems (not those of the `live` run
    folders): mounted ones are copied out and removed; an image without a mount (a reboot) is
    mounted again first. Returns what was done, for the log."""
    done: list[str] = []
    try:
        runs = os.open(runs_dir, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    except OSError:
        return done
    try:
        for name, image in mounted_runs(runs_dir, images_dir).items():
            if name not in live:
                try:
                    release(runs, name, image)
                    done.append(f"kept run {name} (its file system was still mounted)")
                except OSError as exc:
                    done.append(f"run {name}: {exc}")
        for image in sorted(images_dir.glob("*.img")) if images_dir.is_dir() else []:
            name = image.stem
            if name in live or mounted(runs, name):
                continue
            try:
                with contextlib.suppress(FileNotFoundError):
                    os.close(open_dir(runs, name))
                    mount_image(image, runs, name)
                release(runs, name, image)
                done.append(f"kept run {name} (from its image)")
            except OSError as exc:
                done.append(f"lost run {name}: {exc}")
                with contextlib.suppress(OSError):
                    image.unlink()
    finally:
        os.close(runs)
    return done


def kept_bytes(runs_dir: Path) -> int:
    """Disk used by the kept run folders (mounted, live ones not counted). Each is walked through
    the run folder's helper (by descriptor, links never followed, bounded depth and count): a run
    allowed without a file system of its own is still the guest's while it runs."""
    total = 0
    try:
        dev = os.stat(runs_dir).st_dev
        names = os.listdir(runs_dir)
    except OSError:
        return 0
    for name in names:
        with contextlib.suppress(OSError):
            st = os.lstat(runs_dir / name)
            if stat.S_ISDIR(st.st_mode) and st.st_dev == dev:
                total += folder_bytes(runs_dir / name)
    return total
