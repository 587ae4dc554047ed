"""Runs and their logs through a real appliance: the host log writer, downloads in every format
against `xrf decode`, kill -9, the lost badge, disk full, damaged files, the rerun viewer."""

from __future__ import annotations

import contextlib
import io
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from xrf_testing.harness import Server, stop_server
from xrf_testing.logs_support import COST, PROBE, REPO, start, wait_for
from xrflab.logs import open_log


def _xrf_decode(path: Path, fmt: str, out: Path) -> bytes:
    env = dict(os.environ, PYTHONPATH=str(REPO / "appliance"))
    subprocess.run(
        [sys.executable, "-m", "xrflab.cli", "decode", str(path), "--to", fmt, "-o", str(out)],
        check=True,
        env=env,
        capture_output=True,
    )
    return out.read_bytes()


def _run_probe(server: Server, cycles: int = 400, **body: Any) -> dict[str, Any]:
    """A probe run driven to RUN, `cycles` more cycles, then stopped; returns the run's log info."""
    server.stop_run()
    run = server.start_run(PROBE, **body)
    for cmd in ("initialise", "start"):
        r = server.http.post("/api/runs/current/command", json={"cmd": cmd})
        assert r.status_code == 200 and r.json()["accepted"], r.text
    wait_for(lambda: server.http.get("/api/logs/runs?limit=1").json()[0]["state"] in ("RUN", "") or True)
    c0 = server.http.get(f"/api/logs/runs/{run['id']}").json()["run"]["cycles"]
    wait_for(
        lambda: server.http.get(f"/api/logs/runs/{run['id']}").json()["run"]["cycles"] > c0 + cycles, what="cycles"
    )
    return run


def _logs(server: Server, run_id: int) -> dict[str, Any]:
    r = server.http.get(f"/api/logs/runs/{run_id}")
    assert r.status_code == 200, r.text
    return r.json()


def _check_probe(rec: np.ndarray) -> None:
    c = rec["cycle_2"]
    assert np.array_equal(rec["count"], c.astype(np.int32))
    assert np.array_equal(rec["flag"], (c & 1) == 1)
    assert np.array_equal(np.ascontiguousarray(rec["letter"]).view(np.uint8), (97 + c % 26).astype(np.uint8))
    assert np.array_equal(rec["ratio"], c.astype(np.float32) * np.float32(0.5))
    assert np.array_equal(rec["value"], c * 0.25)


def test_round_trip_every_format_matches_xrf_decode(server: Server, tmp_path: Path) -> None:
    run = _run_probe(server)
    server.stop_run()
    info = _logs(server, run["id"])
    r = info["run"]
    assert r["status"] == "ended" and not r["live"] and r["log_lost"] == 0 and r["log_note"] == ""
    assert len(info["files"]) == 1
    f = info["files"][0]
    assert f["kind"] == "xrflog" and f["skipped"] == [] and f["lost"] == 0 and f["records"] == r["log_records"] > 400
    path = Path(r["run_dir"] if "run_dir" in r else server.data_dir / "runs" / str(run["id"])) / f["name"]
    path = server.data_dir / "runs" / str(run["id"]) / f["name"]
    log = open_log(path)
    assert np.array_equal(log.records["seq"], np.arange(len(log.records), dtype=np.uint64))
    _check_probe(log.records)
    assert log.segments[0].header["run"] == str(run["id"]) and log.segments[0].header["program"]
    url = f"/api/logs/runs/{run['id']}/files/{f['name']}"
    raw = server.http.get(url, params={"fmt": "raw"})
    assert raw.status_code == 200 and raw.content == path.read_bytes()
    for fmt in ("csv", "parquet", "mat", "rrd"):
        got = server.http.get(url, params={"fmt": fmt}, timeout=120)
        assert got.status_code == 200, got.text
        assert f".{fmt}" in got.headers["content-disposition"]
        want = _xrf_decode(path, fmt, tmp_path / f"decoded.{fmt}")
        if fmt in ("csv", "parquet"):
            assert got.content == want, fmt
        elif fmt == "mat":
            # Byte for byte except the creation time in MAT's 116-byte text header.
            assert got.content[116:] == want[116:] and len(got.content) == len(want)
            import scipy.io

            m = scipy.io.loadmat(io.BytesIO(got.content))
            assert np.array_equal(m["value"].ravel(), log.records["value"])
        else:
            # rerun chunks carry fresh random ids: compare what the recordings hold.
            assert _rrd_values(got.content, tmp_path / "api.rrd") == _rrd_values(want, tmp_path / "cli.rrd")
            _check_viewer_link(server, run["id"], f["name"], got.content)
    if True:  # the CSV is the streamed one: its numbers read back exactly
        import pyarrow.csv as pcsv

        table = pcsv.read_csv(io.BytesIO(server.http.get(url, params={"fmt": "csv"}).content))
        assert np.array_equal(table.column("value").to_numpy(), log.records["value"])
    # The per-second framework timing series is kept beside the log.
    t = server.http.get(f"/api/logs/runs/{run['id']}/timing")
    assert t.status_code == 200 and b'"wakeup"' in t.content


