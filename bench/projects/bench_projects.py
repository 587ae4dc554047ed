"""Time from upload to a runnable build (base and 20-sim templates, cold and unchanged rebuild)
through a real appliance, and the archive checker's cost on a 50 MB archive.

    .venv/bin/python bench/projects/bench_projects.py [--repeat 3]

"cold" = a new project: upload, check, unpack, a fresh build folder, CMake configure + compile +
link in the sandbox (rt_core's install is cached, as on a running appliance). "unchanged" = Build
pressed again on the same source: the earlier build is reused.
"""

from __future__ import annotations

import argparse
import io
import os
import statistics
import sys
import tarfile
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(REPO / "appliance"), str(REPO / "tests")]

from xrf_testing.harness import shared_builds_root, start_server, stop_server  # noqa: E402
from xrf_testing.projects_support import reachable_tmp  # noqa: E402
from xrflab.projects import archive  # noqa: E402

TEMPLATES = {"base": REPO / "student_projects/templates/base", "20sim": REPO / "student_projects/templates/20sim"}


def targz(folder: Path) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        t.add(folder, arcname=folder.name, filter=lambda i: None if "/build" in i.name else i)
    return buf.getvalue()


def upload_to_runnable(http, data: bytes) -> tuple[float, float, float, dict]:  # noqa: ANN001
    t0 = time.perf_counter()
    r = http.post("/api/projects", files={"file": ("p.tar.gz", data, "application/gzip")})
    assert r.status_code == 201, r.text
    t_up = time.perf_counter() - t0
    pid = r.json()["project"]["id"]
    b = http.post(f"/api/projects/{pid}/builds").json()
    while b["status"] in ("queued", "building"):
        time.sleep(0.05)
        b = http.get(f"/api/projects/{pid}/builds/{b['id']}").json()
    assert b["status"] == "ok", b["result"]
    t_cold = time.perf_counter() - t0
    t1 = time.perf_counter()
    again = http.post(f"/api/projects/{pid}/builds").json()
    assert again["reused"]
    t_again = time.perf_counter() - t1
    return t_up, t_cold, t_again, b


def checker_50mb() -> dict[str, float]:
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "big.tar.gz"
        buf = io.BytesIO()
        with tarfile.open(fileobj=buf, mode="w:gz", compresslevel=1) as t:
            t.add(TEMPLATES["base"], arcname="p", filter=lambda i: None if "/build" in i.name else i)
            for i in range(25):  # incompressible: 25 x 2 MB -> a 50 MB archive
                data = os.urandom(2 << 20)
                info = tarfile.TarInfo(f"p/data/blob{i:02d}.bin")
                info.size = len(data)
                t.addfile(info, io.BytesIO(data))
        path.write_bytes(buf.getvalue())
        size = path.stat().st_size
        runs_check, runs_unpack = [], []
        for k in range(3):
            t0 = time.perf_counter()
            archive.check(path)
            runs_check.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            archive.unpack(path, Path(d) / f"out{k}")
            runs_unpack.append(time.perf_counter() - t0)
        return {
            "archive_mb": size / (1 << 20),
            "check_s": statistics.median(runs_check),
            "unpack_s": statistics.median(runs_unpack),
        }


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    print(f"machine: {os.cpu_count()} CPUs, {os.uname().sysname} {os.uname().release}")
    c = checker_50mb()
    print(
        f"checker on a {c['archive_mb']:.1f} MB tar.gz: check {c['check_s'] * 1000:.0f} ms "
        f"({c['archive_mb'] / c['check_s']:.0f} MB/s), check+unpack {c['unpack_s'] * 1000:.0f} ms (median of 3)"
    )
    server = start_server(reachable_tmp("bench"), shared_builds_root())
    try:
        # warm the rt_core install and the build user once (not part of any figure)
        upload_to_runnable(server.http, targz(TEMPLATES["base"]))
        print(
            f"{'template':8} {'upload+check (ms)':>18} {'cold: upload->runnable (s)':>28} {'unchanged rebuild (ms)':>24}"
        )
        for name, folder in TEMPLATES.items():
            data = targz(folder)
            rows = [upload_to_runnable(server.http, data) for _ in range(a.repeat)]
            up = statistics.median(r[0] for r in rows) * 1000
            cold = statistics.median(r[1] for r in rows)
            again = statistics.median(r[2] for r in rows) * 1000
            spread = f"[{min(r[1] for r in rows):.2f}..{max(r[1] for r in rows):.2f}]"
            print(f"{name:8} {up:18.0f} {cold:20.2f} {spread:>7} {again:24.1f}")
    finally:
        stop_server(server)
    return 0


if __name__ == "__main__":
    sys.exit(main())
