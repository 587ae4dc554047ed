"""A log converted in a process of its own, which ends with the conversion (the appliance's
downloads: server/http/logs.py).

Why a process: the rerun SDK never frees a recording made from Python (rerun-io/rerun#2116,
open): every `.rrd` conversion in the appliance left two recordings' threads and ~2.6 MB behind
for its lifetime (bench/appliance/practical.py: +4 threads and +2.6 MB a download), and a large
log's MAT or Parquet conversion peaks at hundreds of MB (+290 MB for a 625 000-record run) that
the allocator does not all give back. A child's memory returns when it exits.

What the child gets: the log as an already opened descriptor (the appliance opened it through
RunFolder: no link followed, a private copy where the loop could still change it), the format,
the target path in the appliance's own cache folder, the name to show, and the run's parameter
change table as JSON on stdin. It opens nothing in the run's folder itself.

    python -m xrflab.logs.convert_child FD FORMAT TARGET SHOWN_NAME < changes.json

Exit 0: written. Exit 3: the log is not one it can read (LogFormatError; its message on stderr).
Anything else: a failure (the traceback on stderr).

CSV is streamed, not cached (``csv_in_child``): TARGET ``-`` writes it to stdout, after one line
of JSON with what the reader skipped and lost (the response's headers); with parameter changes,
the two zip member names follow SHOWN_NAME. In a child because CSV is written by Arrow: pyarrow's
libraries are ~24 MB of the appliance's RSS for good once imported (issue 30 item 4), and the
appliance produces no Arrow or Parquet itself."""

from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any, BinaryIO, cast

from .layout import LogFormatError  # not .reader: this module is the child's and imports no NumPy

BAD_LOG = 3  # exit status: LogFormatError, message on stderr


class ConversionFailed(RuntimeError):
    """The child failed other than on the log's format (its last line of stderr says why)."""


_STDERR_MAX = 4000  # what a failure's message carries back of the child's stderr


# One heavy child of the appliance at a time (issue 30 item 4): a conversion child is 55-150 MB
# RSS, the rerun viewer's preparation (logs/rerun_files.py and its `rerun --serve-web`) ~160 MB,
# and a class downloading its logs at once would otherwise start one each, on a Pi with the
# appliance's 250 MB budget. The next waits (its request is pending: the browser shows the
# download or the viewer's page as loading), up to HEAVY_WAIT_S: a child held longer (a CSV stream
# to a client that stopped reading) does not stop everyone else's, the next then starts anyway.
HEAVY_WAIT_S = 120.0
HEAVY_POLL_S = 0.25  # how often a waiting request on the event loop looks again
_heavy = threading.BoundedSemaphore(1)


def acquire_heavy(timeout: float = HEAVY_WAIT_S) -> bool:
    """Blocking (off the event loop): True when this caller holds the turn and must
    ``release_heavy()``; False when it waited `timeout` and goes ahead anyway."""
    return _heavy.acquire(timeout=timeout)


def release_heavy() -> None:
    _heavy.release()


@contextlib.asynccontextmanager
async def heavy_turn(timeout: float = HEAVY_WAIT_S) -> AsyncIterator[None]:
    """``acquire_heavy`` for the event loop: waits without a thread, so a request cancelled while
    it waits leaves no turn taken behind it."""
    import asyncio  # here, not at the top: the child imports this module too, and asyncio is ~6 MB of it

    deadline = time.monotonic() + timeout
    turn = _heavy.acquire(blocking=False)
    while not turn and time.monotonic() < deadline:
        await asyncio.sleep(HEAVY_POLL_S)
        turn = _heavy.acquire(blocking=False)
    try:
        yield
    finally:
        if turn:
            _heavy.release()


def convert_in_child(fd: int, shown: str | Path, fmt: str, target: Path, changes: list[dict[str, Any]] | None) -> Path:
    """`convert(shown, fmt, target, log=<the log open as fd>, changes=changes)` in a child process
    (blocking, also while another heavy child runs: call it off the event loop). LogFormatError as
    convert() raises it; ConversionFailed for a child that failed otherwise."""
    env = _child_env()
    turn = acquire_heavy()
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "xrflab.logs.convert_child", str(fd), fmt, str(target), str(shown)],
            input=json.dumps(changes or []).encode(),
            pass_fds=(fd,),
            capture_output=True,
            env=env,
            check=False,
        )
    finally:
        if turn:
            release_heavy()
    err = proc.stderr.decode("utf-8", "replace").strip()[-_STDERR_MAX:]
    if proc.returncode == BAD_LOG:
        raise LogFormatError(err)
    if proc.returncode != 0:
        last = err.splitlines()[-1] if err else f"exit status {proc.returncode}"
        raise ConversionFailed(f"converting {Path(shown).name} to {fmt} failed: {last}")
    return target


# The child's allocators (issue 30 item 4; what the environment sets wins): glibc's malloc with
# two arenas, as the appliance itself (server/cli/serve.py), and Arrow's buffers from that malloc,
# not from Arrow's own pool, which kept what a Parquet conversion had freed (a 200 000-record log:
# 133 -> 99 MB RSS).
CHILD_ALLOCATORS = {"MALLOC_ARENA_MAX": "2", "ARROW_DEFAULT_MEMORY_POOL": "system"}


def _child_env() -> dict[str, str]:
    return dict(CHILD_ALLOCATORS) | dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))