def _check_viewer_link(server: Server, run_id: int, name: str, rrd: bytes) -> None:
    """The link rerun's web viewer is given (it sends no cookie and opens only a path ending in
    .rrd): the same download without a login, for that log only; anything else about it is a 404."""
    link = server.http.get(f"/api/logs/runs/{run_id}/viewer-link/{name}")
    assert link.status_code == 200, link.text
    path = link.json()["path"]
    assert path.startswith("/api/logs/viewer/") and path.endswith(".rrd"), path
    anonymous = httpx.Client(base_url=server.url, timeout=120)
    try:
        got = anonymous.get(path)
        assert got.status_code == 200 and got.content == rrd
        assert anonymous.head(path).status_code == 200
        token = path.split("/")[4]
        user_id, expires, mac = token.split(".")
        forged = [
            path.removesuffix(".rrd"),  # not the viewer's name for it
            path.replace(f"/{run_id}/", f"/{run_id + 1}/"),  # another run, the same link
            path.replace(token, f"{user_id}.{int(expires) + 1}.{mac}"),  # a longer life
            path.replace(token, f"{user_id}.{expires}.{'0' * len(mac)}"),
            path.replace(name, "other.xrf"),  # another file of the run
        ]
        for bad in forged:
            assert anonymous.get(bad).status_code == 404, bad
        assert anonymous.get(f"/api/logs/runs/{run_id}/files/{name}?fmt=rrd").status_code == 401
    finally:
        anonymous.close()
    assert server.http.get(f"/api/logs/runs/{run_id}/viewer-link/nothing.xrf").status_code == 404


def _rerun_threads(pid: int) -> int:
    """The rerun SDK's recording threads in process `pid` (RecordingStream, ChunkBatcher::...):
    two per recording, kept for the process's lifetime (rerun-io/rerun#2116)."""
    n = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(OSError):
            n += Path(f"/proc/{pid}/task/{tid}/comm").read_text().startswith(("RecordingStream", "ChunkBatcher"))
    return n


def _libraries(pid: int, *names: str) -> set[str]:
    """The shared libraries of process `pid` whose file name contains one of `names`."""
    found = set()
    for line in Path(f"/proc/{pid}/maps").read_text().splitlines():
        path = line.split(None, 5)[5] if len(line.split(None, 5)) > 5 else ""
        if any(n in Path(path).name for n in names):
            found.add(Path(path).name)
    return found


def _malloc_heaps(pid: int) -> int:
    """glibc's malloc arenas besides the main one in process `pid`: each is a heap at a 64 MiB
    boundary (HEAP_MAX_SIZE), anonymous and read-write from its start."""
    n = 0
    for line in Path(f"/proc/{pid}/maps").read_text().splitlines():
        f = line.split()
        if len(f) == 5 and f[1] == "rw-p" and int(f[0].split("-")[0], 16) % (64 << 20) == 0:
            n += 1
    return n


def test_conversions_leave_nothing_in_the_appliance(server: Server) -> None:
    """MAT, Parquet and .rrd are converted in a child process that ends with the conversion, and
    CSV is written by one as it streams: the appliance gains no rerun recording (each .rrd made
    in it kept two recordings' threads and ~2.6 MB for good: bench/appliance/practical.py) and
    loads neither Arrow's libraries nor rerun's (~24 MB each for good, issue 30 item 4) for a
    run nobody watched live and its downloads."""
    pid = server.proc.pid
    before = _rerun_threads(pid)
    for _ in range(3):
        run = _run_probe(server, cycles=200)
        server.stop_run()
        f = _logs(server, run["id"])["files"][0]
        url = f"/api/logs/runs/{run['id']}/files/{f['name']}"
        for fmt in ("rrd", "mat", "parquet", "csv"):
            got = server.http.get(url, params={"fmt": fmt}, timeout=120)
            assert got.status_code == 200 and len(got.content) > 0, (fmt, got.text)
    assert _rerun_threads(pid) == before, "a conversion left rerun recording threads in the appliance"
    assert not _libraries(pid, "libarrow", "libparquet", "rerun_bindings"), "Arrow or rerun loaded in the appliance"
    # Its threads share a bounded number of malloc arenas (server/cli/serve.py limit_malloc_arenas:
    # with glibc's default, 12-15 in an appliance after some runs, each keeping what was freed in it).
    if os.environ.get("MALLOC_ARENA_MAX", "2") == "2":
        assert _malloc_heaps(pid) <= 2, f"{_malloc_heaps(pid)} malloc arenas besides the main one"


