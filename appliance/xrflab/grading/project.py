"""What a project can be graded on: its Ros2Xeno fields (setpoints a scenario may drive) and the
variables its logger logs (what checks may read), found in its files so a scenario is checked
against the assignment when it is uploaded, before any student's build runs.

The logged variables come from the sources' `logger.addVariable("name", ...)` calls (a scan: the
names are string literals in every example, template and 20-sim export). A name built at run time
is not found; the scenario is then refused with the names that were, and the educator can name
the variable literally.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from .. import msgdef

ADD_VARIABLE = re.compile(r"addVariable\s*\(\s*\"([A-Za-z_][A-Za-z0-9_]{0,63})\"")
SOURCE_EXT = (".cpp", ".hpp", ".h", ".cc", ".cxx", ".hh")
MAX_FILES = 2000
MAX_FILE_BYTES = 1 << 20


def ros2xeno_fields(project: Path) -> set[str]:
    for p in (project / "msg" / "Ros2Xeno.msg", *project.glob("*/msg/Ros2Xeno.msg")):
        if p.is_file():
            try:
                return {f.name for f in msgdef.parse_msg_file(p)}
            except (msgdef.MsgError, OSError, ValueError):
                return set()
    return set()


def logged_variables(project: Path) -> set[str]:
    names: set[str] = set()
    seen = 0
    for root, dirs, files in os.walk(project, followlinks=False):
        dirs[:] = [d for d in dirs if d not in ("build", ".git") and not d.startswith(".")]
        for f in files:
            if not f.endswith(SOURCE_EXT):
                continue
            seen += 1
            if seen > MAX_FILES:
                return names
            p = Path(root) / f
            try:
                if p.is_symlink() or p.stat().st_size > MAX_FILE_BYTES:
                    continue
                names |= set(ADD_VARIABLE.findall(p.read_text(errors="replace")))
            except OSError:
                continue
    return names
