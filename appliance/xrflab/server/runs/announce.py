"""What the browsers are told about the run: its `run` message (started, ended, or the current
one for a client that connects) and its `state` message, made from a `Run`.

The models are server/ws/messages.py's (RunMessage, StateMessage); who sees which part of them is
ownership.scope's. A field a message leaves out (the run's program before its shared memory is
open, `cycles` without a run) is not set, so it stays absent on the wire, as app.js expects. `state` goes out when something a person would see changed (the state, a
rejection, the loop's liveness), not per sample: the reader calls `refresh_state` after every
batch, and a command's answer calls it at once.
"""

from __future__ import annotations

import contextlib
import time
from typing import Any, Literal

from ... import channels as chmod
from ...channels import ChannelsCorrupt, ChannelsError, StatusBusy
from ...channels.binding import CData
from ...channels.status import status_from_struct
from ..ws.hub import Hub
from ..ws.messages import Rejected, RunMessage, StateMessage
from .run import Run
from .store import RunRow


def schema_fields(schema: str) -> list[dict[str, Any]]:
    """[{name, type}] from a normalised .msg text, for the dashboard's controls and plots."""
    from ...msgdef import Codec

    return [{"name": f.name, "type": f.type, "count": f.count} for f in Codec(schema).fields]


RunEvent = Literal["current", "started", "ended"]


def run_message(run: Run | None, last_row: RunRow | None, event: RunEvent = "current") -> RunMessage:
    """The `run` message of `run`, or of the last run's record (`last_row`) when none is live."""
    row = run.row if run else last_row
    fields: dict[str, Any] = {}
    if run and run.channels is not None:
        info = run.channels.info
        fields.update(
            program=info["program"],
            cycle_freq=info["cycle_freq"],
            backend=info["backend"],
            transport=info["transport"],
            channels=int(run.channels.geom.channels),  # bounded when the segment was opened
            ros2xeno=schema_fields(info["ros2xeno_schema"]),
            xeno2ros=schema_fields(info["xeno2ros_schema"]),
            setpoint=run.setpoint,
        )
    if run and run.guest is not None:
        fields["confinement"] = run.guest.as_dict()
    return RunMessage(event=event, run=row.as_dict() if row else None, active=bool(run and run.alive), **fields)


def state_message(run: Run | None) -> StateMessage:
    """The `state` message: the loop's state and the commands it accepts now ("NO RUN" without
    a run whose shared memory is open)."""
    if run is None or run.channels is None or run.last_status is None:
        return StateMessage(
            run_id=run.row.id if run else None,
            active=False,
            state=0,
            name="NO RUN",
            allowed=[],
            rejected=None,
            last_error=0,
        )
    s = run.last_status
    rejected = None
    if s.cmd_rejected:
        rejected = Rejected(
            ticket=s.cmd_rejected,
            cmd=s.last_rejected_cmd,
            name=chmod.command_name(s.last_rejected_cmd),
            reason=s.reject_reason,
        )
    alive = bool(run.alive and s.running)
    return StateMessage(
        run_id=run.row.id,
        active=alive,
        state=s.state,
        name=s.state_name,
        allowed=chmod.allowed_commands(s.state) if alive else [],
        rejected=rejected,
        last_error=s.last_error,
        cycles=s.cycles,
    )


def ended(run: Run) -> tuple[RunMessage, StateMessage]:
    """The `run` and `state` messages of a run that just ended: inactive, no command allowed
    (whatever the last status the loop left says)."""
    return (
        run_message(run, None, "ended").model_copy(update={"active": False}),
        state_message(run).model_copy(update={"active": False, "allowed": []}),
    )


# The longest a reader batch leaves run.last_status unconverted: the timing task refreshes it
# once a second from its own copy (server/runs/timing.py), the reader after a batch whose samples
# say the state changed, or when it is this old (a rejection or an error without a state change
# is seen within it; a command's own answer refreshes at once). 0.25 s made a conversion of the
# whole status 2-3 times a second with a dashboard open (issue 30 item 4, session 16).
STATUS_REFRESH_S = 1.0


def refresh_state(run: Run, hub: Hub, per_batch: bool = False, copy: CData | None = None) -> None:
    """Publish `state` when the state, a rejection, or liveness changed. `per_batch` (the
    reader, after every batch): compare the few fields of the key first and convert the whole
    status only when it changed or STATUS_REFRESH_S passed (run.last_status feeds the `state`
    snapshot's cycle count and the live log counts: STATUS_REFRESH_S old at most). `copy`:
    a status copy the caller made just now (Channels.status_copy: the timing task's of the
    second), read instead of a copy of this call's own."""
    if run.channels is None:
        return
    now = time.monotonic()
    try:
        if per_batch and run.last_status is not None and now - run.last_status_at < STATUS_REFRESH_S:
            try:
                key = (*run.channels.state_key(), run.alive)
            except ChannelsCorrupt:
                raise
            except ChannelsError:
                return
            if key == run.last_state_key:
                return
        if copy is not None:
            run.last_status, run.last_status_at = status_from_struct(copy), now
        else:
            with contextlib.suppress(StatusBusy):
                run.last_status = run.channels.status()  # while the loop writes it: the last good copy
                run.last_status_at = now
    except ChannelsCorrupt as exc:
        # A status block kept locked while the loop runs (channels/status.py): the run is stopped.
        if run.report_corrupt is not None:
            run.report_corrupt(exc)
        return
    s = run.last_status
    if s is None:
        return
    key = (s.state, s.cmd_rejected, s.running, s.last_error, run.alive)
    if key != run.last_state_key:
        run.last_state_key = key
        hub.publish(state_message(run))
