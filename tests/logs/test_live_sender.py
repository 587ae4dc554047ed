"""The live recording's sender without the rerun SDK (logs/rerun_sender.py, issue 30 item 4): what a
viewer reads from the run's proxy is, for rerun, what the SDK's sender sent for the same calls
(entities, timelines, values to the bit, series names, text log, the live blueprint); and an
appliance whose run was watched live has neither rerun nor pyarrow loaded. When rerun changes its
messages, the first fails: rrdfile.py's and rerun_sender.py's "rerun 0.41" constants are where to look."""

from __future__ import annotations

import struct
import subprocess
import sys
import time
import uuid
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from xrf_testing.grpcweb import READ_MESSAGES, read_messages
from xrf_testing.harness import free_port, stop_server, wait_for
from xrf_testing.logs_support import PROBE, start
from xrf_testing.rerun_stream import fields
from xrf_testing.sdk_live import SdkSender
from xrflab.logs.rerun_sender import LiveSender, escape_part
from xrflab.logs.rerun_servers import _rerun_cli
from xrflab.logs.rrdfile import CHANGES_ENTITY, variable_groups

RERUN = Path(sys.executable).with_name("rerun")  # (the venv's wrapper: for `rerun rrd`)
PROXY = [*_rerun_cli(), "--serve-grpc", "--bind", "127.0.0.1"]  # the binary itself, as the appliance starts it
NAMES = ["pos_left", "pos_right", "θ_a", "θ_b", "x\u0301", "speed"]  # groups pos, θ, signals (x́, speed)
TELEMETRY = ["enc", "pwm", "xeno2ros"]


