"""A file's SHA-256, read in chunks: what names a source version's files (versions.py) and what an
assignment's archive is checked against (assignments.py, the room's side too).

A module of its own, below both: the assignments on a bench are data, the versions a service over
the project store, and the one may not import the other (tests/lint/layers.py).
"""

from __future__ import annotations

import hashlib
from pathlib import Path


def sha256_file(p: Path) -> str:
    """The SHA-256 of a file's contents, read in chunks (versions, assignment archives)."""
    h = hashlib.sha256()
    with open(p, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 16), b""):
            h.update(chunk)
    return h.hexdigest()
