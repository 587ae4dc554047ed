"""Files the appliance writes or serves inside a run folder, whose contents the loop controls.

The loop is untrusted: it names its log file (``log_meta.path`` in the shared memory), and while
it runs it can create, rename and symlink anything in its run folder. So whatever the appliance
opens there on its behalf is

- **confined** by name (`confine`): an absolute path outside the run folder is mapped into it
  with the same layout (``/home/x/logs/log`` -> ``<run>/home/x/logs/log``, what the runtime's
  XenoFileHandler does too), a name under the run folder stays where it is, and a ``..`` part is
  refused (the runtime never publishes one: only a misbehaving loop does);
- **opened without following symlinks** (`open_in`): one ``openat(O_NOFOLLOW)`` per component,
  starting from the run folder itself, so a symlink (to another run, the accounts database, ...)
  planted anywhere on the way ends in ELOOP/ENOTDIR instead of a write or a read elsewhere; only a
  regular file with one link is accepted (no FIFO to block the writer, no hard link to a file
  outside);
- **listed without following symlinks** (`walk_files`).

A path a file was opened by (`fd_path`) names the opened file itself (``/proc/self/fd/N``), so a
rename or symlink swap after the checks changes nothing.
"""

from __future__ import annotations

import errno
import os
import stat
from collections.abc import Iterator
from pathlib import Path

DIR_MODE = 0o770
FILE_MODE_MASK = 0o660  # never world-readable, whatever mode the loop asks for


class RunPathError(ValueError):
    """A name the appliance refuses to open for the loop (it would leave the run folder)."""


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


def _open_dir(dir_fd: int, name: str, create: bool) -> int:
    flags = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        return os.open(name, flags, dir_fd=dir_fd)
    except FileNotFoundError:
        if not create:
            raise
    try:
        os.mkdir(name, DIR_MODE, dir_fd=dir_fd)
    except FileExistsError:
        pass  # made meanwhile (by the loop, say): opened below like any other
    return os.open(name, flags, dir_fd=dir_fd)


def open_in(
    run_dir: str | Path, rel: str, flags: int = os.O_RDONLY, mode: int = 0o640, create_dirs: bool = False
) -> int:
    """Open `rel` (a `confine`d name) under `run_dir` without following a symlink anywhere below
    the run folder; a regular file with one link only. `flags` e.g. ``os.O_WRONLY | os.O_CREAT |
    os.O_APPEND``; `create_dirs` makes missing folders on the way. Returns the fd (close-on-exec)."""
    parts = rel.split("/")
    if any(p in ("", ".", "..") for p in parts):
        raise RunPathError(f"{rel!r} is not a plain name under the run folder")
    fd = os.open(run_dir, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        for part in parts[:-1]:
            nxt = _open_dir(fd, part, create_dirs)
            os.close(fd)
            fd = nxt
        # O_NONBLOCK: a FIFO the loop put there must not hang the writer in open().
        f = os.open(parts[-1], flags | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK, mode & FILE_MODE_MASK, dir_fd=fd)
    except OSError as exc:
        if exc.errno in (errno.ELOOP, errno.ENOTDIR):
            raise OSError(
                exc.errno, f"{exc.strerror} (a symlink on the way? links in a run folder are never followed)"
            ) from None
        raise
    finally:
        os.close(fd)
    st = os.fstat(f)
    if not stat.S_ISREG(st.st_mode) or st.st_nlink != 1:
        os.close(f)
        raise OSError(
            errno.EPERM,
            f"{rel} is not a plain file of the run "
            f"({'a link to another file' if stat.S_ISREG(st.st_mode) else 'not a regular file'})",
        )
    os.set_blocking(f, True)
    return f


def fd_path(fd: int) -> str:
    """A path naming the open file `fd` itself (for libraries that take a path)."""
    return f"/proc/self/fd/{fd}"


def walk_files(run_dir: str | Path, skip_top: tuple[str, ...] = ()) -> Iterator[tuple[str, os.stat_result]]:
    """(relative name, lstat) of every regular file under `run_dir`; symlinks (to files or
    folders) are neither listed nor entered. `skip_top`: top-level names to leave out."""
    root = str(run_dir)
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        rel_dir = os.path.relpath(dirpath, root)
        if rel_dir == ".":
            dirnames[:] = [d for d in dirnames if d not in skip_top]
            filenames = [f for f in filenames if f not in skip_top]
        for name in filenames:
            try:
                st = os.lstat(os.path.join(dirpath, name))
            except OSError:
                continue
            if stat.S_ISREG(st.st_mode):
                yield (name if rel_dir == "." else f"{rel_dir}/{name}"), st


__all__ = ["RunPathError", "confine", "fd_path", "open_in", "walk_files"]
