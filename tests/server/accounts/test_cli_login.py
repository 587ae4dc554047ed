"""`xrf login`: an API token for the CLI in ~/.config/xrf-lab/token (0600), sent as Bearer."""

from __future__ import annotations

import os
import stat
import subprocess
import sys

import httpx

from xrf_testing.harness import REPO_ROOT, Server


def xrf(args: list[str], home, stdin: str = "") -> subprocess.CompletedProcess[str]:  # type: ignore[no-untyped-def]
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT / "appliance"), XDG_CONFIG_HOME=str(home))
    env.pop("XRF_TOKEN", None)
    env.pop("XRF_URL", None)
    return subprocess.run(
        [sys.executable, "-m", "xrflab.cli", *args], input=stdin, env=env, text=True, capture_output=True, timeout=60
    )


def test_xrf_login_stores_a_private_token(server: Server, tmp_path) -> None:
    pw = server.create_user("clidev", "student")
    bad = xrf(["login", "--url", server.url, "--user", "clidev", "--password-stdin"], tmp_path, "wrong\n")
    assert bad.returncode == 1 and "refused (401)" in bad.stderr
    ok = xrf(["login", "--url", server.url, "--user", "clidev", "--password-stdin"], tmp_path, pw + "\n")
    assert ok.returncode == 0, ok.stderr
    path = tmp_path / "xrf-lab" / "token"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    assert (tmp_path / "xrf-lab" / "url").read_text().strip() == server.url
    token = path.read_text().strip()
    me = httpx.get(server.url + "/api/me", headers={"Authorization": f"Bearer {token}"}).json()
    assert me["username"] == "clidev"
    gone = xrf(["login", "--forget"], tmp_path)
    assert gone.returncode == 0 and not path.exists()
    assert httpx.get(server.url + "/api/me", headers={"Authorization": f"Bearer {token}"}).status_code == 401
