"""The topic table of docs/educators/room.md ("What travels over the broker") says what each MQTT
payload carries: every model of xrflab.room.payloads is in it, with exactly its fields, on the
topics topics.py names. A field added to a model without the doc (or the reverse) fails here."""

from __future__ import annotations

import re

from pydantic import BaseModel

from xrf_testing.harness import REPO_ROOT
from xrflab.room import payloads

DOC = REPO_ROOT / "docs" / "educators" / "room.md"
MODELS: dict[str, type[BaseModel]] = {
    m.__name__: m
    for m in (
        payloads.Online,
        payloads.Status,
        *payloads.EventModels,
        payloads.Reply,
        payloads.Grades,
        payloads.GradeRow,
        payloads.GradeCheck,
        payloads.GradeCell,
        payloads.GradeProgress,
        payloads.Stop,
        payloads.Message,
        payloads.Selfcheck,
        payloads.Collect,
        payloads.Grade,
        payloads.ClassList,
        payloads.Account,
        payloads.Assignment,
        payloads.RoomOnline,
    )
}


def documented() -> dict[str, tuple[str, set[str]]]:
    """model name -> (topic cell, fields) from the table's rows."""
    out: dict[str, tuple[str, set[str]]] = {}
    for line in DOC.read_text().splitlines():
        if not line.startswith("| `xrf/"):
            continue
        cells = [c.strip() for c in line.strip("|").split("|")]
        names = re.findall(r"`([^`]+)`", cells[3])
        assert names, line
        assert names[0] not in out, f"{names[0]} twice in the table"
        out[names[0]] = (cells[0], set(names[1:]))
    return out


def test_every_payload_is_documented_with_its_fields() -> None:
    doc = documented()
    assert set(doc) == set(MODELS), f"in the doc only: {set(doc) - set(MODELS)}; undocumented: {set(MODELS) - set(doc)}"
    for name, (topic, fields) in doc.items():
        assert fields == set(MODELS[name].model_fields), (name, fields ^ set(MODELS[name].model_fields))
        assert topic.startswith("`xrf/"), (name, topic)


def test_no_bench_payload_carries_an_address() -> None:
    """Where a bench is comes from its enrolment only (issue 26, hole 9)."""
    bench_models = [
        payloads.Online,
        payloads.Status,
        *payloads.EventModels,
        payloads.Reply,
        payloads.Grades,
        payloads.GradeRow,
    ]
    for model in bench_models:
        assert not {"url", "address", "host", "dashboard_url"} & set(model.model_fields), model.__name__
