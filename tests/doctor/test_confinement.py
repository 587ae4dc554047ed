"""xrf doctor's `confinement` check: which run sandbox confines students' controllers (mode,
identity, each layer holding or missing with its reason). Faked reports for every verdict, and
the real probe (guest_spawn.probe: /bin/true started in the sandbox as a run would be) on this
machine, with a layer dropped through the test-only $XRF_GUEST_TEST_DROP."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from xrflab import doctor, guest
from xrflab.doctor import FAILURE, OK, SKIPPED, WARNING, ConfinementProbe, Context
from xrflab.server.runs.guest_spawn import GuestReport, identity
from xrflab.server.settings import Settings

ALL_HOLD = {name: "" for name in guest.LAYERS}


def fake(layers=None, error="", mode="root", notes=None, ident="controllers run as xrf-run (uid 999)"):
    report = GuestReport(mode=mode, layers=dict(ALL_HOLD if layers is None else layers), notes=notes or [], error=error)
    return lambda ctx: ConfinementProbe(report, ident, "xrf")


def check(probe, **kw):
    return doctor.check_confinement(Context(root=Path("/"), guest_probe=probe, **kw))


def test_all_layers_hold_is_ok_and_lists_every_layer():
    r = check(fake())
    assert r.status == OK, r
    assert (
        "mode root" in r.detail and "controllers run as xrf-run (uid 999)" in r.detail and "probed as xrf" in r.detail
    )
    assert f"all {len(guest.LAYERS)} layers hold" in r.detail
    assert [i["name"] for i in r.items] == list(guest.LAYERS)
    assert all(i["status"] == "ok" and i["detail"] == "" for i in r.items)
    assert r.to_dict()["items"] == r.items


def test_missing_layer_fails_when_runs_are_refused():
    why = "no subordinate uid for this user (/etc/subuid) or no newuidmap"
    r = check(
        fake({**ALL_HOLD, "user": why}, error="missing protection: user: ...", mode="userns"), allow_unconfined=False
    )
    assert r.status == FAILURE, r
    assert "mode userns" in r.detail and f"missing: user ({why})" in r.detail
    assert "runs are refused" in r.detail and "--allow-unconfined" in r.detail
    assert "/etc/subuid" in r.fix and "uidmap" in r.fix
    user = next(i for i in r.items if i["name"] == "user")
    assert user == {"name": "user", "status": "missing", "detail": why}
    assert sum(i["status"] == "missing" for i in r.items) == 1


def test_missing_layer_is_a_warning_when_the_educator_allowed_it():
    r = check(
        fake(
            {
                **ALL_HOLD,
                "network": "unshare refused (Operation not permitted)",
                "pid": "unshare refused (Operation not permitted)",
            }
        ),
        allow_unconfined=True,
    )
    assert r.status == WARNING, r
    assert "controllers run WITHOUT: " in r.detail and "network (unshare refused" in r.detail
    assert "pid (" in r.detail and "allowed by --allow-unconfined" in r.detail
    assert "user namespaces" in r.fix and r.fix.count("unprivileged_userns_clone") == 1  # one fix, said once
    # the educator's choice may come from the appliance's settings too
    data = Path("/nonexistent")
    r = check(fake({**ALL_HOLD, "user": "x"}), settings=Settings(data_dir=data, allow_unconfined=True))
    assert r.status == WARNING
    r = check(fake({**ALL_HOLD, "user": "x"}), settings=Settings(data_dir=data, allow_unconfined=False))
    assert r.status == FAILURE


def test_sandbox_that_cannot_start_fails_even_when_allowed():
    r = check(
        fake(
            {},
            error="no user namespace (Operation not permitted): the loop cannot be confined without root",
            mode="userns",
        ),
        allow_unconfined=True,
    )
    assert r.status == FAILURE and "could not start a controller" in r.detail and "no user namespace" in r.detail
    assert "user namespaces" in r.fix


def test_prepared_tree_is_not_probed():
    r = doctor.check_confinement(Context(root=Path("/tmp")))
    assert r.status == SKIPPED and "prepared tree" in r.detail


def test_without_the_appliance_dependencies_it_is_not_checked():
    def probe(ctx):
        raise ImportError("No module named 'cffi'")

    r = check(probe)
    assert r.status == SKIPPED and "cffi" in r.detail


# ---- the real probe on this machine ----------------------------------------------------------

_AVAILABLE: list = []


def sandbox_or_skip(tmp_path) -> None:
    """As a normal user on a machine without user namespaces the sandbox cannot start at all
    (the check then fails, tested above with a faked report): nothing more to see here."""
    if not _AVAILABLE:
        from xrflab.server.runs.guest_spawn import probe

        report = probe(Settings(data_dir=tmp_path, allow_unconfined=True))
        _AVAILABLE.append(not (report.error and not report.missing))
    if not _AVAILABLE[0]:
        pytest.skip("the run sandbox cannot start a controller on this machine as this user")


@pytest.mark.live  # the real probe: a sandbox and mkfs, processes the walk cannot see (tiers.py)
def test_real_probe_reports_this_machines_sandbox(tmp_path):
    """guest_spawn.probe starts /bin/true in the sandbox: as root every layer holds here; the
    mode and identity are those guest_spawn.identity() gives."""
    sandbox_or_skip(tmp_path)
    ctx = Context(root=Path("/"), settings=Settings(data_dir=tmp_path))
    r = doctor.check_confinement(ctx)
    ident = identity()
    assert f"mode {ident.mode}" in r.detail and ident.note in r.detail, r
    assert [i["name"] for i in r.items] == list(guest.LAYERS)
    if os.geteuid() == 0:
        assert r.status == OK, r
    else:  # a normal user: whatever this machine gives, said layer by layer
        missing = [i for i in r.items if i["status"] == "missing"]
        assert (r.status == OK) == (not missing), r
        for i in missing:
            assert i["detail"] and i["name"] in r.detail


@pytest.mark.live  # the real probe: a sandbox and mkfs, processes the walk cannot see (tiers.py)
@pytest.mark.parametrize("allow,status", [(False, FAILURE), (True, WARNING)])
def test_real_probe_with_a_dropped_layer(tmp_path, monkeypatch, allow, status):
    sandbox_or_skip(tmp_path)
    monkeypatch.setenv("XRF_GUEST_TEST_DROP", "network")
    r = doctor.check_confinement(Context(root=Path("/"), settings=Settings(data_dir=tmp_path, allow_unconfined=allow)))
    assert r.status == status, r
    net = next(i for i in r.items if i["name"] == "network")
    assert net == {"name": "network", "status": "missing", "detail": "skipped for a test"}
    assert "network (skipped for a test)" in r.detail


def test_cli_shows_the_layers_and_honours_allow_unconfined(tmp_path):
    """`xrf doctor` on this machine: the confinement line, one line per layer; with a layer
    dropped it fails, and --allow-unconfined makes that a warning."""
    sandbox_or_skip(tmp_path)
    env = dict(os.environ, XRF_GUEST_TEST_DROP="user")
    env.pop("XRF_ALLOW_UNCONFINED", None)
    base = [sys.executable, "-m", "xrflab.cli", "doctor", "--no-live", "--data", str(tmp_path)]
    text = subprocess.run(base, capture_output=True, text=True, env=env, timeout=120)
    out = text.stdout
    assert "[FAIL] Run sandbox" in out, out + text.stderr
    assert "user          MISSING: skipped for a test" in out and "network       holds" in out
    assert text.returncode == 1
    js = subprocess.run([*base, "--json", "--allow-unconfined"], capture_output=True, text=True, env=env, timeout=120)
    conf = {r["id"]: r for r in json.loads(js.stdout)}["confinement"]
    assert conf["status"] == WARNING and "WITHOUT: user (skipped for a test)" in conf["detail"], conf
    assert {i["name"]: i["status"] for i in conf["items"]}["user"] == "missing"


def test_helpers_refused_points_at_no_new_privileges():
    r = check(
        fake({}, error="newuidmap/newgidmap refused the subordinate ids of /etc/subuid, /etc/subgid", mode="userns")
    )
    assert r.status == FAILURE and "NoNewPrivileges" in r.fix and "deploy/install" in r.fix


# ---- xrf serve --allow-unconfined ----------------------------------------------------------


def test_serve_allow_unconfined_reaches_the_settings(tmp_path, monkeypatch):
    """`xrf serve --allow-unconfined` (and --trusted-proxy beside it) end in the Settings the app
    is made with; without it the environment's default holds (off)."""
    from xrflab import cli
    from xrflab.server import app as app_module
    from xrflab.server.cli import serve as cli_serve

    seen = []
    monkeypatch.setattr(app_module, "create_app", lambda settings: settings)
    monkeypatch.setattr(cli_serve, "serve", lambda app, settings: seen.append(settings))
    monkeypatch.delenv("XRF_ALLOW_UNCONFINED", raising=False)
    parser = cli.build_parser()
    for argv, want in ((["--allow-unconfined"], True), ([], False)):
        args = parser.parse_args(["serve", "--data", str(tmp_path), "--trusted-proxy", "10.0.0.1", *argv])
        assert cli_serve.run(args) == 0
        assert seen[-1].allow_unconfined is want and seen[-1].trusted_proxies == ("10.0.0.1",)
    text = subprocess.run(
        [sys.executable, "-m", "xrflab.cli", "serve", "--help"], capture_output=True, text=True
    ).stdout
    help_text = " ".join(text.split())
    assert "--allow-unconfined" in help_text and "let runs start when a protection layer" in help_text
    assert "--trusted-proxy" in help_text
