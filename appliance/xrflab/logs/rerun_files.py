"""The rerun web viewer's files, copied from rerun's own file server into a folder, in bounded
memory: the child process of the appliance that prepares the viewer (server/http/rerun.py
``_viewer_cache``), once per rerun version.

    python -m xrflab.logs.rerun_files FOLDER

starts ``rerun --serve-web`` (``logs.rerun_servers.RerunViewer``, 127.0.0.1), copies every file
of ``VIEWER_FILES`` into FOLDER, points the wasm's absolute URLs at the appliance
(``neutralise_wasm_file``), writes each file's gzip beside it, and stops the server. index.html is
left as rerun serves it: the appliance rewrites it (a few KB) and marks the folder ready.

Why streamed and why a module of its own (issue 30 item 4): the copy held the 43 MB wasm in memory
several times over (the HTTP response, each URL's ``bytes.replace``, the gzip), and the child
imported the appliance's HTTP layer (FastAPI, pydantic) to get at the code: 203 MB RSS at a
practical's first live viewer, on top of the appliance and ``--serve-web``. Here each file goes
through in ``CHUNK`` pieces, and only the standard library and rerun_servers are imported.
"""

from __future__ import annotations

import gzip
import shutil
import sys
import urllib.request
from pathlib import Path
from typing import BinaryIO

VIEWER_FILES = ("index.html", "re_viewer.js", "re_viewer_bg.wasm", "favicon.ico", "apple-touch-icon.png")
OFFLINE_PREFIX = "/rerun/offline/"
# Absolute URLs the viewer fetches by itself (found by recording a browser's requests, rerun 0.41):
# analytics, the "new version" check, the examples manifest, map tiles; then the bare web-app
# origin (links into app.rerun.io). Longer ones first: they contain the shorter.
WASM_URLS = (
    b"https://tel.rerun.io/api/pog",
    b"https://api.github.com/repos/rerun-io/rerun/releases/latest",
    b"https://app.rerun.io/version/",
    b"https://tile.openstreetmap.org/",
    b"https://app.rerun.io",
)
CHUNK = 1 << 20  # bytes of a file in memory at a time
FETCH_TIMEOUT_S = 120


def offline_url(url: bytes) -> bytes:
    """A same-origin path exactly as long as `url` (the wasm's strings keep their lengths)."""
    path = OFFLINE_PREFIX.encode() + url.split(b"://", 1)[1].replace(b"/", b"_")
    return (path + b"_" * len(url))[: len(url)]


def _occurrences(f: BinaryIO, needle: bytes, chunk: int) -> list[int]:
    """Offsets of `needle` in the file, non-overlapping, left to right (as bytes.replace finds
    them), reading `chunk` bytes at a time with an overlap of len(needle) - 1."""
    found: list[int] = []
    f.seek(0)
    base, carry, after = 0, b"", 0  # `after`: the first offset a next match may start at
    while block := f.read(chunk):
        buf = carry + block
        start = base - len(carry)
        pos = buf.find(needle, max(0, after - start))
        while pos >= 0:
            found.append(start + pos)
            after = start + pos + len(needle)
            pos = buf.find(needle, after - start)
        keep = min(len(buf), len(needle) - 1)
        carry = buf[len(buf) - keep :] if keep else b""
        base += len(block)
    return found


def neutralise_wasm_file(path: Path, chunk: int = CHUNK) -> list[str]:
    """Overwrite, in place and in order, each of WASM_URLS in the file with its offline_url (the
    same length, so nothing moves): the result of bytes.replace for each in turn. Returns the
    URLs not found (a newer rerun)."""
    missing = []
    with open(path, "r+b") as f:
        for url in WASM_URLS:
            offsets = _occurrences(f, url, chunk)
            if not offsets:
                missing.append(url.decode())
            for off in offsets:
                f.seek(off)
                f.write(offline_url(url))
            f.flush()
    return missing


def gzip_beside(path: Path) -> None:
    """`path`.gz, level 6, no name or time in its header (the same bytes every time)."""
    with open(path, "rb") as src, open(path.with_name(path.name + ".gz"), "wb") as dst:
        with gzip.GzipFile(filename="", mode="wb", fileobj=dst, compresslevel=6, mtime=0) as gz:
            shutil.copyfileobj(src, gz, CHUNK)


def fetch_to(url: str, path: Path) -> None:
    with urllib.request.urlopen(url, timeout=FETCH_TIMEOUT_S) as r, open(path, "wb") as out:  # noqa: S310 (127.0.0.1)
        shutil.copyfileobj(r, out, CHUNK)


def copy_viewer(folder: Path, web_port: int) -> list[str]:
    """Every viewer file from rerun's file server on `web_port` into `folder`, the wasm
    neutralised, the gzips beside them but index.html's (the appliance rewrites it). Returns the
    wasm URLs not found."""
    missing: list[str] = []
    for name in VIEWER_FILES:
        path = folder / name
        fetch_to(f"http://127.0.0.1:{web_port}/{name}", path)
        if name.endswith(".wasm"):
            missing = neutralise_wasm_file(path)
        if name != "index.html":
            gzip_beside(path)
    return missing


def peak_rss_kib() -> int:
    """This process's own peak RSS (VmHWM): not getrusage's ru_maxrss, which a child started by
    fork and exec inherits from its parent (Linux keeps the larger of the two)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    return 0


def main(argv: list[str]) -> int:
    from .rerun_servers import RerunViewer

    folder = Path(argv[0])
    folder.mkdir(parents=True, exist_ok=True)
    viewer = RerunViewer()
    try:
        missing = copy_viewer(folder, viewer.web_port)
    finally:
        viewer.stop()
    if missing:  # a newer rerun: the CSP still stops them in the browser (the appliance logs this line)
        print("URLs not found to neutralise: " + ", ".join(missing), file=sys.stderr)
    print(f"peak RSS KiB: {peak_rss_kib()}")  # for the benchmark and the test (the appliance ignores stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
