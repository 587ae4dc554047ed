"""HTTP routes of the ROS 2 bridge the appliance runs (server/runs/ros_bridge.py): its status for anyone
who may watch, the on/off toggle for educators (audited). The bridge's lease gate is not here:
it is a Unix socket only bridge processes started by the appliance can use (see
server/runs/ros_bridge.py and docs/ros2/bridge.md)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, Request
from pydantic import BaseModel, Field

from ..security import audit
from ..security.auth import Perm, User, client_address, current_user, requires

router = APIRouter(prefix="/api/ros", tags=["ros"])


class RosToggle(BaseModel):
    enabled: bool = Field(description="run the ROS 2 bridge with every loop run")


class RosStatus(BaseModel):
    enabled: bool
    state: str = Field(description="running | stopped | failed")
    pid: int | None
    run_id: int | None
    user: str = Field(description="the user the bridge acts for (its XenoCmd obey this user's lease)")
    topics: list[str]
    last_error: str
    restarts: int
    started: float | None = Field(description="Unix time the running bridge process started")
    scheduling: str = Field(description="SCHED_FIFO priority or why normal scheduling")
    output: str = Field(description="the bridge's output file (runs/<id>/ros-bridge.txt)")
    configured_user: str = Field(description="ros_bridge_user setting ('' = whoever started the run)")


@router.get("", response_model=RosStatus, dependencies=[requires(Perm.WATCH)])
async def ros_status(request: Request) -> dict[str, Any]:
    return request.app.state.ros.status()


@router.post("", response_model=RosStatus, dependencies=[requires(Perm.EDUCATOR)])
async def ros_toggle(body: RosToggle, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    ros = request.app.state.ros
    was = ros.enabled
    status = await ros.set_enabled(body.enabled)
    audit.record(
        user, "ros.bridge", {"enabled": body.enabled, "was": was, "run": status["run_id"]}, client_address(request)
    )
    return status
