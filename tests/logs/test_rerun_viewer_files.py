"""The rerun web viewer's files are prepared in bounded memory (server/http/rerun_files.py, issue 30
item 4): the wasm's URLs rewritten in place as bytes.replace would, and the preparing child no
longer holds the 43 MB wasm several times over."""

from __future__ import annotations

import gzip
import os
import random
import subprocess
import sys
from pathlib import Path

from xrflab.logs.rerun_files import VIEWER_FILES, WASM_URLS, gzip_beside, neutralise_wasm_file, offline_url


def _replaced(data: bytes) -> bytes:
    for url in WASM_URLS:
        data = data.replace(url, offline_url(url))
    return data


def test_in_place_rewrite_is_bytes_replace_across_chunk_edges(tmp_path: Path) -> None:
    rng = random.Random(7)
    parts = []
    for _ in range(400):
        parts.append(bytes(rng.randrange(256) for _ in range(rng.randrange(0, 40))))
        parts.append(rng.choice(WASM_URLS + (b"https://app.rerun.io/version/x", b"https://app.rerun.i")))
    data = b"".join(parts)
    path = tmp_path / "w.wasm"
    for chunk in (7, 16, 29, 64, 1 << 20):  # the URLs straddle chunk edges at every small size
        path.write_bytes(data)
        assert neutralise_wasm_file(path, chunk=chunk) == []
        assert path.read_bytes() == _replaced(data), chunk
    path.write_bytes(b"nothing to see")
    assert neutralise_wasm_file(path) == [u.decode() for u in WASM_URLS]


def test_gzip_beside(tmp_path: Path) -> None:
    path = tmp_path / "f.js"
    path.write_bytes(os.urandom(3 << 20))
    gzip_beside(path)
    assert gzip.decompress((tmp_path / "f.js.gz").read_bytes()) == path.read_bytes()


def test_the_preparing_child_stays_small(tmp_path: Path) -> None:
    """The child as the appliance runs it: every file there, the wasm neutralised, and its own
    peak RSS (it prints it) far below the 203 MB of the copy made in memory with the HTTP layer
    imported (bench/README.md, session 10: 42 MB). (Its `rerun --serve-web` is rerun's: ~115 MB.)"""
    folder = tmp_path / "viewer"
    proc = subprocess.run(
        [sys.executable, "-m", "xrflab.logs.rerun_files", str(folder)],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr.decode(errors="replace")
    for name in VIEWER_FILES:
        assert (folder / name).stat().st_size > 0
        if name != "index.html":  # the appliance rewrites and gzips index.html itself
            assert gzip.decompress((folder / (name + ".gz")).read_bytes()) == (folder / name).read_bytes()
    wasm = (folder / "re_viewer_bg.wasm").read_bytes()
    assert len(wasm) > 10 << 20
    assert b"https://tel.rerun.io/api/pog" not in wasm
    assert offline_url(b"https://tel.rerun.io/api/pog") in wasm
    peak_kib = int(proc.stdout.decode().rsplit("peak RSS KiB:", 1)[1])
    assert peak_kib < 80 * 1024, f"{peak_kib / 1024:.0f} MB"  # 42 MB here
