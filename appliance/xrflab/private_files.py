"""Data-folder files are private to the appliance's user, whatever the umask it was started with.

``xrf serve`` sets a 0o077 umask (cli_serve.serve); this is the explicit part for the files that
matter most, the SQLite databases, so that a store opened from any other entry point (tests, a
maintenance script) is private too. SQLite creates a database's ``-wal``, ``-shm`` and
``-journal`` with the database file's own mode (and chmods them to it, ignoring the umask), so
the file is created 0600 *before* SQLite opens it.
"""

from __future__ import annotations

import os
from pathlib import Path

DB_MODE = 0o600
SIDE_FILES = ("-wal", "-shm", "-journal")


def private_db(path: Path) -> None:
    """Create ``path`` (0600) if missing, else chmod it 0600; side files left by an older version
    with looser modes are tightened too."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, DB_MODE)
    try:
        os.fchmod(fd, DB_MODE)
    finally:
        os.close(fd)
    for suffix in SIDE_FILES:
        side = path.with_name(path.name + suffix)
        try:
            fd = os.open(side, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
        except OSError:  # missing (the usual case), or a link: never followed
            continue
        try:
            os.fchmod(fd, DB_MODE)
        finally:
            os.close(fd)