def test_an_appliance_in_no_room_loads_no_cryptography(server: Server) -> None:
    """cryptography (its Rust extension, ~6 MB of the appliance's RSS) is the lab room's, for a
    bench enrolled in one (room/sso.py imports it when a key is first used): an appliance that
    never joined a room, after runs and downloads, does not map it (issue 30 item 4)."""
    run = _run_probe(server, cycles=200)
    server.stop_run()
    assert _logs(server, run["id"])["files"]
    mapped = [
        line.split(None, 5)[5]
        for line in Path(f"/proc/{server.proc.pid}/maps").read_text().splitlines()
        if len(line.split(None, 5)) > 5 and "/cryptography/" in line
    ]
    assert not mapped, f"cryptography loaded in the appliance: {sorted(set(mapped))[:3]}"


def _rrd_values(data: bytes, path: Path) -> dict[str, list[tuple[list[int], list[float]]]]:
    """entity -> [(cycles, values)] read back with rerun's own RRD reader, in file order."""
    from rerun.chunk import RrdReader

    path.write_bytes(data)
    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        if "Scalars:scalars" not in batch.schema.names:
            continue
        entity = batch.schema.metadata[b"rerun:entity_path"].decode()
        out.setdefault(entity, []).append(
            (batch.column("cycle").to_pylist(), [v[0] for v in batch.column("Scalars:scalars").to_pylist()])
        )
    assert out
    return out


def test_kill_9_mid_run_decodes_and_the_run_shows_crashed(server: Server) -> None:
    run = _run_probe(server, cycles=300)
    pid = server.http.get(f"/api/runs/{run['id']}").json()["pid"]
    os.kill(pid, signal.SIGKILL)
    r = wait_for(
        lambda: (lambda x: x if x["status"] != "running" else None)(_logs(server, run["id"])["run"]),
        what="the run to end",
    )
    assert r["status"] == "crashed" and r["crashed"] and r["crash_reason"] == "signal"
    listed = next(x for x in server.http.get("/api/logs/runs").json() if x["id"] == run["id"])
    assert listed["status"] == "crashed" and listed["log_lost"] == 0
    f = _logs(server, run["id"])["files"][0]
    path = server.data_dir / "runs" / str(run["id"]) / f["name"]
    log = open_log(path)
    # The appliance kept the shared memory and drained the ring after the kill: every record
    # the loop logged is in the file, whole, in sequence.
    assert log.skipped == [] and log.lost == 0 and len(log) == r["log_records"] >= 300
    assert np.array_equal(log.records["seq"], np.arange(len(log), dtype=np.uint64))
    _check_probe(log.records)


def test_damaged_file_the_run_page_says_what_was_skipped(server: Server) -> None:
    run = _run_probe(server, cycles=100)
    server.stop_run()
    f = _logs(server, run["id"])["files"][0]
    path = server.data_dir / "runs" / str(run["id"]) / f["name"]
    with open(path, "ab") as out:
        out.write(b"\x01" * 19)  # a torn last record
    g = _logs(server, run["id"])["files"][0]
    assert g["records"] == f["records"] and g["skipped_bytes"] == 19
    assert "truncated last record" in g["skipped"][0] and "19 bytes" in g["skipped"][0]
    csv = server.http.get(f"/api/logs/runs/{run['id']}/files/{f['name']}", params={"fmt": "csv"})
    assert csv.status_code == 200 and csv.headers["x-log-skipped"] == "1"
    assert csv.text.count("\n") == f["records"] + 1


def test_unknown_file_and_traversal_are_404(server: Server) -> None:
    run = server.http.get("/api/logs/runs?limit=1").json()[0]
    for name in ("..%2F..%2F..%2Fruns.sqlite3", "output.txt", "nope.xrf"):
        r = server.http.get(f"/api/logs/runs/{run['id']}/files/{name}")
        assert r.status_code == 404, name
    assert server.http.get("/api/logs/runs/99999").status_code == 404


