"""``xrf run-disk-helper``: run folders as file systems of their own for an appliance that is
not root (the Pi's ``xrf`` service), done by root on its behalf (server/runs/disk.py).

Mounting needs CAP_SYS_ADMIN, which the appliance never has. This small root service
(deploy/systemd/xrf-run-disk.socket and .service, socket-activated) does exactly that and
nothing else, for one data folder and one user, both named on its command line:

- a request is one JSON line on its Unix socket: ``{"op": "attach", "run": 12, "mb": 2048,
  "files": 65536}``, ``{"op": "release", "run": 12}``, ``{"op": "sweep", "live": [12]}`` or
  ``{"op": "ping"}``; the answer is one JSON line, ``{"ok": true, ...}`` or ``{"error": "..."}``;
- only the appliance's user (SO_PEERCRED) or root is answered;
- the run folder is ``<data>/runs/<run>`` (``run`` an integer), reached by descriptors without
  following a symlink, and must be a folder of the appliance's user, empty and not yet a mount;
  sizes are capped by ``--max-mb`` and ``--max-files``;
- images live in ``--images``, a folder of root's (the appliance cannot plant a link there).

What an appliance owned by an attacker could do with it: mount a file system of at most
``--max-mb`` on an empty folder of its own, and copy such a file system's content into its own
folder. docs/developers/security.md, "Resources the kernel bounds".
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import pwd
import socket
import stat
import struct
import sys
from pathlib import Path
from typing import Any

HELP = "(root) make a non-root appliance's run folders file systems of their own (socket-activated by systemd)"
DEFAULT_SOCKET = "/run/xrf-lab/run-disk.sock"
REQUEST_MAX = 4096


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="the appliance's data folder (its runs/ is served)")
    parser.add_argument("--images", type=Path, required=True, help="a folder of root's for the run images")
    parser.add_argument("--owner", required=True, help="the appliance's user: the only one answered")
    parser.add_argument("--max-mb", type=int, default=2048, help="largest run file system (default 2048)")
    parser.add_argument("--max-files", type=int, default=65536, help="most files in one (default 65536)")
    parser.add_argument(
        "--socket", default=None, help=f"listen here (default: the socket systemd passes, else {DEFAULT_SOCKET})"
    )


class Helper:
    def __init__(self, data: Path, images: Path, owner: int, max_mb: int, max_files: int) -> None:
        self.data, self.images, self.owner = data, images, owner
        self.max_mb, self.max_files = max_mb, max_files

    def _runs(self) -> int:
        data = os.open(self.data, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
        try:
            from .disk import open_dir

            return open_dir(data, "runs")
        finally:
            os.close(data)

    def _images(self) -> None:
        """The images' folder: root's own, 0700, not a link (made on first use)."""
        self.images.mkdir(mode=0o700, exist_ok=True)
        st = os.lstat(self.images)
        if not stat.S_ISDIR(st.st_mode) or st.st_uid != 0 or st.st_mode & 0o077:
            raise ValueError(f"{self.images} must be a folder of root's, mode 0700")

    def handle(self, req: dict[str, Any]) -> dict[str, Any]:
        from . import disk as run_disk

        op = req.get("op")
        if op == "ping":
            return {"ok": True, "max_mb": self.max_mb, "max_files": self.max_files, "data": str(self.data)}
        if op == "sweep":
            live = {str(int(x)) for x in req.get("live", [])}
            return {"ok": True, "done": run_disk.sweep(self.data / "runs", self.images, live)}
        run = int(req.get("run", -1))
        if run < 0:
            raise ValueError("no run")
        name = str(run)
        image = self.images / f"{run}.img"
        runs = self._runs()
        try:
            if op == "attach":
                st = os.stat(name, dir_fd=runs, follow_symlinks=False)
                if not stat.S_ISDIR(st.st_mode) or st.st_uid != self.owner:
                    raise ValueError(f"runs/{name} is not a folder of the appliance's")
                if run_disk.mounted(runs, name):
                    raise ValueError(f"runs/{name} is a mount already")
                folder = run_disk.open_dir(runs, name)
                try:
                    if os.listdir(folder):
                        raise ValueError(f"runs/{name} is not empty")
                finally:
                    os.close(folder)
                mb = max(1, min(int(req.get("mb", self.max_mb)), self.max_mb))
                files = max(64, min(int(req.get("files", self.max_files)), self.max_files))
                spec = run_disk.DiskSpec(mb << 20, files, self.owner, st.st_gid, reserve_for=self.owner)
                self._images()
                run_disk.attach(runs, name, image, spec)
                return {"ok": True, "mb": mb, "files": files}
            if op == "release":
                stats = run_disk.release(runs, name, image)
                skipped = [] if stats is None else stats.skipped[:3]
                return {"ok": True, "skipped": stats.skipped_count if stats else 0, "why": skipped}
            raise ValueError(f"unknown op {op!r}")
        finally:
            os.close(runs)


def _peer_uid(conn: socket.socket) -> int:
    creds = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    return struct.unpack("3i", creds)[1]


def serve(listener: socket.socket, helper: Helper) -> None:
    """One request per connection, one at a time (one appliance, one run at a time)."""
    while True:
        conn, _ = listener.accept()
        with conn:
            conn.settimeout(10)
            try:
                if _peer_uid(conn) not in (helper.owner, 0):
                    conn.sendall(b'{"error": "not the appliance\'s user"}\n')
                    continue
                raw = b""
                while b"\n" not in raw and len(raw) < REQUEST_MAX:
                    chunk = conn.recv(REQUEST_MAX)
                    if not chunk:
                        break
                    raw += chunk
                try:
                    answer = helper.handle(json.loads(raw.split(b"\n", 1)[0]))
                except Exception as exc:  # noqa: BLE001 - the client is told; the helper goes on
                    answer = {"error": f"{type(exc).__name__}: {exc}"}
                conn.sendall((json.dumps(answer) + "\n").encode())
            except OSError:
                continue


def request(path: str, req: dict[str, Any], timeout: float = 120.0) -> dict[str, Any]:
    """The appliance's side: one request to the helper; raises OSError (unreachable) or
    RuntimeError (it refused)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        s.connect(path)
        s.sendall((json.dumps(req) + "\n").encode())
        raw = b""
        while not raw.endswith(b"\n"):
            chunk = s.recv(65536)
            if not chunk:
                break
            raw += chunk
    answer = json.loads(raw or b"{}")
    if not answer.get("ok"):
        raise RuntimeError(answer.get("error", "no answer"))
    return dict(answer)


def _listener(path: str | None) -> socket.socket:
    if path is None and os.environ.get("LISTEN_PID") == str(os.getpid()) and os.environ.get("LISTEN_FDS") == "1":
        return socket.socket(fileno=3)  # systemd's socket activation (sd_listen_fds)
    path = path or DEFAULT_SOCKET
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(path)
    s.listen(8)
    return s


def run(args: argparse.Namespace) -> int:
    if os.geteuid() != 0:
        print("xrf run-disk-helper: must run as root (it mounts file systems)", file=sys.stderr)
        return 2
    owner = pwd.getpwnam(args.owner).pw_uid if not args.owner.isdigit() else int(args.owner)
    helper = Helper(args.data, args.images, owner, args.max_mb, args.max_files)
    listener = _listener(args.socket)
    if args.socket:
        os.chown(args.socket, 0, pwd.getpwuid(owner).pw_gid if not args.owner.isdigit() else owner)
        os.chmod(args.socket, 0o660)
    serve(listener, helper)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="xrf run-disk-helper", description=HELP)
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
