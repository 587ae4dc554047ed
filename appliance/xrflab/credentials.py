"""The CLI's appliance credentials: ``xrf login`` stores an API token in
~/.config/xrf-lab/token (mode 0600) and the appliance's URL next to it in ``url``; remote
commands (``xrf upload``, ...) send ``Authorization: Bearer <token>``. XRF_URL / XRF_TOKEN in
the environment win over the files. Stdlib only: every ``xrf`` call may import this."""

from __future__ import annotations

import os
from pathlib import Path

from .server.settings import Settings

DEFAULT_URL = f"http://{Settings.host}:{Settings.port}"


def config_dir() -> Path:
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "xrf-lab"


def _read(name: str) -> str:
    try:
        return (config_dir() / name).read_text().strip()
    except OSError:
        return ""


def token() -> str:
    return os.environ.get("XRF_TOKEN") or _read("token")


def url() -> str:
    return os.environ.get("XRF_URL") or _read("url") or DEFAULT_URL


def auth_headers() -> dict[str, str]:
    t = token()
    return {"Authorization": f"Bearer {t}"} if t else {}


def save(appliance_url: str, api_token: str) -> Path:
    """Write the token (0600, in a 0700 folder) and the URL; returns the token file."""
    folder = config_dir()
    folder.mkdir(parents=True, exist_ok=True)
    os.chmod(folder, 0o700)
    path = folder / "token"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.fchmod(fd, 0o600)  # an older file may have had wider rights
        os.write(fd, (api_token + "\n").encode())
    finally:
        os.close(fd)
    (folder / "url").write_text(appliance_url.rstrip("/") + "\n")
    return path


def forget() -> None:
    for name in ("token",):
        try:
            (config_dir() / name).unlink()
        except FileNotFoundError:
            pass
