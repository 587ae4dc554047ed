"""Running one build in its sandbox: the appliance's side.

What the build gets is written down here and nowhere else: its whole environment (nothing of the
appliance's own), the folders it keeps seeing where the sandbox covers their parent (its source
and rt_core read-only, its build folder, the appliance's code and Python read-only), the data
folder covered, and its token (``build_procs.py``). The sandbox process (``sandbox.py``) gets
that as a ``SandboxSpec``; its output, the build's log, comes back line by line. The wall time is
enforced from here: at the limit, and at the end of every build, the build's processes are ended
(``build_procs.kill_build``).
"""

from __future__ import annotations

import contextlib
import os
import secrets
import signal
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path

from ..tied import popen_tied
from .build_procs import TOKEN_ENV, RunningBuilds, kill_build
from .build_user import python_for
from .sandbox_config import SandboxConfig, SandboxSpec

APPLIANCE_DIR = Path(__file__).resolve().parents[2]  # appliance/ (the xrflab package's parent)
# The module whose ``--sandbox`` and ``--inner`` the build runs (builder.main): its name is what
# a process listing shows of a build.
ENTRY = "xrflab.projects.builder"


def run_sandboxed(
    src: Path,
    build_dir: Path,
    cache_dir: Path | None,
    uid: int,
    gid: int,
    log: Callable[[str], None],
    *,
    config: SandboxConfig,
    hide_dir: Path | None,
    running: RunningBuilds,
) -> tuple[bool, int]:
    """Build ``src`` in ``build_dir`` as ``uid``/``gid``, every output line to ``log``; returns
    (timed out, exit code)."""
    token = secrets.token_hex(16)
    env = {
        TOKEN_ENV: token,  # marks this build's processes (kill_build_processes)
        "PATH": "/usr/local/bin:/usr/bin:/bin",
        "HOME": str(build_dir),
        "TMPDIR": "/tmp",
        "LANG": "C.UTF-8",
        "PYTHONPATH": str(APPLIANCE_DIR),
        "PYTHONDONTWRITEBYTECODE": "1",
        "CLICOLOR_FORCE": "0",
    }
    if cache_dir is not None:
        env["XRF_CACHE_DIR"] = str(cache_dir)
    elif os.environ.get("XRF_CACHE_DIR"):
        env["XRF_CACHE_DIR"] = os.environ["XRF_CACHE_DIR"]
    inner = [python_for(uid), "-m", ENTRY, "--inner", str(src), str(build_dir)]
    from .. import build

    cache = Path(env.get("XRF_CACHE_DIR") or build._cache_root()).resolve()
    # What the build needs where the sandbox covers a folder (the data folder, /tmp, ...).
    keep = [
        (str(src.resolve()), True),
        (str(build_dir.resolve()), False),
        (str(cache), True),
        (str(APPLIANCE_DIR), True),
        (str(build.REPO_ROOT / "rt_core"), True),
        (str(Path(sys.prefix).resolve()), True),
    ]
    hide = hide_dir.resolve() if hide_dir else None
    covered = hide is not None and all(Path(k).is_relative_to(hide) for k, _ in keep[:2])
    spec = SandboxSpec(config, uid, gid, env, keep, str(hide) if covered else None)
    cmd = [sys.executable, "-m", ENTRY, "--sandbox", spec.to_json(), "--", *inner]
    wenv = {TOKEN_ENV: token, "PATH": env["PATH"], "PYTHONPATH": str(APPLIANCE_DIR), "LANG": "C.UTF-8"}
    # Tied: a build does not run on after the appliance died (server/children.popen_tied).
    proc = popen_tied(
        cmd,
        death_signal=signal.SIGKILL,
        cwd=build_dir,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        errors="replace",
        bufsize=1,
        env=wenv,
    )
    running.add(proc, token)

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            log(line.rstrip("\n"))

    reader = threading.Thread(target=pump, name="xrf-build-output", daemon=True)
    reader.start()
    timed_out = False
    try:
        rc = proc.wait(timeout=config.timeout_s)
    except subprocess.TimeoutExpired:
        timed_out = True
        with contextlib.suppress(OSError):
            os.killpg(proc.pid, signal.SIGKILL)
        rc = proc.wait()
    finally:
        # Whatever the build left behind (background children, a fork bomb's remains): the
        # group's SIGKILL ends the PID namespace; the token finds them without one. Only
        # this build's: another appliance's build as the same user goes on.
        kill_build(proc, token)
        running.remove(proc)
    reader.join(5)
    if timed_out:
        log(f"sandbox: wall-time limit of {config.timeout_s:.0f} s reached: build stopped")
    return timed_out, rc
