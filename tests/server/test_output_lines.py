"""The loop's printed output is the guest's: the console cutter holds at most one line, cuts long
lines and counts floods instead of queueing them (server/runs/output_lines.py)."""

from __future__ import annotations

from xrflab.server.runs.output_lines import OutputLines


def feed(cutter: OutputLines, data: bytes) -> list[str]:
    out: list[str] = []
    cutter.feed(data, out)
    return out


def test_lines_split_and_the_rest_waits() -> None:
    c = OutputLines()
    assert feed(c, b"one\ntwo\nthr") == ["one", "two"]
    assert feed(c, b"ee\n") == ["three"]
    out: list[str] = []
    c.flush(out)
    assert out == []


def test_a_line_that_never_ends_is_cut_and_never_held_whole() -> None:
    c = OutputLines(line_max=100, lines_per_poll=10**9)
    lines: list[str] = []
    for _ in range(1000):  # 1 MB without a newline, fed in 1 KB chunks
        c.feed(b"x" * 1000, lines)
        assert len(c._pending) < 100  # what the appliance holds between reads: less than a line
    assert len(lines) == 10_000 and all(len(t) == 100 for t in lines)
    assert c.skipped == 0


def test_a_flood_is_counted_not_queued() -> None:
    c = OutputLines(lines_per_poll=200)
    out = feed(c, b"\n" * 100_000)
    assert len(out) == 200
    assert c.take_skipped() == 100_000 - 200
    assert c.take_skipped() == 0  # reported once


def test_bytes_that_are_not_utf8_are_replaced_not_fatal() -> None:
    c = OutputLines()
    assert feed(c, b"bad \xff\xfe byte\n") == ["bad \ufffd\ufffd byte"]


def test_the_last_line_without_newline_comes_at_the_end() -> None:
    c = OutputLines()
    assert feed(c, b"done") == []
    out: list[str] = []
    c.flush(out)
    assert out == ["done"]
