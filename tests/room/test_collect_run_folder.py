"""Issue 26, guest-writable folders: a bench packing a collection (room/collect.py, `pack_bench`)
reads run folders through the run folder's helper. What the loop planted there - a link to a
secret named like a log, output.txt replaced by a link, a folder link, a FIFO, a name that is
not UTF-8 - is never followed into the archive the room gets; the run's own files are. (A guard:
main already packed through open_in, so this passes there too.)"""

from __future__ import annotations

import os
import tarfile
import time
from pathlib import Path

from xrflab.room.collect import RunToPack, pack_bench

SECRET = b"enrolment key: signs room tokens\n"
LOG = b"x,y\n5,5\n" + b"\0" * 16 * 8  # an XRF2 .bin of 8 records


def test_a_collection_takes_the_runs_files_and_follows_no_link(tmp_path: Path) -> None:
    secret = tmp_path / "room" / "enrolment.json"
    secret.parent.mkdir()
    secret.write_bytes(SECRET)
    secret_log = tmp_path / "secret-log.bin"
    secret_log.write_bytes(LOG + SECRET)
    run = tmp_path / "runs" / "7"
    (run / "logs").mkdir(parents=True)
    (run / "logs" / "mine.bin").write_bytes(LOG)
    (run / os.fsdecode(b"bad\xff.bin")).write_bytes(LOG)
    (run / "output.txt").symlink_to(secret)
    (run / "stolen.bin").symlink_to(secret_log)
    (run / "elsewhere").symlink_to(tmp_path / "room")
    os.mkfifo(run / "fifo.bin")
    out = tmp_path / "bench.tar.gz"
    record = {"id": 7, "owner": "mallory"}
    t0 = time.monotonic()
    manifest = pack_bench("b1", "a1", [RunToPack("mallory", {"id": 1, "name": "p"}, 3, record, str(run))], ["csv"], out)
    assert time.monotonic() - t0 < 30, "a FIFO blocked the packing"
    with tarfile.open(out) as tar:
        names = tar.getnames()
        data = b"".join(tar.extractfile(m).read() for m in tar.getmembers() if m.isfile())  # type: ignore[union-attr]
    assert SECRET not in data and b"enrolment key" not in data
    assert "mallory/7/logs/logs/mine.bin" in names and "mallory/7/logs/logs/mine.csv" in names, names
    assert "mallory/7/logs/bad_.bin" in names, names  # the name made safe for the archive
    assert not [n for n in names if "stolen" in n or "elsewhere" in n or "fifo" in n or n.endswith("output.txt")]
    assert len(manifest["runs"]) == 1
