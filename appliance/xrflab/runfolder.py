"""The one way the appliance touches a folder a guest can write: a run folder (and the run's own
/dev/shm folder). Issue 26, "guest-writable folders".

While a controller runs it can create, rename, link and delete anything in its run folder:
symlinks (to /etc/shadow, the room enrolment file, another run), FIFOs, hard links, deep trees,
names that are not UTF-8. Everything the appliance and its helpers do there - the host log
writer, the timing series, the 3D recorder, the console (output.txt), the ROS 2 bridge's output,
listings, downloads and conversions, the room's collections, the disk guard, clean-up - goes
through this module, which cannot leave the folder and takes plain files only:

- **Resolution** (`RunFolder`): the folder is opened once (a directory fd, ``O_NOFOLLOW``) and
  every name is resolved from that fd by ``openat2(RESOLVE_BENEATH | RESOLVE_NO_SYMLINKS |
  RESOLVE_NO_MAGICLINKS)``: the kernel refuses a symlink anywhere on the way and ``..`` out of
  the folder (ELOOP/EXDEV). Mount points are crossed: only the appliance mounts anything in a run
  folder (a size-limited file system, a test's tiny tmpfs); the guest's own mounts stay in its
  private mount namespace (guest.py makes it MS_PRIVATE). Where openat2 is missing (Linux
  < 5.6, or a seccomp filter that refuses it) the same is done by hand: one
  ``openat(O_NOFOLLOW | O_DIRECTORY)`` per folder from the folder's fd, ``O_NOFOLLOW`` on the last
  part. Names are plain relative names (`confine`): ``..``, empty parts and NUL are refused.
- **Plain files only**: what is opened is checked on the open descriptor (``fstat``): a regular
  file with one link (no FIFO, socket or device; no hard link to a file elsewhere), and for the
  files the appliance writes, owned by the appliance (a file the guest made in its place is
  refused, never appended to). Opens are ``O_NONBLOCK`` (a FIFO cannot block them) and
  ``O_NOCTTY``; ``O_TRUNC`` is never used (it would truncate before the checks): a rewrite is a
  new temporary file renamed over the old name inside the folder (`RunFolder.replace`), a
  truncation happens after the checks (`RunFolder.open(truncate=True)`).
- **Reading by descriptor, bounded**: reads take at most a given size (`read_bytes`); downloads
  stream from the opened descriptor, never by name (a swap after the check changes nothing); a
  file is memory-mapped only when nobody but the appliance can change it (`open_mappable`:
  otherwise its bytes are copied first), because a guest truncating a file under a mapping
  would kill the appliance with SIGBUS.
- **Listing without following** (`walk`, `walk_files`): folders are entered through their fd,
  never by path, so a folder swapped for a link between the listing and the descent is not
  entered; depth and entry counts are bounded.
- **Deleting without following** (`remove_tree`, `remove_folder`): ``unlinkat``/``rmdir`` relative
  to the folder's fd, folders entered through their fd; a link is removed, never its target.
- **Names that are not UTF-8** are shown escaped (`shown`: ``\\xNN`` for each byte that is not
  UTF-8, ``\\\\`` for a backslash) and taken back exactly (`unshown`): listed and downloadable,
  never a 500.

A module of its own at the package's top, standard library only (like guest.py): the launcher's
side (run_disk, run_limits) imports it with a bare python3, and it is not a logs concern.
"""

from __future__ import annotations

import ctypes
import errno
import os
import re
import secrets
import stat
from collections.abc import Iterator
from pathlib import Path

DIR_MODE = 0o770
# Files the appliance makes in a run folder: the guest (the folder's group) may read them, never
# write them (nobody but the appliance may change a file it maps or appends to), and never others.
FILE_MODE_MASK = 0o640

MAX_DEPTH = 32  # folders below the run folder a listing enters (logs sit 3-4 deep: home/x/logs/)
MAX_ENTRIES = 20_000  # entries a listing looks at before it stops (a normal run has < 20)
USAGE_DEPTH, USAGE_ENTRIES = 256, 1_000_000  # what the disk guard's count walks

# openat2(2): <linux/openat2.h>. New system calls have one number on every architecture.
_SYS_OPENAT2 = 437
_AT_FDCWD = -100
RESOLVE_NO_XDEV = 0x01
RESOLVE_NO_MAGICLINKS = 0x02
RESOLVE_NO_SYMLINKS = 0x04
RESOLVE_BENEATH = 0x08
RESOLVE = RESOLVE_BENEATH | RESOLVE_NO_SYMLINKS | RESOLVE_NO_MAGICLINKS
_O_PATH_FLAGS = os.O_PATH | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC  # all openat2 takes with O_PATH


