"""The grades CSV, for this appliance's table and the room's: one writer, and no cell a spreadsheet
would run, whichever column a student's or a bench's text lands in."""

from __future__ import annotations

import csv
import io

import pytest

from xrflab.grading.service import csv_cell, grades_csv

FORMULAS = ["=1+1", "+SUM(A1)", "-2+3", "@cmd", "\t=x", "\r=x"]


def _table(text: str) -> dict:
    return {
        "checks": [{"id": "overshoot"}, {"id": "settle"}],
        "rows": [
            {
                "owner": text,
                "bench": text,
                "project": text,
                "status": text,
                "checks": {"overshoot": {"earned": 1.5}, "settle": {"earned": text}},
                "earned": -0.5,
                "points": 4,
                "build": text,
                "graded_at": text,
            }
        ],
    }


@pytest.mark.parametrize("formula", FORMULAS)
def test_no_text_cell_is_a_formula(formula: str) -> None:
    for extra in ((), ("bench",)):
        rows = list(csv.reader(io.StringIO(grades_csv(_table(formula), extra=extra))))
        header, row = rows
        assert header[: 1 + len(extra)] == ["owner", *extra]
        cells = dict(zip(header, row))
        numbers = {"overshoot", "total", "max"}
        for name, cell in cells.items():
            if name in numbers:
                continue
            assert cell == "'" + formula, (name, cell)
        # numbers stay numbers, a negative one too
        assert (cells["overshoot"], cells["total"], cells["max"]) == ("1.5", "-0.5", "4")


def test_plain_text_and_missing_values() -> None:
    t = _table("alice")
    t["rows"][0].update(build=None, graded_at=None)
    t["rows"][0]["checks"] = {}
    header, row = list(csv.reader(io.StringIO(grades_csv(t))))
    cells = dict(zip(header, row))
    assert header == ["owner", "project", "status", "overshoot", "settle", "total", "max", "build", "graded_at"]
    assert cells["owner"] == "alice" and cells["build"] == "" and cells["graded_at"] == "" and cells["settle"] == ""


def test_csv_cell_leaves_ordinary_text() -> None:
    for text in ("alice", "lab 1", "a=b", "1-2", ""):
        assert csv_cell(text) == text