@pytest.fixture
def proxy() -> Iterator[str]:
    """A rerun message proxy as the appliance starts one (rerun_servers.LiveProxy), holding all."""
    port = free_port()
    proc = subprocess.Popen(
        [*PROXY, "--port", str(port), "--server-memory-limit", "64MiB"],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        wait_for(lambda: _listening(port), 20, "the rerun proxy")
        yield f"127.0.0.1:{port}"
    finally:
        proc.terminate()
        proc.wait(10)


def _listening(port: int) -> bool:
    import socket

    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def _send(sender: Any) -> None:
    """What LiveRerun sends for a run: the blueprint, series names, decimated rows of three batches
    (NaN and infinities among them, a non-ASCII group), telemetry, parameter changes."""
    rng = np.random.default_rng(12)
    groups = sorted(set(variable_groups(NAMES).values()))
    by_group: dict[str, list[str]] = {}
    for n, g in variable_groups(NAMES).items():
        by_group.setdefault(f"log/{escape_part(g)}", []).append(n)
    sender.connect()
    sender.blueprint(groups, TELEMETRY, 10.0, 1000)
    wall = 1_795_000_000_000_000_000
    for batch in range(3):
        cycle = np.arange(batch * 500, (batch + 1) * 500, 10, dtype=np.int64)
        t_ns = wall + cycle * 1_000_000 + 17
        for entity, members in by_group.items():
            sender.series_names(entity, members)
            values = rng.normal(size=(len(cycle), len(members)))
            values[3, 0] = np.nan
            values[4, -1] = -np.inf
            sender.scalars(entity, cycle, t_ns, values)
        for key in ("enc", "pwm"):
            sender.series_names(f"telemetry/{key}", ["1", "2"])
            sender.scalars(
                f"telemetry/{key}",
                cycle[::5],
                t_ns[::5],
                rng.integers(-99, 99, (len(cycle[::5]), 2)).astype(np.float64),
            )
        sender.series_names("telemetry/xeno2ros", ["speed"])
        sender.scalars("telemetry/xeno2ros", cycle[::5], t_ns[::5], rng.normal(size=(len(cycle[::5]), 1)))
        sender.texts(
            CHANGES_ENTITY,
            np.array([batch * 500 + 7], dtype=np.int64),
            np.array([1795000000.123456789 + batch], dtype=np.float64),
            [f"kp: {batch} -> {batch + 1} at cycle {batch * 500 + 7} (alice)"],
            "INFO",
        )
        assert sender.flush()
    sender.close()


def _received(hostport: str, until: bytes) -> list[bytes]:
    """Every message the proxy replays to a ReadMessages reader (as the appliance's read route
    forwards them to a viewer)."""
    with httpx.Client(base_url=f"http://{hostport}") as client:
        got = read_messages(client, READ_MESSAGES, timeout=30, quiet=3)
    assert got.status == 200 and until in got.data, (got.status, got.ended_by)
    return got.messages


def _as_rrd(messages: list[bytes], path: Path) -> Path:
    """ReadMessagesResponse{log_msg = 1}: LogMsg's field = the .rrd frame's kind, its bytes the frame's."""
    out = bytearray(b"RRF2" + bytes([0, 41, 0, 0]) + bytes([0, 2, 0, 0]))
    for m in messages:
        for number, log_msg in fields(m):
            assert number == 1 and isinstance(log_msg, bytes)
            for kind, payload in fields(log_msg):
                assert isinstance(payload, bytes)
                out += struct.pack("<QQ", kind, len(payload)) + payload
    path.write_bytes(out)
    return path


def _activations(messages: list[bytes]) -> list[dict[int, Any]]:
    out = []
    for m in messages:
        for _, log_msg in fields(m):
            for kind, payload in fields(log_msg):  # type: ignore[arg-type]
                if kind == 3:
                    msg = dict(fields(payload))  # type: ignore[arg-type]
                    out.append({k: v for k, v in msg.items() if k != 1})
    return out


def _recording(path: Path) -> dict[str, Any]:
    """What rerun's reader makes of the recording: its id, and per entity its static components and
    its rows (timelines, each component's values) in time order."""
    from rerun.chunk import RrdReader

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # no footer: rerun scans the stream
        reader = RrdReader(path)
    (store,) = reader.recordings()
    entities: dict[str, Any] = {}
    for chunk in reader.stream(store=store):
        batch = chunk.to_record_batch()
        entity = batch.schema.metadata[b"rerun:entity_path"].decode()
        e = entities.setdefault(entity, {"static": {}, "rows": []})
        kinds = {f.name: (f.metadata or {}).get(b"rerun:kind", b"").decode() for f in batch.schema}
        timelines = sorted(n for n, k in kinds.items() if k == "index")
        data = sorted(n for n, k in kinds.items() if k == "data")
        if not timelines:
            for n in data:
                e["static"][n] = batch.column(n).to_pylist()
            continue
        cols = {n: batch.column(n).cast("int64").to_pylist() for n in timelines}
        for n in data:
            col = batch.column(n)
            if "Scalars" in n:  # float64 to the bit (NaN and infinities included)
                cols[n] = [np.asarray(v, dtype="<f8").tobytes() for v in col.to_pylist()]
            else:
                cols[n] = col.to_pylist()
        names = timelines + data
        e["rows"] += [tuple(zip(names, r)) for r in zip(*(cols[n] for n in names))]
    for e in entities.values():
        e["rows"].sort()
    start = entities.pop("/__properties")
    assert list(start["static"]) == ["RecordingInfo:start_time"]
    return {"recording": str(store), "entities": entities}


def _blueprint(path: Path) -> Any:
    """The blueprint as a tree (its random ids replaced by what they point to)."""
    from rerun.chunk import RrdReader

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reader = RrdReader(path)
    (store,) = reader.blueprints()
    entities: dict[str, dict[str, Any]] = {}
    for chunk in reader.stream(store=store):
        batch = chunk.to_record_batch()
        entity = batch.schema.metadata[b"rerun:entity_path"].decode()
        row = {n: batch.column(n).to_pylist()[-1] for n in batch.schema.names if ":" in n}
        entities.setdefault(entity, {}).update(row)
    root = bytes(entities.pop("/viewport")["ViewportBlueprint:root_container"][0])
    container = entities.pop(f"/container/{uuid.UUID(bytes=root)}")
    views = []
    for ref in container.pop("ContainerBlueprint:contents"):
        views.append(
            (
                entities.pop("/" + ref),
                entities.pop(f"/{ref}/ViewContents"),
                entities.pop(f"/{ref}/VisibleTimeRanges"),
            )
        )
    return container, views, entities  # what is left: the panels


def test_a_viewer_reads_what_the_sdk_sent(proxy: str, tmp_path: Path) -> None:
    import rerun  # noqa: F401  (the reference; the appliance never imports it)

    _send(LiveSender(lambda: f"http://{proxy}", "run-7"))
    ours = _received(proxy, b"kp: 2 -> 3")
    # the SDK's, through a proxy of its own
    other = subprocess.Popen(
        [*PROXY, "--port", str(port := free_port())],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        wait_for(lambda: _listening(port), 20, "the SDK's proxy")
        _send(SdkSender(f"rerun+http://127.0.0.1:{port}/proxy", "run-7"))
        sdk = _received(f"127.0.0.1:{port}", b"kp: 2 -> 3")
    finally:
        other.terminate()
        other.wait(10)
    ours_rrd, sdk_rrd = _as_rrd(ours, tmp_path / "ours.rrd"), _as_rrd(sdk, tmp_path / "sdk.rrd")
    verify = subprocess.run(
        [str(RERUN), "rrd", "verify", "--check-footers", "false", str(ours_rrd)], capture_output=True, text=True
    )
    assert verify.returncode == 0, verify.stderr[-3000:]

    mine, theirs = _recording(ours_rrd), _recording(sdk_rrd)
    assert mine["recording"] == theirs["recording"]
    assert sorted(mine["entities"]) == sorted(theirs["entities"]), (
        sorted(mine["entities"]),
        sorted(theirs["entities"]),
    )
    assert "/log/θ" in mine["entities"] and "/log/signals" in mine["entities"]
    for entity, e in theirs["entities"].items():
        assert mine["entities"][entity] == e, entity
    assert len(mine["entities"]["/log/pos"]["rows"]) == 150
    assert mine["entities"]["/params/changes"]["rows"][0][1] == ("time", 1795000000123456768)  # ns, truncated

    assert _blueprint(ours_rrd) == _blueprint(sdk_rrd)
    container, views, panels = _blueprint(ours_rrd)
    assert [v[0]["ViewBlueprint:display_name"][0] for v in views] == ["log: pos", "log: signals", "log: θ", *TELEMETRY]
    assert set(panels) == {"/blueprint_panel", "/selection_panel", "/time_panel"}
    assert _activations(ours) == _activations(sdk) == [{2: 1, 3: 1}]  # made active and default


def test_a_failed_batch_is_dropped_and_the_next_brings_the_recording_again(proxy: str, tmp_path: Path) -> None:
    """The proxy stopped (or restarted: an empty one, maybe on another port): the batch that did not
    reach it is dropped, as the SDK's client dropped it, and the next one reaches the proxy where
    it listens now, with what a viewer needs first (store info, blueprint, series names)."""
    where = ["127.0.0.1:9"]  # nothing listens there (discard port, refused on loopback)
    sender = LiveSender(lambda: f"http://{where[0]}", "run-8")
    sender.connect()
    sender.blueprint(["signals"], TELEMETRY, 10.0, 1000)
    sender.series_names("log/signals", ["a", "b"])
    cycle = np.arange(10, dtype=np.int64)
    sender.scalars("log/signals", cycle, cycle + 1_795_000_000_000_000_000, np.ones((10, 2)))
    assert not sender.flush() and sender.failed_posts == 1
    where[0] = proxy
    sender.scalars("log/signals", cycle + 10, cycle + 1_795_000_000_000_000_010, np.full((10, 2), 2.0))
    assert sender.flush()
    sender.close()
    rec = _recording(_as_rrd(_received(proxy, b"SeriesLines"), tmp_path / "again.rrd"))
    signals = rec["entities"]["/log/signals"]
    assert signals["static"] == {"SeriesLines:names": [["a", "b"]]}
    assert [r[0] for r in signals["rows"]] == [("cycle", c) for c in range(10, 20)]  # the failed batch is not there
    assert _blueprint(tmp_path / "again.rrd")[1][0][0]["ViewBlueprint:space_origin"] == ["/log/signals"]


def _maps(pid: int) -> str:
    return Path(f"/proc/{pid}/maps").read_text()


def test_an_appliance_watched_live_loads_neither_rerun_nor_arrow(tmp_path: Path, monkeypatch) -> None:
    """Issue 30 item 4: the appliance imported the rerun SDK (and pyarrow, rerun_bindings: ~55 MB
    RSS, for good) at a run's first viewer. A viewer now reads the run's stream, and the
    appliance has mapped neither library nor imported either package (serve_for_test.py's import
    log: every top-level module the appliance imported)."""
    imports = tmp_path / "imports.txt"
    monkeypatch.setenv("XRF_IMPORT_LOG", str(imports))  # (the appliance's environment: serve_for_test.py)
    s = start(tmp_path / "data")
    try:
        r = s.http.post("/api/runs", json={"build": PROBE}, timeout=300)
        assert r.status_code == 201, r.text
        run_id = r.json()["id"]
        for cmd in ("initialise", "start"):
            assert s.http.post("/api/runs/current/command", json={"cmd": cmd}).json()["accepted"]
        wait_for(lambda: s.http.get("/api/logs/rerun").json()["live_run"] == run_id, 20, "the run's live proxy")
        got = read_messages(
            s.http, READ_MESSAGES, timeout=60, until=lambda d: f"run-{run_id}".encode() in d and b"ratio" in d
        )
        assert got.ended_by == "until", got.ended_by  # the run's samples reached the viewer
        time.sleep(1.0)  # (a few more batches sent)
        maps = _maps(s.proc.pid)
        assert "rerun_bindings" not in maps and "libarrow" not in maps and "pyarrow" not in maps
        loaded = set(imports.read_text().split())
        assert "httpx" in loaded and "numpy" in loaded  # (the log works)
        assert not loaded & {"rerun", "rerun_bindings", "pyarrow"}, sorted(
            loaded & {"rerun", "rerun_bindings", "pyarrow"}
        )
    finally:
        stop_server(s)
