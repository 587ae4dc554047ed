"""``xrf upload DIR``: pack a project folder as tar.gz and upload it to the appliance.

    xrf upload my_project                       # new project, prints its id
    xrf upload my_project --project 3 --build   # new version of project 3, build it, wait
    XRF_URL=http://pi.local:8000 XRF_TOKEN=... xrf upload my_project

Build folders, .git and editor folders are not packed; links are left out (the appliance refuses
them), with a warning. DIR may be an XRF2 controller package whose messages are in the XRF2
folder its CMakeLists.txt names (../XRF2) or in an xrf2_msgs package beside it: that message
folder is packed too, where it sits relative to the package, so the appliance finds it by the
same rules as `xrf build` (build.locate_project).
"""

from __future__ import annotations

import argparse
import io
import os
import sys
import tarfile
import time
from pathlib import Path

HELP = "upload a project folder to the appliance (packed as tar.gz); optionally build it"
SKIP = {"build", "install", "log", ".git", "__pycache__", ".vscode", ".idea"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "dir",
        type=Path,
        help="the project folder (with CMakeLists.txt and msg/), an XRF2 "
        "controller package, or a ROS 2 workspace holding one",
    )
    from . import credentials

    p.add_argument(
        "--url",
        default=credentials.url(),
        help=f"the appliance (default $XRF_URL, the one of `xrf login`, or {credentials.DEFAULT_URL})",
    )
    p.add_argument(
        "--token", default=credentials.token(), help="API token (default $XRF_TOKEN or the one of `xrf login`)"
    )
    p.add_argument("--name", default="", help="project name (default: the folder's name)")
    p.add_argument("--project", type=int, help="upload as a new version of this project id")
    p.add_argument("--build", action="store_true", help="build it after uploading and wait for the result")


# How far above the project folder a message folder may be packed from (XRF2 keeps them one or
# two folders up, in the workspace's src/): beyond, the archive's names would spell out the
# student's home folder.
MAX_UP = 3


class PackError(Exception):
    """The folder cannot be uploaded as it is; the message says what to upload instead."""


def messages_outside(folder: Path) -> Path | None:
    """The folder holding the project's Ros2Xeno.msg / Xeno2Ros.msg when it is outside ``folder``
    (an XRF2 package's ../XRF2/.../XRF2_msgs/msg), else None. PackError when the project is
    incomplete (build.locate_project's reason) or the messages are too far away to pack."""
    from . import build

    folder = folder.resolve()
    try:
        msg_dir = build.locate_project(folder).msg_dir.resolve()
    except build.BuildError as exc:
        raise PackError(f"{folder}: {exc.message}") from None
    if msg_dir.is_relative_to(folder):
        return None
    up = Path(os.path.relpath(folder, os.path.commonpath([folder, msg_dir]))).parts
    if len(up) > MAX_UP:
        raise PackError(
            f"{folder}: its messages are in {msg_dir}, too far from the project to pack with it; "
            "upload the ROS 2 workspace that holds both, or copy Ros2Xeno.msg and Xeno2Ros.msg "
            "into the project's msg/ folder"
        )
    return msg_dir


def pack(folder: Path) -> tuple[bytes, list[str]]:
    """tar.gz of the folder's contents (names relative to it); (bytes, warnings). When the messages
    are outside the folder (messages_outside), names are relative to the folder holding both, and
    the message folder's .msg files (and its package's package.xml) are packed as well."""
    folder = folder.resolve()
    warnings: list[str] = []
    msg_dir = messages_outside(folder)
    root = Path(os.path.commonpath([folder, msg_dir])) if msg_dir else folder
    buf = io.BytesIO()

    def add(tar: tarfile.TarFile, p: Path) -> None:
        info = tar.gettarinfo(str(p), arcname=p.relative_to(root).as_posix())
        info.uid = info.gid = 0
        info.uname = info.gname = ""
        with open(p, "rb") as fh:
            tar.addfile(info, fh)

    with tarfile.open(fileobj=buf, mode="w:gz", format=tarfile.PAX_FORMAT) as tar:
        for dirpath, dirnames, filenames in os.walk(folder):
            dirnames[:] = sorted(
                d
                for d in dirnames
                if d not in SKIP and not d.startswith(".") and not _link(Path(dirpath) / d, folder, warnings)
            )
            for f in sorted(filenames):
                p = Path(dirpath) / f
                if _link(p, folder, warnings) or not p.is_file():
                    continue
                add(tar, p)
        if msg_dir is not None:
            extra = sorted(f for f in msg_dir.iterdir() if f.suffix == ".msg" and f.is_file() and not f.is_symlink())
            manifest = msg_dir.parent / "package.xml"
            if manifest.is_file() and not manifest.is_symlink():
                extra.append(manifest)
            for p in extra:
                add(tar, p)
            warnings.append(
                f"packed {os.path.relpath(msg_dir, folder)} too: the project's messages "
                f"(as {msg_dir.relative_to(root).as_posix()}, next to {folder.relative_to(root).as_posix()}/)"
            )
    return buf.getvalue(), warnings


def _link(p: Path, root: Path, warnings: list[str]) -> bool:
    if p.is_symlink():
        warnings.append(f"left out {p.relative_to(root)}: a link (the appliance accepts files and folders only)")
        return True
    return False


def run(args: argparse.Namespace) -> int:
    import httpx

    folder: Path = args.dir
    try:
        data, warnings = pack(folder)
    except PackError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    headers = {"Authorization": f"Bearer {args.token}"} if args.token else {}
    # A name only when one is given: the appliance names a workspace after the controller package
    # it builds (not "ws" or "src"), anything else after the folder (the archive's name).
    name = args.name
    with httpx.Client(base_url=args.url, headers=headers, timeout=60) as http:
        files = {"file": (f"{name or folder.resolve().name}.tar.gz", data, "application/gzip")}
        if args.project:
            r = http.put(f"/api/projects/{args.project}/source", files=files)
        else:
            r = http.post("/api/projects", files=files, data={"name": name})
        if r.status_code >= 400:
            detail = (
                r.json().get("detail") if r.headers.get("content-type", "").startswith("application/json") else r.text
            )
            if isinstance(detail, dict):
                detail = detail.get("error") or detail
            print(f"error: upload refused ({r.status_code}): {detail}", file=sys.stderr)
            return 1
        up = r.json()
        pid = up["project"]["id"]
        print(f"project {pid} ({up['project']['name']}): {up['files']} files, {len(data)} bytes packed")
        if up.get("package"):
            print(f"a ROS 2 workspace: its controller package {up['package']}/ is built")
        if not args.build:
            return 0
        r = http.post(f"/api/projects/{pid}/builds")
        if r.status_code >= 400:
            print(f"error: build refused ({r.status_code}): {r.text}", file=sys.stderr)
            return 1
        b = r.json()
        if b.get("reused"):
            print(f"unchanged source: build {b['id']} reused ({b['result']})")
            return 0 if b["status"] == "ok" else 1
        print(f"build {b['id']} queued")
        while b["status"] in ("queued", "building"):
            time.sleep(0.5)
            b = http.get(f"/api/projects/{pid}/builds/{b['id']}").json()
        print(f"build {b['id']}: {b['status']}: {b['result']}")
        if b["status"] != "ok":
            for d in b.get("details", {}).get("diagnostics", [])[:10]:
                if d["kind"] == "error":
                    loc = f"{d['file']}:{d['line']}" + (f":{d['col']}" if d.get("col") else "") if d["file"] else ""
                    print(f"  {loc} {d['message']}".rstrip())
            return 1
        return 0
