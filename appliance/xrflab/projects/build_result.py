"""The build inside the sandbox, and how its outcome gets out.

Inside the sandbox the build is ``python -m xrflab.projects.builder --inner SRC BUILD_DIR``: it
runs ``xrflab.build`` and writes its outcome to ``xrf-result.json`` in the build folder, the only
thing the sandbox hands back besides its output. The appliance reads that file as untrusted (the
build user wrote it): not through a link, at most 1 MiB, and anything but a JSON object is no
result.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

RESULT_FILE = "xrf-result.json"


def inner_main(src: str, build_dir: str) -> int:
    """Inside the sandbox: the build itself; the result goes to a JSON file in the build folder."""
    from xrflab import build

    out = Path(build_dir) / RESULT_FILE
    try:
        # within=src: the messages are looked for in the uploaded source only (not in the
        # project folder's older versions next to it).
        r = build.build_project(src, Path(build_dir) / "cmake", log=lambda line: print(line, flush=True), within=src)
    except build.BuildError as exc:
        out.write_text(json.dumps({"ok": False, "error": exc.message}))
        print(f"error: {exc.message}", flush=True)
        return 1
    out.write_text(
        json.dumps(
            {
                "ok": True,
                "executable": str(r.executable),
                "layout": r.layout,
                "twenty_sim": r.twenty_sim,
                "taken": r.taken,
                "left_out": r.left_out,
            }
        )
    )
    return 0


def read_result(build_dir: Path) -> dict[str, Any]:
    """The build's result as the build wrote it ({} when there is none or it is not an object)."""
    p = build_dir / RESULT_FILE
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError:
        return {}
    with os.fdopen(fd) as f:
        try:
            data = json.loads(f.read(1 << 20))
        except ValueError:
            return {}
    return data if isinstance(data, dict) else {}