class RunPathError(ValueError):
    """A name the appliance refuses to use in a run folder (it would leave the folder)."""


class _OpenHow(ctypes.Structure):
    _fields_ = [("flags", ctypes.c_uint64), ("mode", ctypes.c_uint64), ("resolve", ctypes.c_uint64)]


_libc = ctypes.CDLL(None, use_errno=True)  # an instance of our own: argtypes set here stay ours
_syscall = _libc.syscall
_syscall.restype = ctypes.c_long
_syscall.argtypes = [ctypes.c_long, ctypes.c_int, ctypes.c_char_p, ctypes.POINTER(_OpenHow), ctypes.c_size_t]
_have_openat2: bool | None = None  # probed on first use; `use_openat2` (tests) forces either way


def _openat2(dirfd: int, path: bytes, flags: int, mode: int, resolve: int) -> int:
    how = _OpenHow(flags, mode, resolve)
    for _ in range(16):
        fd = int(_syscall(_SYS_OPENAT2, dirfd, path, ctypes.byref(how), ctypes.sizeof(how)))
        if fd >= 0:
            return fd
        err = ctypes.get_errno()
        if err not in (errno.EAGAIN, errno.EINTR):  # EAGAIN: a rename raced RESOLVE_BENEATH
            raise OSError(err, os.strerror(err))
    raise OSError(errno.EAGAIN, os.strerror(errno.EAGAIN))


def openat2_available() -> bool:
    """The kernel has openat2 and lets us call it (else the O_NOFOLLOW walk is used)."""
    global _have_openat2
    if _have_openat2 is None:
        try:
            os.close(_openat2(_AT_FDCWD, b"/", os.O_PATH | os.O_DIRECTORY | os.O_CLOEXEC, 0, RESOLVE_NO_SYMLINKS))
            _have_openat2 = True
        except OSError:  # ENOSYS (an old kernel), EPERM (a seccomp filter), ...
            _have_openat2 = False
    return _have_openat2


def use_openat2(on: bool | None) -> None:
    """Force the fallback walk (False), or probe openat2 again (None, True). For tests."""
    global _have_openat2
    _have_openat2 = False if on is False else None


# ---- names ----------------------------------------------------------------------------------


