"""The live viewer's warm-up recording (issue 31 bug 6, session 14): a small `.rrd` the live viewer's
tab gives the viewer before the run's data (frontend/rerun-tab.js, ``GET /api/logs/rerun/warmup.rrd``).

Without a GPU driver the viewer's first frame with plots took 0.5-1.2 s by itself: it makes its
render pipelines then (7 WebGL programs, 14 shaders compiled in software), and that frame was the one with
the run's first samples, which were that much older when they reached the screen. Drawn first, this
recording makes the viewer build them while the run's stream still connects; the tab then closes it
and hands over the run's data.

What it holds: one entity of time series (two series of a sine and its cosine, ``SAMPLES`` rows) on
the live recording's two timelines (``cycle``, a sequence, and ``time``, a timestamp), the kind of
plot the live blueprint shows (logs/rerun_sender.py); no blueprint (the viewer's default one is a
time-series view of it). Its own application (``APPLICATION``) and recording id, so nothing of it
is ever part of a run's recording or blueprint; the tab closes it by that store id
(frontend/rerun-tab.js ``WARMUP_STORE``). Made with logs/rerun_wire.py's encoding, as the .rrd
download (logs/rrdfile.py): tests/logs/test_rerun_warmup.py reads it back with the pinned SDK.
"""

from __future__ import annotations

import functools
import io
import math
from array import array

from .rerun_wire import RECORDING, index_column, le_bytes, make_store_id, row_id_column, scalars_column
from .rrdfile import RrdWriter

APPLICATION = "xrflab-warmup"
RECORDING_ID = "warmup"
ENTITY = "/warmup"
SAMPLES = 200
PERIOD_NS = 10_000_000  # 100 samples/s, as the live view's display rate (rerun_live.LIVE_HZ)
T0_NS = 1_700_000_000_000_000_000  # (a fixed time: the recording is the same at every start)


def store_id() -> bytes:
    return make_store_id(RECORDING, RECORDING_ID, APPLICATION)


@functools.cache
def warmup_rrd() -> bytes:
    """The warm-up recording as a .rrd stream (made once per process: ~10 KB)."""
    buf = io.BytesIO()
    w = RrdWriter(buf)
    store = store_id()
    w.store_info(store)
    n = SAMPLES
    cycles = array("q", range(n))
    times = array("q", (T0_NS + i * PERIOD_NS for i in range(n)))
    values = array("d")
    for i in range(n):
        values.extend((math.sin(i / 16), math.cos(i / 16)))
    columns = [
        row_id_column(w.tuids.rows(n), n),
        index_column("cycle", False, le_bytes(cycles), True),
        index_column("time", True, le_bytes(times), True),
        scalars_column(le_bytes(values), n, 2),
    ]
    w.chunk(store, ENTITY, columns, n)
    return buf.getvalue()


__all__ = ["APPLICATION", "ENTITY", "RECORDING_ID", "SAMPLES", "store_id", "warmup_rrd"]
