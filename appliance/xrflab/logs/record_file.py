"""A log file the host appends records to, which only ever ends at a whole record.

A write can fail part-way (disk full, I/O error, file too large). The file is then cut back to
its last complete record, so what was written stays decodable by the reader, and the caller
learns how many of the records it handed over made it (``PartialWrite``). The file is opened in
the run folder through its helper (``runfolder.open_in``: no symlink followed, a plain file of the
appliance's own, never group-writable): the loop names it, and must not be able to truncate it
under a reader that maps it.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..runfolder import open_in


class PartialWrite(Exception):
    """A write failed: `done` of the records handed over are in the file, the rest are not."""

    def __init__(self, done: int, error: OSError) -> None:
        super().__init__(str(error))
        self.done = done
        self.error = error


class RecordFile:
    def __init__(self, fd: int, stride: int) -> None:
        self.fd = fd
        self.stride = stride
        self.size = os.fstat(fd).st_size

    @staticmethod
    def open(run_dir: Path, rel: str, mode: int, stride: int) -> RecordFile:
        """`rel` (confined to the run folder already) for appending, made with `mode` and the
        folders on the way when missing."""
        fd = open_in(run_dir, rel, os.O_WRONLY | os.O_CREAT | os.O_APPEND, mode, create_dirs=True, own=True)
        try:
            return RecordFile(fd, stride)
        except OSError:
            os.close(fd)
            raise

    def write_all(self, data: bytes | memoryview) -> None:
        """All of `data` (a segment header, or records); raises OSError with what was written
        counted in ``size``."""
        view = memoryview(data)
        while view:
            n = os.write(self.fd, view)
            self.size += n
            view = view[n:]

    def append(self, records: memoryview, n: int) -> None:
        """`n` records; raises PartialWrite after cutting the file back to its last whole record."""
        before = self.size
        try:
            self.write_all(records)
        except OSError as exc:
            done = (self.size - before) // self.stride
            try:
                os.ftruncate(self.fd, before + done * self.stride)
            except OSError:
                pass
            raise PartialWrite(done, exc) from exc

    def close(self, sync: bool = False) -> None:
        if sync:
            try:
                os.fsync(self.fd)
            except OSError:
                pass
        os.close(self.fd)