def test_rerun_viewer_is_served_behind_the_login(server: Server) -> None:
    import httpx

    assert httpx.get(server.url + "/api/logs/rerun").status_code == 401
    assert httpx.get(server.url + "/rerun/").status_code == 401
    page = server.http.get("/rerun/")
    assert page.status_code == 200 and "re_viewer.js" in page.text
    js = server.http.get("/rerun/re_viewer.js")
    assert js.status_code == 200 and len(js.content) > 10000
    assert server.http.get("/rerun/..%2Fruns.sqlite3").status_code == 404
    # the live URL names the host the browser used (the live stream: test_live_stream.py)
    _run_probe(server, cycles=50)
    # The run's live proxy starts beside the run, not before it (logs/live.py): waited for.
    wait_for(lambda: server.http.get("/api/logs/rerun").json()["live_url"], timeout=60, what="the live proxy")
    info = server.http.get("/api/logs/rerun", headers={"Host": "192.168.7.2:8000"}).json()
    assert info["available"] and info["live_url"] == "rerun+http://192.168.7.2:8000/proxy", info
    info = server.http.get("/api/logs/rerun", headers={"Host": "xrf-bench-3.local"}).json()
    assert info["live_url"] == "rerun+http://xrf-bench-3.local:80/proxy", info
    server.stop_run()


def test_lost_records_are_counted_and_shown(tmp_path: Path) -> None:
    """The host writer stalls (the appliance is stopped with SIGSTOP) while the loop logs at
    10 kHz: the ring fills, the loop drops and counts, never waits; the gap shows in seq."""
    s = start(
        tmp_path / "data",
        loop_env={"XRF_FREQ": "10000", "XRF_BENCH_NVARS": "32"},
        host_timeout_ms=30000,
        hang_timeout_ms=30000,
    )
    try:
        run = s.start_run(COST)
        for cmd in ("initialise", "start"):
            assert s.http.post("/api/runs/current/command", json={"cmd": cmd}).json()["accepted"]
        s.wait_cycles(run["id"], 2000)
        os.kill(s.proc.pid, signal.SIGSTOP)
        time.sleep(3.0)  # the ring holds ~1.6 s at 10 kHz x 304 bytes
        os.kill(s.proc.pid, signal.SIGCONT)
        s.wait_cycles(run["id"], 2000)  # the appliance answers again and the loop went on
        s.stop_run()
        r = next(x for x in s.http.get("/api/logs/runs").json() if x["id"] == run["id"])
        assert r["log_lost"] > 1000 and r["status"] == "ended"
        log = open_log(next((s.data_dir / "runs" / str(run["id"])).rglob("cost_*.xrf")))
        assert log.lost == r["log_lost"] and len(log) == r["log_records"]
        assert int(log.records["seq"][-1]) + 1 == len(log) + log.lost
    finally:
        stop_server(s)


def test_disk_full_stops_the_run_and_its_log_stays_whole(tmp_path: Path) -> None:
    """The run folder is a file system of its own (issue 26; here 6 MiB, a part of it reserved
    for the appliance): when the run's log fills the run's share, the run is stopped for its disk
    limit with an alarm, and the file holds whole records only, nothing lost or damaged (the host
    writer drains into the reserve). Before issue 26 the folder lay on the data disk (a tiny tmpfs
    stood in for a full one) and logging stopped while the run went on."""
    if os.geteuid() != 0:
        pytest.skip("the run's own file system needs root (a non-root appliance uses the root helper)")
    # At 10 kHz the probe fills the run's share in seconds (at its 1 kHz default it took a minute).
    s = start(tmp_path / "data", run_disk_mb=6, run_files=256, loop_env={"XRF_FREQ": "10000"})
    try:
        with s.ws() as ws:
            ws.send({"type": "subscribe", "topics": ["alarm", "state"]})
            run = _run_probe(s, cycles=10)
            alarm = ws.wait_for(lambda m: m.get("type") == "alarm" and m.get("kind") == "disk", 120, seen=True)
            assert "full" in alarm["message"], alarm
        wait_for(lambda: _logs(s, run["id"])["run"]["status"] == "ended", 30, "the run to end")
        info = _logs(s, run["id"])
        r, f = info["run"], info["files"][0]
        assert r["end_reason"] == "disk", r
        assert f["records"] == r["log_records"] > 1000
        assert f["skipped"] == [] and f["lost"] == 0  # nothing written was damaged
        log = open_log(s.data_dir / "runs" / str(run["id"]) / f["name"])
        _check_probe(log.records)
    finally:
        stop_server(s)
