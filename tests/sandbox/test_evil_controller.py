"""A controller that tries everything a curious student would (tests/fixtures/evil_controller: its
own main, evil.cpp and CMakeLists.txt over the base template's files),
uploaded, built and run through the appliance like any project: every attempt must fail, and
nothing it started may outlive the run."""

from __future__ import annotations

import os
import re
import socket
from pathlib import Path

from xrf_testing.harness import Server, wait_for
from xrf_testing.hostile import project_files
from xrf_testing.projects_support import targz, upload_and_build

REPO = Path(__file__).resolve().parents[2]
EVIL = REPO / "tests" / "fixtures" / "evil_controller"
BASE = REPO / "student_projects" / "templates" / "base"
ATTEMPTS = {
    "read_accounts_db",
    "read_accounts_wal",
    "read_runs_db",
    "read_audit_db",
    "list_other_project",
    "read_other_project",
    "write_other_project",
    "write_data_dir",
    "read_appliance_code",
    "read_appliance_environ",
    "read_shadow",
    "list_home",
    "list_root_home",
    "write_etc",
    "write_usr",
    "signal_appliance",
    "connect_appliance",
    "connect_other_local",
    "connect_internet",
    "inherited_fds",
    "setuid_root",
}


def processes_named(comm: str) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                if Path(f"/proc/{entry}/comm").read_text().strip() == comm:
                    out.append(int(entry))
            except OSError:
                continue
    return out


def test_every_attempt_fails_and_nothing_survives(server: Server, data_dir: Path) -> None:
    server.stop_run()
    other_http, _ = server.login("alice", server.create_user("alice"))
    evil_http, _ = server.login("mallory", server.create_user("mallory"))
    other_pid = other_http.post(
        "/api/projects", files={"file": ("base.tar.gz", targz(project_files(BASE), "alices"), "application/gzip")}
    ).json()["project"]["id"]
    # The folder alice's upload created (the only project so far): its unpacked source.
    (other_src,) = (data_dir / "projects").glob("*/src")
    other_main = other_src / "src"
    assert other_pid and (other_main / "main.cpp").is_file()
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(4)
    targets = (
        f'#define EVIL_DATA_DIR "{data_dir}"\n'
        f'#define EVIL_OTHER_SRC "{other_main}"\n'
        f'#define EVIL_APPLIANCE_CODE "{REPO}/appliance/xrflab/server/security/accounts.py"\n'
        f"#define EVIL_APPLIANCE_PORT {server.url.rsplit(':', 1)[1]}\n"
        f"#define EVIL_OTHER_PORT {listener.getsockname()[1]}\n"
        f"#define EVIL_APPLIANCE_PID {server.proc.pid}\n"
    ).encode()
    try:
        pid, bid = upload_and_build(
            evil_http,
            targz({**project_files(BASE), **project_files(EVIL), "src/targets.h": targets}, "evil"),
            "evil.tar.gz",
        )
        assert evil_http.post("/api/lease/take").status_code == 200
        r = evil_http.post(f"/api/projects/{pid}/builds/{bid}/run", json={}, timeout=60)
        assert r.status_code == 201, r.text
        run = r.json()["run"]
        output = data_dir / "runs" / str(run["id"]) / "output.txt"
        text = wait_for(
            lambda: output.is_file() and "EVIL done" in output.read_text() and output.read_text(),
            30,
            "the evil controller's report",
        )
        found = dict(re.findall(r"^EVIL (\w+): (SUCCEEDED|blocked) ", text, re.M))
        assert set(found) == ATTEMPTS, f"attempts not reported: {ATTEMPTS - set(found)}\n{text}"
        # Of the data folder only the bare path to its own run folder and build is there.
        listed = dict(re.findall(r"^EVIL (list_\w+): listed \([^:]*:(.*)\)$", text, re.M))
        shown = {k: set(v.split()) for k, v in listed.items()}
        assert shown.get("list_data_dir", set()) <= {"runs", "projects"}, text
        assert shown.get("list_runs", set()) <= {str(run["id"])}, text
        assert len(shown.get("list_projects", set())) <= 1, text  # its own project's folder only
        succeeded = [line for line in text.splitlines() if "SUCCEEDED" in line]
        assert not succeeded, "the sandbox let these through:\n" + "\n".join(succeeded)
        # The sleeper exists while the run does (so the check below can see it)...
        sleepers = wait_for(lambda: processes_named("evil-sleeper"), 10, "the sleeper to start")
        assert len(sleepers) == 1
        # ...and is gone with the run, without anyone killing it by pid.
        assert evil_http.post("/api/runs/current/stop", timeout=30).status_code == 200
        wait_for(lambda: not processes_named("evil-sleeper"), 5, "the setsid sleeper to end with the run")
        assert not (other_main / "planted.cpp").exists() and not (data_dir / "planted.txt").exists()
        listed = other_http.get(f"/api/projects/{other_pid}").json()
        assert "planted" not in str(listed)
        row = server.http.get(f"/api/runs/{run['id']}").json()
        shm_dir = Path("/dev/shm") / row["shm"].split("/")[0]
        assert not shm_dir.exists(), f"{shm_dir} left behind"
        assert "all layers hold" in text or os.geteuid() != 0, text
    finally:
        listener.close()
        for p in processes_named("evil-sleeper"):
            os.kill(p, 9)
