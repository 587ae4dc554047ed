"""An uploaded project's source folder as the pages show it: which controller package it builds
and the fields of its messages.

Where they are is build.locate_project's answer (one definition, shared with `xrf build`, the
upload check and `xrf upload`), bounded to the source folder: an XRF2 project's messages may be
in its framework folder or an xrf2_msgs package elsewhere in the uploaded workspace, never
outside the upload."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from .. import build

MESSAGES = ("Ros2Xeno", "Xeno2Ros")


def locate(src: Path) -> build.ProjectSource | None:
    """The controller and its messages in ``src``, or None when the source is incomplete (an
    editor save removed a file, say): the page still shows it, the build says what is missing."""
    try:
        return build.locate_project(src, within=src)
    except (build.BuildError, OSError):
        return None


def package_of(located: build.ProjectSource) -> tuple[str, str]:
    """(path relative to the source folder, name) of the controller package a workspace builds,
    ("", "") when the folder is the project itself. The name is the one its package.xml gives
    (what colcon and ROS 2 call it), else the folder's."""
    folder, project = located.folder.resolve(), located.project.resolve()
    if project == folder:
        return "", ""
    name = project.name
    try:
        m = re.search(r"<name>\s*([^<\s]+)\s*</name>", (project / "package.xml").read_text(errors="replace"))
        if m:
            name = m.group(1)
    except OSError:
        pass
    return project.relative_to(folder).as_posix(), name


def message_fields(src: Path, located: build.ProjectSource | None = None) -> dict[str, Any]:
    """{message: [{name, type, count}] or {"error": why}} for Ros2Xeno and Xeno2Ros, parsed
    from the files the build takes (the Projects page's schema, the build's recorded facts)."""
    from ..msgdef import Codec, MsgError, parse_msg_file

    if located is None:
        try:
            located = build.locate_project(src, within=src)
        except (build.BuildError, OSError) as exc:
            reason = exc.message if isinstance(exc, build.BuildError) else str(exc)
            return {name: {"error": reason} for name in MESSAGES}
    out: dict[str, Any] = {}
    for name in MESSAGES:
        p = located.msg_dir / f"{name}.msg"
        try:
            out[name] = [{"name": f.name, "type": f.type, "count": f.count} for f in Codec(parse_msg_file(p)).fields]
        except (MsgError, OSError, ValueError) as exc:
            out[name] = {"error": str(exc)}
    return out
