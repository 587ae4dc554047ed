"""The appliance's common time boundaries for its slow periodic work (issue 30 item 4).

Every task or thread of the appliance that wakes once a second or slower (the reader with
nobody connected, the timing task, the limits guard, the event loop's sign of life to the safety
watcher, the room's enrolment poll) sleeps until the next multiple of its period on the
monotonic clock, so they wake together rather than each on a timer of its own: on a busy core a
wake-up of a Python process costs more (its caches gone cold) than the little each does. What
waits for something to happen does not tick at all (session 14): uvicorn's server (its Date
header is made when read), the lease's idle watch (until the holder's deadline), the live
rerun sender with no viewer (until one comes), the output poll with nobody taking monitor lines
(at the reader's idle batch).
"""

from __future__ import annotations

import time


def until_aligned(period_s: float) -> float:
    """Seconds until the next multiple of `period_s` on the monotonic clock (asyncio's and the
    threads' clock); a boundary less than 1 ms away is skipped for the next one (no double
    wake-up around it)."""
    if period_s <= 0:
        return 0.0
    left = period_s - time.monotonic() % period_s
    return left if left > 0.001 else left + period_s
