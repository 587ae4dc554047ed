"""Once per timing period (1 s): how the loop keeps its time, for the dashboards' timing panel,
and the deadline-miss alarm.

The loop keeps a histogram per cycle stage in its shared memory (rt_core's status block); this
task reads them with the counters and sends one `timing` message: per-stage summaries, the
wake-up jitter, every stage's histogram (for tools), the telemetry and log counters. New missed
deadlines since the last period raise a `deadline_miss` alarm that says how many; a loop that
paused or stopped itself because our heartbeat was late (host_lost) raises `host_lost`, so
nobody is left looking at a run that paused for no reason they can see.
"""

from __future__ import annotations

import asyncio

from ...channels import ChannelsError
from ...ticks import until_aligned
from ..ws.hub import Hub
from ..ws.messages import AlarmMessage, Histogram, StageSummary, TimingMessage
from .run import Run


async def timing(run: Run, period_s: float, hub: Hub) -> None:
    ch = run.channels
    assert ch is not None
    while True:
        await asyncio.sleep(until_aligned(period_s))  # with the other once-a-second work
        # The histograms (eight of 512 buckets, converted in Python) and the message only for
        # someone who takes `timing`; the deadline-miss alarm below is checked every period.
        wanted = hub.wants("timing")
        try:
            if not wanted:  # the alarms' fields, not the whole status converted
                missed, host_lost = ch.alarm_counts()
                _miss_alarm(run, missed, hub)
                if host_lost > run.last_host_lost:  # rare: then the state's name too
                    s = ch.status()
                    _host_lost_alarm(run, s.host_lost, s.state_name, hub)
                continue
            s = ch.status()
            hists = ch.histograms()
        except ChannelsError:
            continue
        _host_lost_alarm(run, s.host_lost, s.state_name, hub)
        stages = {
            name: StageSummary(
                count=h.count,
                min=h.min,
                max=h.max,
                mean=h.mean,
                p50=h.percentile(50),
                p99=h.percentile(99),
            )
            for name, h in hists.items()
        }
        wake = hists.get("wakeup")
        hub.publish(
            TimingMessage(
                run_id=run.row.id,
                cycles=s.cycles,
                misses=s.missed,
                cycle_freq=ch.info["cycle_freq"],
                stages=stages,
                jitter=Histogram(edges=wake.edges, counts=wake.counts) if wake else Histogram(edges=[], counts=[]),
                # every stage's histogram (non-empty buckets: lower edge ns, count), for tools
                histograms={name: Histogram(edges=h.edges, counts=h.counts) for name, h in hists.items()},
                telemetry_sent=run.telemetry_sent,
                log_lost=s.log_lost,
                host_lost=s.host_lost,
            )
        )
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
