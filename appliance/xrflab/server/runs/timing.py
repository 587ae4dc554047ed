"""Once per timing period (1 s): how the loop keeps its time, for the dashboards' timing panel,
and the deadline-miss alarm.

The loop keeps a histogram per cycle stage in its shared memory (rt_core's status block); this
task reads them with the counters and sends one `timing` message: per-stage summaries, the
wake-up jitter, every stage's histogram (for tools), the telemetry and log counters. New missed
deadlines since the last period raise a `deadline_miss` alarm that says how many; a loop that
paused or stopped itself because our heartbeat was late (host_lost) raises `host_lost`, so
nobody is left looking at a run that paused for no reason they can see. With nobody taking the
timing message it refreshes the run's status instead (announce.refresh_state): the reader reads
only every few seconds then.
"""

from __future__ import annotations

import asyncio
from typing import Any

from ...channels import ChannelsCorrupt, ChannelsError, Status
from ...channels import Histogram as ChHistogram
from ...channels.status import histograms_of
from ...ticks import until_aligned
from ..ws.hub import Hub
from ..ws.messages import AlarmMessage, TimingMessage
from .announce import refresh_state
from .run import Run


def timing_message_fields(
    run_id: int, s: Status, hists: dict[str, ChHistogram], cycle_freq: int, telemetry_sent: int
) -> dict[str, Any]:
    """The wire fields of the TimingMessage of a status and its stages' histograms, as the model
    dumps them (its fields' order, every field set): built here, not through the model (nine
    models a second and their dump, for one dashboard: issue 30 item 4)."""
    wake = hists.get("wakeup")
    return {
        "run_id": run_id,
        "cycles": s.cycles,
        "misses": s.missed,
        "cycle_freq": cycle_freq,
        "stages": {
            name: {
                "count": h.count,
                "min": h.min,
                "max": h.max,
                "mean": float(h.mean),
                "p50": h.percentile(50),
                "p99": h.percentile(99),
            }
            for name, h in hists.items()
        },
        "jitter": {"edges": wake.edges, "counts": wake.counts} if wake else {"edges": [], "counts": []},
        # every stage's histogram (non-empty buckets: lower edge ns, count), for tools
        "histograms": {name: {"edges": h.edges, "counts": h.counts} for name, h in hists.items()},
        "telemetry_sent": telemetry_sent,
        "log_lost": s.log_lost,
        "host_lost": s.host_lost,
    }


async def timing(run: Run, period_s: float, hub: Hub) -> None:
    ch = run.channels
    assert ch is not None
    checked = False  # the first message is checked against TimingMessage (Hub.publish_fields)
    while True:
        await asyncio.sleep(until_aligned(period_s))  # with the other once-a-second work
        # One copy of the status block for everything below (the series' sample, the state
        # refresh, the message): a copy each was two 33 KB copies a second (issue 30 item 4).
        try:
            copy = ch.status_copy()
        except ChannelsCorrupt as exc:  # kept locked on purpose: the run is stopped (announce.py)
            if run.report_corrupt is not None:
                run.report_corrupt(exc)
            continue
        except ChannelsError:
            continue  # no copy yet (the loop mid-write since the start): the next second
        # The run's timing series (timing.jsonl): its sample taken here, where the event loop
        # wakes anyway, its line written by the host writer's thread at its next drain
        # (logs/host_writer.py take_timing: that thread wakes every few seconds, not each second).
        rl = run.logging
        if rl is not None:
            rl.writer.take_timing(copy)
        # The run's status refreshed from this copy (and its state published should it have
        # changed), once a second: the REST routes and the room show run.last_status, and with
        # nobody connected the reader reads only every IDLE_PERIOD_S (4 s, server/runs/reader.py);
        # with a dashboard the reader refreshes it on a state change in its samples
        # (announce.STATUS_REFRESH_S).
        refresh_state(run, hub, copy=copy)  # the whole copy converted: s below is this second's
        s = run.last_status
        if s is None:
            continue
        _host_lost_alarm(run, s.host_lost, s.state_name, hub)
        # The histograms (eight of 512 buckets, converted in Python) and the message only for
        # someone who takes `timing`; the deadline-miss alarm below is checked every period.
        if not hub.wants("timing"):
            _miss_alarm(run, s.missed, hub)
            continue
        hists = histograms_of(copy)
        fields = timing_message_fields(run.row.id, s, hists, ch.info["cycle_freq"], run.telemetry_sent)
        if not checked:
            TimingMessage.model_validate(fields)
            checked = True
        hub.publish_fields("timing", fields)
        _miss_alarm(run, s.missed, hub)


def _miss_alarm(run: Run, missed: int, hub: Hub) -> None:
    """`deadline_miss` when deadlines were missed since the last period."""
    if missed > run.last_missed:
        hub.publish(
            AlarmMessage(
                kind="deadline_miss",
                run_id=run.row.id,
                misses=missed,
                new=missed - run.last_missed,
                message=f"{missed - run.last_missed} deadline miss(es) in the last second ({missed} in total)",
            )
        )
        run.last_missed = missed


def _host_lost_alarm(run: Run, lost: int, state: str, hub: Hub) -> None:
    """`host_lost` when the loop acted on a late host heartbeat since the last period (its
    host_timeout_action: it paused or stopped itself)."""
    if lost > run.last_host_lost:
        run.last_host_lost = lost
        hub.publish(
            AlarmMessage(
                kind="host_lost",
                run_id=run.row.id,
                message=f"the controller went to {state} by itself: the appliance did not answer for over a "
                "second (stuck or starved of CPU). Its outputs are as that state makes them; start it again "
                "to go on.",
            )
        )
