"""The appliance's services the room's side of a bench works with (its commands, its status)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..grading.service import GradingService
    from ..projects.service import ProjectsService
    from ..selfcheck_service import SelfCheckService
    from ..server.runs.supervisor import Supervisor
    from ..server.security.auth import Security
    from ..server.settings import Settings


@dataclass(frozen=True)
class BenchServices:
    """What the room's side of a bench works with: the appliance's services, made once by the
    composition root (server/app.py) and handed over, not fished out of the app's state."""

    settings: Settings
    supervisor: Supervisor
    security: Security
    selfcheck: SelfCheckService
    projects: ProjectsService
    grading: GradingService
