"""A build sandbox's limits and what the sandbox process is handed.

Two sides must agree on these: the appliance, which reads the limits from its settings and starts
the sandbox (``sandbox_launch.py``), and the sandbox process, which applies them before it execs
the build (``sandbox.py``). The appliance hands the process a ``SandboxSpec`` as JSON on its
command line (it has nothing else in common with the appliance: a fresh Python, a new session).
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field, fields
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..server.settings import Settings


@dataclass(frozen=True)
class SandboxConfig:
    timeout_s: float = 300.0
    memory_mb: int = 2048  # RLIMIT_AS of each process (cc1plus of a big file needs ~1 GB)
    nproc: int = 256  # RLIMIT_NPROC of the build user
    fsize_mb: int = 512  # RLIMIT_FSIZE: largest file a build may write
    cpu_s: int = 900  # RLIMIT_CPU per process
    nofile: int = 1024
    user: str = "xrf-build"
    rt_cpu: int | None = 1  # the loop's CPU; builds never run there
    tmpfs_mb: int = 256

    @staticmethod
    def from_settings(settings: Settings) -> SandboxConfig:
        """These defaults, then XRF_BUILD_* env; builds keep off the loop's CPU (XRF_CPU of the
        appliance's loop_env, else of the environment)."""
        base = SandboxConfig()
        values: dict[str, Any] = {}
        for f in ("timeout_s", "memory_mb", "nproc", "fsize_mb", "cpu_s", "nofile", "user"):
            env = os.environ.get("XRF_BUILD_" + f.upper())
            if env is not None:
                values[f] = type(getattr(base, f))(env)
        cpu = settings.loop_env.get("XRF_CPU") or os.environ.get("XRF_CPU")
        if cpu not in (None, ""):
            values["rt_cpu"] = int(cpu)
        return SandboxConfig(**{**asdict(base), **values})


@dataclass(frozen=True)
class SandboxSpec:
    """One build's sandbox: its limits, who it runs as, the build's whole environment, and the
    folders it keeps seeing where the sandbox covers their parent: (path, read_only)."""

    limits: SandboxConfig
    uid: int
    gid: int
    env: dict[str, str]
    keep: list[tuple[str, bool]] = field(default_factory=list)
    # The data folder: covered in the build's mount namespace except for what ``keep`` puts back.
    hide: str | None = None

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @staticmethod
    def from_json(text: str) -> SandboxSpec:
        data = json.loads(text)
        limits = {f.name: data["limits"][f.name] for f in fields(SandboxConfig)}
        return SandboxSpec(
            limits=SandboxConfig(**limits),
            uid=int(data["uid"]),
            gid=int(data["gid"]),
            env={str(k): str(v) for k, v in data["env"].items()},
            keep=[(str(path), bool(ro)) for path, ro in data["keep"]],
            hide=data.get("hide"),
        )
