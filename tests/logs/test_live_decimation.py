"""The live rerun view's decimation to a display rate keeps every bucket's min and max (issue 31
bug 6): a one-cycle spike in a 1 kHz variable is still drawn by a viewer that gets 100 points/s.
The run's log keeps every record; only the live view is decimated (logs/rerun_live.py)."""

from __future__ import annotations

import numpy as np

from xrflab.logs.rerun_live import LIVE_HZ, _split_last_bucket, decimate_minmax


def _buckets(cycle: np.ndarray, n: int) -> dict[int, np.ndarray]:
    return {int(b): cycle // n == b for b in np.unique(cycle // n)}


def test_min_and_max_of_each_bucket_survive_in_their_order() -> None:
    rng = np.random.default_rng(31)
    cycle = np.arange(1000, 3000)  # 2 s at 1 kHz, not starting at a bucket's edge
    cycle = cycle[rng.random(len(cycle)) > 0.05]  # a few missed cycles: buckets of unequal size
    n = int(round(2 * 1000 / LIVE_HZ))
    values = rng.normal(size=(len(cycle), 3))
    values[123, 0] = 50.0  # one-cycle spikes, up and down, in different series
    values[777, 1] = -50.0
    values[400:460, 2] = 7.0  # a bucket (and more) constant
    values[900, 2] = np.nan  # a NaN among numbers does not hide the bucket's extremes

    rows, out = decimate_minmax(cycle // n, values)

    assert len(rows) == len(out) and np.all(np.diff(rows) > 0)  # rows of the input, in order
    out_bucket = cycle[rows] // n
    for b, members in _buckets(cycle, n).items():
        mine = out_bucket == b
        assert 1 <= mine.sum() <= 2, (b, mine.sum())  # at most two points per bucket
        for s in range(values.shape[1]):
            got = out[mine, s]
            assert np.nanmin(got) == np.nanmin(values[members, s]), (b, s)
            assert np.nanmax(got) == np.nanmax(values[members, s]), (b, s)
            # in the order they occurred: the first point is the extreme that came first
            idx = np.flatnonzero(members)
            first_lo = idx[np.nanargmin(values[members, s])] < idx[np.nanargmax(values[members, s])]
            if got[0] != got[-1]:
                assert (got[0] < got[-1]) == first_lo, (b, s)
    # the spikes are there, at their bucket
    assert 50.0 in out[:, 0] and -50.0 in out[:, 1]
    # the display rate: at most LIVE_HZ points per second per series (+1 for a bucket cut at the ends)
    seconds = (cycle[-1] - cycle[0] + 1) / 1000
    assert len(out) <= LIVE_HZ * seconds + 2, (len(out), seconds)


def test_a_bucket_of_one_row_is_one_point_and_nothing_in_nothing_out() -> None:
    rows, out = decimate_minmax(np.array([0, 1, 1, 2]), np.array([[1.0], [5.0], [-5.0], [3.0]]))
    assert rows.tolist() == [0, 1, 2, 3] and out[:, 0].tolist() == [1.0, 5.0, -5.0, 3.0]
    rows, out = decimate_minmax(np.zeros(0, dtype=np.int64), np.zeros((0, 2)))
    assert len(rows) == 0 and out.shape == (0, 2)


def test_the_last_incomplete_bucket_waits_for_the_next_batch() -> None:
    rec = np.zeros(45, dtype=[("cycle", "<u8"), ("v", "<f8")])
    rec["cycle"] = np.arange(100, 145)  # buckets of 20: 100-119, 120-139, 140-144 (incomplete)
    sent, kept = _split_last_bucket(rec, 20)
    assert sent["cycle"][-1] == 139 and kept["cycle"].tolist() == list(range(140, 145))
    sent, kept = _split_last_bucket(rec[:40], 20)  # ends on a bucket's last cycle: complete
    assert len(sent) == 40 and len(kept) == 0
    sent, kept = _split_last_bucket(rec[40:], 20)  # all in one incomplete bucket
    assert len(sent) == 0 and len(kept) == 5
