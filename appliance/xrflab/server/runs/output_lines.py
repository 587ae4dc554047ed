"""The loop's printed output cut into console lines, bounded.

The controller writes its stdout/stderr into a file of its run folder, and what it writes is the
guest's (docs/developers/security.md, "What a guest writes"): a line may never end (a gigabyte
without a newline), or a million empty lines may come in a second. The appliance holds at most one
line's worth of pending bytes, cuts longer lines, and passes the dashboards at most
``lines_per_poll`` lines per poll; the rest is counted and said, never queued. The file itself
keeps everything the disk limit allows (downloads of output.txt are whole).
"""

from __future__ import annotations

from dataclasses import dataclass, field

LINE_MAX = 1024  # bytes of one console line; a longer one is cut into pieces of this size
LINES_PER_POLL = 200  # lines per poll (100 ms) to the dashboards: 2000 lines/s, more than anyone reads


@dataclass
class OutputLines:
    """Bytes in, bounded lines out. ``skipped`` counts lines not passed on since the last report."""

    line_max: int = LINE_MAX
    lines_per_poll: int = LINES_PER_POLL
    skipped: int = 0
    _pending: bytearray = field(default_factory=bytearray)

    def feed(self, chunk: bytes, out: list[str]) -> None:
        """Append to ``out`` the complete lines in ``chunk`` (with what was pending) while ``out``
        holds fewer than ``lines_per_poll``; count the others in ``skipped``."""
        start = 0
        while start < len(chunk):
            nl = chunk.find(b"\n", start)
            end = len(chunk) if nl < 0 else nl
            room = self.line_max - len(self._pending)
            if end - start >= room:
                # A line longer than line_max: pass on what fits, the rest starts a new line.
                self._pending += chunk[start : start + room]
                self._emit(out)
                start += room
                continue
            self._pending += chunk[start:end]
            if nl < 0:
                break
            self._emit(out)
            start = nl + 1

    def flush(self, out: list[str]) -> None:
        """The last line when the output ends without a newline."""
        if self._pending:
            self._emit(out)

    def take_skipped(self) -> int:
        n, self.skipped = self.skipped, 0
        return n

    def _emit(self, out: list[str]) -> None:
        if len(out) < self.lines_per_poll:
            out.append(self._pending.decode("utf-8", "replace"))
        else:
            self.skipped += 1
        self._pending.clear()