STREAM_CHUNK = 1 << 20  # bytes read from the child at a time


def _failure(proc: subprocess.Popen[bytes], err: BinaryIO, what: str) -> Exception:
    """LogFormatError or ConversionFailed for an ended child, from its exit status and stderr."""
    err.seek(0)
    text = err.read().decode("utf-8", "replace").strip()[-_STDERR_MAX:]
    if proc.returncode == BAD_LOG:
        return LogFormatError(text)
    last = text.splitlines()[-1] if text else f"exit status {proc.returncode}"
    return ConversionFailed(f"{what} failed: {last}")


def csv_in_child(
    fd: int, shown: str | Path, changes: list[dict[str, Any]] | None, zip_names: tuple[str, str] | None = None
) -> tuple[dict[str, int], Iterator[bytes]]:
    """The CSV of the log open as `fd` (a zip with the change table when there are `changes`,
    its members `zip_names`), written by a child process: ({"skipped": n, "lost": n}, the bytes
    as chunks). Blocking until the child has read the log: call it off the event loop; the
    chunks too (Starlette iterates a plain iterator in its thread pool). LogFormatError (the log
    is not readable, or its segments differ) before anything is streamed; a child that fails
    mid-way ends the iterator with ConversionFailed. The child is killed when the iterator is
    closed before its end (the client went away). `fd` may be closed once this returns."""
    what = f"writing {Path(shown).name} as CSV"
    argv = [sys.executable, "-m", "xrflab.logs.convert_child", str(fd), "csv", "-", str(shown)]
    if changes:
        argv += list(zip_names or ("samples.csv", "param_changes.csv"))
    err = tempfile.TemporaryFile()  # a file, not a pipe: the child never blocks on it
    turn = acquire_heavy()  # held until the stream ends (end)
    try:
        proc = subprocess.Popen(
            argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err, pass_fds=(fd,), env=_child_env()
        )
    except BaseException:
        err.close()
        if turn:
            release_heavy()
        raise
    assert proc.stdin is not None and proc.stdout is not None
    out = cast(io.BufferedReader, proc.stdout)  # what Popen makes of a pipe (bufsize -1)
    ended = False

    def end() -> None:
        nonlocal ended
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        out.close()
        err.close()
        if turn and not ended:
            release_heavy()
        ended = True

    try:
        proc.stdin.write(json.dumps(changes or []).encode())
        proc.stdin.close()
        first = out.readline(4096)
        if not first.endswith(b"\n"):
            proc.wait()
            raise _failure(proc, err, what)
        counts = {k: int(v) for k, v in json.loads(first).items()}
    except BaseException:
        end()
        raise

    def chunks() -> Iterator[bytes]:
        try:
            while chunk := out.read1(STREAM_CHUNK):
                yield chunk
            if proc.wait() != 0:
                raise _failure(proc, err, what)
        finally:
            end()

    stream = chunks()
    # A stream dropped without being iterated (its response never started) runs no `finally`:
    # the child and the heavy-child turn are ended when it is collected.
    weakref.finalize(stream, end)
    return counts, stream


def _stream_csv(shown: str, fd: int, changes: list[dict[str, Any]], zip_names: list[str]) -> None:
    from .convert import iter_csv_chunks, iter_csv_zip_chunks
    from .reader import open_log

    log = open_log(shown, fd=fd)
    log.check_uniform()
    out = sys.stdout.buffer
    out.write(json.dumps({"skipped": len(log.skipped), "lost": log.lost}).encode() + b"\n")
    out.flush()
    log.release_pages()  # opening and counting read every page (LogFile.release_pages)
    if changes:
        names = (zip_names[0], zip_names[1])
        chunks = iter_csv_zip_chunks(log.path, changes, names, log=log)
    else:
        chunks = iter_csv_chunks(log.path, log=log)
    for chunk in chunks:
        out.write(chunk)
    out.flush()


# The formats the light child writes with the standard library only (logs/plain.py: no NumPy,
# pyarrow or scipy in the child, ~12 MB instead of 52-56; logs/rrdfile.py for .rrd: no NumPy,
# pyarrow or rerun SDK, ~25 MB instead of 90-118; issue 30 item 4); logs/convert.py does them when
# plain.py does not read the log (damage, an XRF2 .bin) and does the others (Parquet).
PLAIN_FORMATS = ("csv", "mat")


def main(argv: list[str]) -> int:
    fd, fmt, target, shown = int(argv[0]), argv[1], argv[2], argv[3]
    changes = json.loads(sys.stdin.read() or "[]")
    try:
        if fmt in PLAIN_FORMATS:
            from . import plain

            if plain.convert(shown, fd, fmt, target, changes, argv[4:6]):
                return 0
        elif fmt == "rrd" and target != "-":
            from . import rrdfile

            if rrdfile.convert(shown, fd, target, changes):
                return 0
        from .convert import convert
        from .reader import open_log

        if target == "-" and fmt == "csv":
            _stream_csv(shown, fd, changes, argv[4:6])
            return 0
        log = open_log(shown, fd=fd)
        log.release_pages()  # opening read every page (LogFile.release_pages): not kept while converting
        convert(shown, fmt, Path(target), log=log, changes=changes or None)
    except LogFormatError as exc:
        print(exc, file=sys.stderr)
        return BAD_LOG
    except BrokenPipeError:  # the appliance stopped reading (its client went away)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
