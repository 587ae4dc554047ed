"""One build's output: its log file, the lines kept for the diagnostics, the lines streamed.

Every line the build prints goes three ways, each bounded so a build that prints without end
costs the appliance nothing: the build's log file (up to ``LOG_MAX_BYTES``, then a note that it
was cut), the recent lines kept in memory for ``diagnostics.py`` and the result line, and the
browser's live view as ``build`` messages carrying the project's owner, so the hub gives them to
the owner (and educators) only (up to ``STREAM_MAX_LINES``, the last saying where the rest is).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TextIO

from .store import BuildRow

# The hub's publish (kind, payload), callable from the build's threads.
Publish = Callable[[str, dict[str, Any]], None]

LOG_MAX_BYTES = 4 << 20
STREAM_MAX_LINES = 4000
_KEPT_MAX = 20000  # lines kept in memory; beyond it the oldest 5000 go


class BuildLog:
    def __init__(self, logf: TextIO, publish: Publish, row: BuildRow) -> None:
        self._logf = logf
        self._publish = publish
        self._row = row
        self.lines: list[str] = []
        self._streamed = 0
        self._log_bytes = 0

    def __call__(self, line: str) -> None:
        self.lines.append(line)
        if len(self.lines) > _KEPT_MAX:
            del self.lines[:5000]
        if self._log_bytes < LOG_MAX_BYTES:
            self._logf.write(line + "\n")
            self._logf.flush()
            self._log_bytes += len(line) + 1
            if self._log_bytes >= LOG_MAX_BYTES:
                self._logf.write("… log truncated\n")
        if self._streamed < STREAM_MAX_LINES:
            self._streamed += 1
            row = self._row
            self._publish(
                "build",
                {
                    "build_id": row.id,
                    "project_id": row.project_id,
                    "owner": row.owner,
                    "line": line if self._streamed < STREAM_MAX_LINES else "… (more in the build log)",
                },
            )
