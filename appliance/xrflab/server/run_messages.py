"""What the browsers are told about the run: its `run` message (started, ended, or the current
one for a client that connects) and its `state` message, made from a `Run`.

The fields are messages.py's (RunMessage, StateMessage); who sees which part of them is
ownership.scope's. `state` goes out when something a person would see changed (the state, a
rejection, the loop's liveness), not per sample: the reader calls `refresh_state` after every
batch, and a command's answer calls it at once.
"""

from __future__ import annotations

import contextlib
from typing import Any

from .. import channels as chmod
from ..channels import ChannelsError
from .hub import Hub
from .run import Run
from .runs import RunRow


def schema_fields(schema: str) -> list[dict[str, Any]]:
    """[{name, type}] from a normalised .msg text, for the dashboard's controls and plots."""
    from ..msgdef import Codec

    return [{"name": f.name, "type": f.type, "count": f.count} for f in Codec(schema).fields]


def run_payload(run: Run | None, last_row: RunRow | None, event: str = "current") -> dict[str, Any]:
    """The `run` message of `run`, or of the last run's record (`last_row`) when none is live."""
    row = run.row if run else last_row
    payload: dict[str, Any] = {
        "event": event,
        "run": row.as_dict() if row else None,
        "active": bool(run and run.alive),
    }
    if run and run.channels is not None:
        info = run.channels.info
        payload.update(
            program=info["program"],
            cycle_freq=info["cycle_freq"],
            backend=info["backend"],
            transport=info["transport"],
            ros2xeno=schema_fields(info["ros2xeno_schema"]),
            xeno2ros=schema_fields(info["xeno2ros_schema"]),
            setpoint=run.setpoint,
        )
    if run and run.guest is not None:
        payload["confinement"] = run.guest.as_dict()
    return payload


def state_payload(run: Run | None) -> dict[str, Any]:
    """The `state` message: the loop's state and the commands it accepts now ("NO RUN" without
    a run whose shared memory is open)."""
    if run is None or run.channels is None or run.last_status is None:
        return {
            "run_id": run.row.id if run else None,
            "active": False,
            "state": 0,
            "name": "NO RUN",
            "allowed": [],
            "rejected": None,
            "last_error": 0,
        }
    s = run.last_status
    rejected = None
    if s.cmd_rejected:
        rejected = {
            "ticket": s.cmd_rejected,
            "cmd": s.last_rejected_cmd,
            "name": chmod.command_name(s.last_rejected_cmd),
            "reason": s.reject_reason,
        }
    alive = run.alive and s.running
    return {
        "run_id": run.row.id,
        "active": alive,
        "state": s.state,
        "name": s.state_name,
        "allowed": chmod.allowed_commands(s.state) if alive else [],
        "rejected": rejected,
        "last_error": s.last_error,
        "cycles": s.cycles,
    }


def refresh_state(run: Run, hub: Hub) -> None:
    """Publish `state` when the state, a rejection, or liveness changed."""
    if run.channels is None:
        return
    with contextlib.suppress(ChannelsError):
        run.last_status = run.channels.status()
    s = run.last_status
    if s is None:
        return
    key = (s.state, s.cmd_rejected, s.running, s.last_error, run.alive)
    if key != run.last_state_key:
        run.last_state_key = key
        hub.publish("state", state_payload(run))