def confine(run_dir: str | Path, path: str) -> str:
    """`path` (as the loop published it) as a name relative to `run_dir`: under the run folder it
    stays, another absolute path is mapped into it, a relative one is taken from it. Raises
    RunPathError for ``..``, an empty name or a NUL byte."""
    if "\0" in path:
        raise RunPathError(f"log path {path!r} holds a NUL byte")
    if os.path.isabs(path):
        for root in {os.path.abspath(run_dir), os.path.realpath(run_dir)}:
            if path == root or path.startswith(root.rstrip("/") + "/"):
                path = path[len(root) :]
                break
    parts = [p for p in path.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise RunPathError(f"log path {path!r} leaves the run folder ('..')")
    if not parts:
        raise RunPathError(f"log path {path!r} names no file")
    return "/".join(parts)


def _parts(rel: str) -> list[str]:
    parts = rel.split("/")
    if not rel or any(p in ("", ".", "..") for p in parts) or "\0" in rel:
        raise RunPathError(f"{shown(rel)!r} is not a plain name under the run folder")
    return parts


_ESCAPED = re.compile(r"\\(\\|x[0-9a-fA-F]{2})")


def shown(rel: str) -> str:
    """A name from the file system (str, surrogate-escaped where it is not UTF-8) as text any
    JSON, header or page can hold: each byte that is not UTF-8 as ``\\xNN``, a backslash as
    ``\\\\``. `unshown` takes it back exactly."""
    out = []
    for ch in rel:
        c = ord(ch)
        if ch == "\\":
            out.append("\\\\")
        elif 0xDC80 <= c <= 0xDCFF:  # os.fsdecode's surrogateescape of the byte c - 0xDC00
            out.append(f"\\x{c - 0xDC00:02x}")
        elif 0xD800 <= c <= 0xDFFF:  # any other lone surrogate (not from the file system)
            out.append("\\x3f")
        else:
            out.append(ch)
    return "".join(out)


def unshown(name: str) -> str:
    """The file system name (surrogate-escaped str) a `shown` name stands for. A backslash not
    followed by ``\\`` or ``xNN`` is taken literally (a name typed by hand)."""

    def back(m: re.Match[str]) -> str:
        s = m.group(1)
        if s == "\\":
            return "\\"
        b = int(s[1:], 16)
        return chr(b) if b < 0x80 else chr(0xDC00 + b)

    return os.fsdecode(os.fsencode(_ESCAPED.sub(back, name)))


def _why(exc: OSError, rel: str) -> OSError:
    """`exc` with a message that says what the rule is (and the name, shown)."""
    err = exc.errno or errno.EIO
    if err == errno.ELOOP:
        text = "a symlink on the way (links in a run folder are never followed)"
    elif err == errno.EXDEV:  # RESOLVE_BENEATH
        text = "it would leave the run folder"
    elif err == errno.ENOTDIR:
        text = "not a folder on the way (or a symlink: links in a run folder are never followed)"
    else:
        text = exc.strerror or os.strerror(err)
    return OSError(err, f"{shown(rel)}: {text}")


# ---- the folder -----------------------------------------------------------------------------


class RunFolder:
    """A folder a guest can write, opened once; every name below it is resolved from that
    descriptor without following a symlink, and only plain files are opened. A context manager
    (the descriptor is closed at exit); safe to share between threads."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not str(path):
            raise FileNotFoundError(errno.ENOENT, "no run folder")
        # The folder's own path is the appliance's (<data>/runs/<id>); its last part is not
        # followed either.
        self.fd = os.open(self.path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1

    def __enter__(self) -> RunFolder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- resolution ---------------------------------------------------------------------------

    def _resolve(self, rel: str, flags: int, mode: int = 0) -> int:
        """The raw open of `rel` below the folder: no symlink, no '..', no mount crossing."""
        parts = _parts(rel)
        if flags & os.O_PATH:
            flags = (flags & _O_PATH_FLAGS) | os.O_NOFOLLOW | os.O_CLOEXEC
        else:
            flags |= os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NOCTTY
        if not flags & (os.O_CREAT | getattr(os, "O_TMPFILE", 0)):
            mode = 0
        try:
            if openat2_available():
                return _openat2(self.fd, os.fsencode(rel), flags, mode, RESOLVE)
            return _walk_open(self.fd, parts, flags, mode)
        except OSError as exc:
            raise _why(exc, rel) from None

    def _parent(self, rel: str, create: bool = False) -> tuple[int, str]:
        """(fd of the folder holding `rel`, its last part): for the *at calls on the name itself
        (unlinkat, renameat, mkdirat), which never follow it. The caller closes the fd."""
        parts = _parts(rel)
        if len(parts) == 1:
            return os.dup(self.fd), parts[0]
        folder = "/".join(parts[:-1])
        if create:
            self.makedirs(folder)
        return self._resolve(folder, os.O_RDONLY | os.O_DIRECTORY), parts[-1]

    def makedirs(self, rel: str, mode: int = DIR_MODE) -> None:
        """Make the folders of `rel` that are missing (none of them followed if a link)."""
        fd = os.dup(self.fd)
        done: list[str] = []
        try:
            for part in _parts(rel):
                done.append(part)
                try:
                    os.mkdir(part, mode, dir_fd=fd)
                except FileExistsError:
                    pass  # made meanwhile (by the loop, say): opened below like any other
                try:
                    nxt = os.open(part, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=fd)
                except OSError as exc:
                    raise _why(exc, "/".join(done)) from None
                os.close(fd)
                fd = nxt
        finally:
            os.close(fd)

    # -- files --------------------------------------------------------------------------------

    def open(
        self,
        rel: str,
        flags: int = os.O_RDONLY,
        mode: int = 0o640,
        *,
        create_dirs: bool = False,
        own: bool = False,
        truncate: bool = False,
    ) -> int:
        """Open `rel` (a `confine`d name): a regular file with one link, else OSError. `flags`
        e.g. ``os.O_WRONLY | os.O_CREAT | os.O_APPEND``; `create_dirs` makes missing folders on
        the way; `own`: the file must be the appliance's (its owner is our uid: a file the
        guest made in its place is refused); `truncate`: emptied after the checks (never
        ``O_TRUNC``). Returns the fd (close-on-exec, blocking)."""
        if flags & os.O_TRUNC:
            raise ValueError("O_TRUNC truncates before the checks: use truncate=True or replace()")
        if create_dirs and "/" in rel:
            self.makedirs(rel.rsplit("/", 1)[0])
        # O_NONBLOCK: a FIFO must not hang the open (it is refused just below).
        fd = self._resolve(rel, flags | os.O_NONBLOCK, mode & FILE_MODE_MASK)
        try:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode):
                raise OSError(errno.EPERM, f"{shown(rel)} is not a plain file of the run (not a regular file)")
            if st.st_nlink != 1:
                raise OSError(errno.EPERM, f"{shown(rel)} is not a plain file of the run (a link to another file)")
            if own and st.st_uid != os.geteuid():
                raise OSError(errno.EPERM, f"{shown(rel)} is not the appliance's file (made by the run)")
            if truncate:
                os.ftruncate(fd, 0)
            os.set_blocking(fd, True)
        except BaseException:
            os.close(fd)
            raise
        return fd

    def lstat(self, rel: str) -> os.stat_result:
        """The entry `rel` itself (a symlink is not followed: its own stat); OSError if missing
        or not reachable without following a link."""
        fd = self._resolve(rel, os.O_PATH)
        try:
            return os.fstat(fd)
        finally:
            os.close(fd)

    def is_file(self, rel: str) -> bool:
        """`rel` is a plain file (regular, one link) reached without a link."""
        try:
            st = self.lstat(rel)
        except (OSError, RunPathError):
            return False
        return stat.S_ISREG(st.st_mode) and st.st_nlink == 1

    def read_bytes(self, rel: str, limit: int) -> bytes:
        """The whole file if it holds at most `limit` bytes, else OSError(EFBIG)."""
        fd = self.open(rel)
        try:
            data = _read_at_most(fd, limit + 1)
        finally:
            os.close(fd)
        if len(data) > limit:
            raise OSError(errno.EFBIG, f"{shown(rel)} is over {limit} bytes")
        return data

    def replace(self, rel: str, data: bytes, mode: int = 0o640) -> None:
        """Write `rel` as a whole: a new file beside it (``O_EXCL``, never followed), renamed
        over the name inside the same folder (a link or FIFO planted there is replaced, never
        written through)."""
        parent, name = self._parent(rel, create=True)
        try:
            tmp = f".{name}.{secrets.token_hex(6)}.tmp"
            fd = os.open(
                tmp,
                os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                mode & FILE_MODE_MASK,
                dir_fd=parent,
            )
            try:
                with os.fdopen(fd, "wb") as f:
                    f.write(data)
                os.rename(tmp, name, src_dir_fd=parent, dst_dir_fd=parent)
            except BaseException:
                try:
                    os.unlink(tmp, dir_fd=parent)
                except OSError:
                    pass
                raise
        finally:
            os.close(parent)

    def open_mappable(self, rel: str, scratch: str | Path | None = None) -> int:
        """An fd of `rel` whose bytes nobody else can change while it is mapped: the file itself
        when only the appliance can write it (ours, not group- or world-writable, one link);
        otherwise a private copy of what it holds now (an unnamed file in `scratch`, default:
        the folder above the run folder, which is the appliance's). A guest that truncates a
        file under a mapping would make the reader fault (SIGBUS) and the appliance die."""
        fd = self.open(rel)
        st = os.fstat(fd)
        if st.st_uid == os.geteuid() and not st.st_mode & 0o022:
            return fd
        try:
            return _private_copy(fd, st.st_size, Path(scratch) if scratch else self.path.parent)
        finally:
            os.close(fd)

    def unlink(self, rel: str) -> None:
        """Remove the entry `rel` (a file, link or FIFO; never what a link points to)."""
        parent, name = self._parent(rel)
        try:
            os.unlink(name, dir_fd=parent)
        finally:
            os.close(parent)

    def rename(self, rel: str, new: str) -> None:
        """Rename `rel` to `new`, both below the folder (the entries themselves, not followed)."""
        src_parent, src = self._parent(rel)
        try:
            dst_parent, dst = self._parent(new, create=True)
            try:
                os.rename(src, dst, src_dir_fd=src_parent, dst_dir_fd=dst_parent)
            finally:
                os.close(dst_parent)
        finally:
            os.close(src_parent)

    # -- listing ------------------------------------------------------------------------------

    def walk(
        self, skip_top: tuple[str, ...] = (), max_depth: int = MAX_DEPTH, max_entries: int = MAX_ENTRIES
    ) -> Iterator[tuple[str, os.stat_result]]:
        """(relative name, lstat) of every entry below the folder, a folder before what it
        holds. Folders are entered through their fd (``O_NOFOLLOW``), never by path, so a link,
        or a folder swapped for one, is listed as what it is and never entered. `skip_top`:
        top-level names left out. Stops after `max_depth` levels and `max_entries` entries."""
        fd = os.open(".", os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC, dir_fd=self.fd)  # an offset of its own
        try:
            yield from _walk(fd, "", 0, skip_top, max_depth, [max_entries])
        finally:
            os.close(fd)

    def walk_files(
        self, skip_top: tuple[str, ...] = (), max_depth: int = MAX_DEPTH, max_entries: int = MAX_ENTRIES
    ) -> Iterator[tuple[str, os.stat_result]]:
        """`walk`, regular files with one link only (what `open` would take)."""
        for rel, st in self.walk(skip_top, max_depth, max_entries):
            if stat.S_ISREG(st.st_mode) and st.st_nlink == 1:
                yield rel, st

    def usage(self) -> int:
        """Bytes the folder's entries take on disk (st_blocks), as far as `walk` reaches: 256
        levels and a million entries (one descriptor per level; deeper than that the kernel's
        limits are the bound, see docs/developers/security.md)."""
        return sum(st.st_blocks * 512 for _, st in self.walk(max_depth=USAGE_DEPTH, max_entries=USAGE_ENTRIES))

    # -- removal ------------------------------------------------------------------------------

    def remove_tree(self, rel: str) -> None:
        """Remove `rel` and all it holds; links are removed, never followed."""
        parent, name = self._parent(rel)
        try:
            _remove_entry(parent, name)
        finally:
            os.close(parent)

    def clear(self) -> None:
        """Remove everything in the folder (the folder stays)."""
        _empty(self.fd)


# ---- helpers --------------------------------------------------------------------------------


def _walk_open(dirfd: int, parts: list[str], flags: int, mode: int) -> int:
    """openat2's rule by hand: each folder opened O_NOFOLLOW | O_DIRECTORY from the last."""
    fd = dirfd
    try:
        for part in parts[:-1]:
            nxt = os.open(part, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=fd)
            if fd != dirfd:
                os.close(fd)
            fd = nxt
        return os.open(parts[-1], flags, mode, dir_fd=fd)
    finally:
        if fd != dirfd:
            os.close(fd)


def _read_at_most(fd: int, n: int) -> bytes:
    chunks = []
    while n > 0:
        chunk = os.read(fd, min(n, 1 << 20))
        if not chunk:
            break
        chunks.append(chunk)
        n -= len(chunk)
    return b"".join(chunks)


def _private_copy(fd: int, size: int, scratch: Path) -> int:
    """An unnamed file in `scratch` holding the first `size` bytes of `fd` (fewer if it shrank)."""
    try:
        out = os.open(scratch, os.O_TMPFILE | os.O_RDWR | os.O_CLOEXEC, 0o600)
    except OSError:  # a file system without O_TMPFILE: a named file, unlinked at once
        import tempfile

        out, name = tempfile.mkstemp(dir=scratch)
        os.unlink(name)
    try:
        done = 0
        while done < size:
            try:
                n = os.copy_file_range(fd, out, size - done, done, done)
            except OSError as exc:
                if exc.errno not in (errno.EXDEV, errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP):
                    raise
                data = os.pread(fd, min(size - done, 1 << 20), done)
                n = os.pwrite(out, data, done) if data else 0
            if n <= 0:
                break
            done += n
    except BaseException:
        os.close(out)
        raise
    return out


def _is_dir_entry(dirfd: int, name: str) -> bool:
    try:
        return stat.S_ISDIR(os.stat(name, dir_fd=dirfd, follow_symlinks=False).st_mode)
    except FileNotFoundError:
        return False


def _remove_entry(dirfd: int, name: str) -> None:
    if _is_dir_entry(dirfd, name):
        sub = os.open(name, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=dirfd)
        try:
            _empty(sub)
        finally:
            os.close(sub)
        os.rmdir(name, dir_fd=dirfd)
    else:
        try:
            os.unlink(name, dir_fd=dirfd)
        except FileNotFoundError:
            pass


def _empty(dirfd: int) -> None:
    """Remove everything below `dirfd` without following a link, without recursion and with one
    descriptor at a time (a guest's tree may be thousands of folders deep): a folder is entered
    through its fd, and left through its ``..``, checked to be the folder it came from."""
    fd = os.open(".", os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC, dir_fd=dirfd)
    path: list[tuple[str, int, int]] = []  # per level entered: (its name, the parent's st_dev, st_ino)
    try:
        while True:
            sub_name = None
            with os.scandir(fd) as it:
                for e in it:
                    if e.is_dir(follow_symlinks=False):
                        sub_name = e.name
                        break
                    _unlink_quiet(fd, e.name)
            if sub_name is not None:
                try:
                    sub = os.open(sub_name, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=fd)
                except OSError as exc:
                    if exc.errno in (errno.ELOOP, errno.ENOTDIR):  # a link or file by now: it goes
                        _unlink_quiet(fd, sub_name)
                        continue
                    if exc.errno == errno.ENOENT:
                        continue
                    raise
                st = os.fstat(fd)
                path.append((sub_name, st.st_dev, st.st_ino))
                os.close(fd)
                fd = sub
                continue
            if not path:
                return  # the folder itself is empty
            name, dev, ino = path.pop()
            parent = os.open("..", os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=fd)
            os.close(fd)
            fd = parent
            st = os.fstat(fd)
            if (st.st_dev, st.st_ino) != (dev, ino):
                raise OSError(errno.EBUSY, "a folder was moved while it was being removed")
            try:
                os.rmdir(name, dir_fd=fd)
            except FileNotFoundError:
                pass
    finally:
        os.close(fd)


def _walk(
    fd: int, prefix: str, depth: int, skip_top: tuple[str, ...], max_depth: int, budget: list[int]
) -> Iterator[tuple[str, os.stat_result]]:
    try:
        it = os.scandir(fd)
    except OSError:
        return
    with it:
        for entry in it:
            if depth == 0 and entry.name in skip_top:
                continue
            budget[0] -= 1
            if budget[0] < 0:
                return
            try:
                st = entry.stat(follow_symlinks=False)
            except OSError:
                continue
            rel = prefix + entry.name
            yield rel, st
            if not stat.S_ISDIR(st.st_mode) or depth + 1 >= max_depth:
                continue
            try:
                sub = os.open(entry.name, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=fd)
            except OSError:  # swapped for a link, or removed, since: not entered
                continue
            try:
                yield from _walk(sub, rel + "/", depth + 1, skip_top, max_depth, budget)
            finally:
                os.close(sub)
            if budget[0] < 0:
                return


def _unlink_quiet(dirfd: int, name: str) -> None:
    try:
        os.unlink(name, dir_fd=dirfd)
    except FileNotFoundError:
        pass


# ---- module-level conveniences ----------------------------------------------------------------


def open_in(
    run_dir: str | Path,
    rel: str,
    flags: int = os.O_RDONLY,
    mode: int = 0o640,
    create_dirs: bool = False,
    own: bool = False,
) -> int:
    """`RunFolder(run_dir).open(rel, ...)` for a single open. Returns the fd."""
    with RunFolder(run_dir) as rf:
        return rf.open(rel, flags, mode, create_dirs=create_dirs, own=own)


def walk_files(run_dir: str | Path, skip_top: tuple[str, ...] = ()) -> list[tuple[str, os.stat_result]]:
    """(relative name, lstat) of every plain file below `run_dir` (`RunFolder.walk_files`)."""
    try:
        rf = RunFolder(run_dir)
    except OSError:
        return []
    with rf:
        return list(rf.walk_files(skip_top))


def folder_bytes(path: str | Path) -> int:
    """Disk use of a guest-writable folder (`RunFolder.usage`); 0 when it is gone."""
    try:
        rf = RunFolder(path)
    except OSError:
        return 0
    with rf:
        return rf.usage()


def remove_folder(path: str | Path) -> None:
    """Remove a guest-writable folder (a run folder, a run's /dev/shm folder) and all it holds,
    without following a link anywhere in it. Missing: nothing to do."""
    path = Path(path)
    try:
        parent = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    except FileNotFoundError:
        return
    try:
        _remove_entry(parent, path.name)
    finally:
        os.close(parent)


__all__ = [
    "FILE_MODE_MASK",
    "RunFolder",
    "RunPathError",
    "confine",
    "folder_bytes",
    "open_in",
    "openat2_available",
    "remove_folder",
    "shown",
    "unshown",
    "use_openat2",
    "walk_files",
]
