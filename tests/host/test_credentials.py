"""xrflab/credentials.py: where `xrf login` keeps the token and URL, and who wins (the environment
over the files). In-process, with a config folder of the test's own (XDG_CONFIG_HOME)."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from xrflab import credentials


@pytest.fixture
def config(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    monkeypatch.delenv("XRF_TOKEN", raising=False)
    monkeypatch.delenv("XRF_URL", raising=False)
    return tmp_path / "xrf-lab"


def test_nothing_saved_means_no_header_and_the_default_url(config: Path) -> None:
    assert credentials.token() == ""
    assert credentials.auth_headers() == {}
    assert credentials.url() == credentials.DEFAULT_URL


def test_save_is_private_and_read_back(config: Path) -> None:
    path = credentials.save("http://bench-3:8000/", "tok-123")
    assert path == config / "token"
    assert stat.S_IMODE(config.stat().st_mode) == 0o700
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert credentials.token() == "tok-123"
    assert credentials.url() == "http://bench-3:8000"  # no trailing slash: paths are appended
    assert credentials.auth_headers() == {"Authorization": "Bearer tok-123"}


def test_an_older_wider_token_file_is_narrowed(config: Path) -> None:
    config.mkdir(mode=0o755)
    old = config / "token"
    old.write_text("old\n")
    old.chmod(0o644)
    credentials.save("http://x", "new")
    assert stat.S_IMODE(old.stat().st_mode) == 0o600 and old.read_text() == "new\n"
    assert stat.S_IMODE(config.stat().st_mode) == 0o700


def test_the_environment_wins_and_forget_removes_the_token_only(config: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    credentials.save("http://saved", "saved")
    monkeypatch.setenv("XRF_TOKEN", "env-token")
    monkeypatch.setenv("XRF_URL", "http://env")
    assert credentials.token() == "env-token" and credentials.url() == "http://env"
    monkeypatch.delenv("XRF_TOKEN")
    monkeypatch.delenv("XRF_URL")
    credentials.forget()
    credentials.forget()  # twice is fine
    assert credentials.token() == "" and credentials.url() == "http://saved"
