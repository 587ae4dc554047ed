"""Issue 26, guest-writable folders: the appliance touches a run folder (and a run's /dev/shm
folder) only through `xrflab.runfolder`, which resolves every name from the folder's
descriptor without following a link and takes plain files only. A new ``open(run_dir / ...)``,
``Path(row.run_dir).read_text()`` or ``os.walk(run.run_dir)`` elsewhere would be a path the guest
controls (a symlink to /etc/shadow, a FIFO) followed as root: this check fails the build on it.

It reads the appliance's source line by line: a line naming a run folder (``run_dir``,
``shm_dir``, or a name assigned from one, like ``root = Path(row.run_dir)``) together with a file
operation (a ``/`` join, ``open(``, ``os.*``/``shutil.*`` file
calls, ``Path`` file methods) must be one of the few listed below, each with the reason it is
safe. Anything else goes through runfolder.py (see docs/developers/security.md, "The run folder").
"""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
CODE = REPO / "appliance" / "xrflab"
HELPER = CODE / "runfolder.py"
# The run's own file system (issue 26, the kernel's disk bound): it mounts an image on the run
# folder before the launcher starts and copies the image's files out after the run's processes are
# gone, by descriptor only (O_NOFOLLOW on every open, links copied as links, never followed, a
# depth bound), so it is a helper of the same kind as runfolder.py, reviewed as one.
DESCRIPTOR_MODULES = {HELPER, CODE / "server" / "runs" / "disk.py"}

NAMES = ("_?run_dir", "shm_dir")  # what the code calls a run folder (plus what is assigned from one)
# `x = <expression naming a run folder>` makes x a run folder too (root = Path(row.run_dir)),
# unless the expression goes through the helper.
ASSIGN = re.compile(r"^\s*([A-Za-z_][\w.]*)\s*(?::[^=]+)?=(?!=)\s*(.+)$")
THROUGH_HELPER = re.compile(
    r"^(RunFolder|open_in|open_output|folder_bytes|remove_folder|confine|recording_size|str|int|len)\("
)
FILE_OP_CALLS = (
    r"|(?<![\w.])open\("  # builtins.open
    r"|\b(os\.(open|walk|listdir|scandir|stat|lstat|unlink|remove|rename|replace|rmdir|mkdir|makedirs|chmod|chown"
    r"|truncate|link|symlink|readlink|chdir)|shutil\.\w+)\("
    r"|\.(iterdir|glob|rglob|read_text|read_bytes|write_text|write_bytes|is_file|is_dir|exists|stat|lstat|unlink"
    r"|mkdir|rmdir|rename|replace|touch|chmod|chown|open|resolve|symlink_to|hardlink_to)\("
)


def patterns(lines: list[str]) -> tuple[re.Pattern[str], re.Pattern[str]]:
    """(a line names a run folder, a line does a file operation) for one source file."""
    names = list(NAMES)
    for _ in range(3):  # a name assigned from a name assigned from a run folder, ...
        named = _named(names)
        for line in lines:
            m = ASSIGN.match(line.split("#", 1)[0])
            if m and named.search(m.group(2)) and not THROUGH_HELPER.match(m.group(2).strip()):
                target = re.escape(m.group(1))
                if target not in names:
                    names.append(target)
    named = _named(names)
    file_op = re.compile(r"(" + named.pattern + r")\)?\s*/(?!\s*[\d/=])" + FILE_OP_CALLS)  # a join, not a division
    return named, file_op


def _named(names: list[str]) -> re.Pattern[str]:
    """NAMES anywhere (row.run_dir too); an assigned name only as itself (root, not x.root)."""
    assigned = [n for n in names if n not in NAMES]
    alt = r"\b(" + "|".join(NAMES) + r")\b"
    return re.compile(alt + (r"|(?<![\w.])(" + "|".join(assigned) + r")\b" if assigned else ""))


# (file below appliance/xrflab, a fragment of the line) -> why it is safe.
ALLOWED = {
    # grading/runner.py: `xrf grade`'s local run folder is the grader's own user's (the TA runs the
    # student's code as themselves, as `xrf run`); on the appliance the run folder is the sandbox's
    # and these reads are bounded: no link followed (O_NOFOLLOW, scandir without following), a
    # bounded count of entries, the output's last 64 KiB, the log through open_log's checks.
    ("grading/runner.py", "`run_dir`, its output into run_dir/output.txt"): "a docstring",
    ("grading/runner.py", 'out_fd = os.open(run_dir / "output.txt"'): "xrf grade's own folder, before the child exists",
    ("grading/runner.py", "run_dir.mkdir(parents=True, exist_ok=True)"): "made by the grader before any guest",
    ("grading/runner.py", 'result.output_tail = _tail(run_dir / "output.txt")'): "O_NOFOLLOW|O_NONBLOCK, last 64 KiB",
    ("grading/runner.py", "the newest regular file under run_dir/logs"): "a docstring",
    ("grading/runner.py", 'for folder in (run_dir / "logs", run_dir):'): "scandir without following links, 64 entries",
    (
        "server/runs/launch.py",
        "run_dir = settings.runs_dir / str(row.id)",
    ): "the run folder's own path, made by the appliance",
    ("server/runs/launch.py", "run_dir.mkdir(parents=True, exist_ok=True)"): "makes the run folder, before any guest",
    ("server/runs/launch.py", "open(os.devnull"): "not the run folder",
    (
        "server/runs/limits.py",
        "runs = os.open(run_dir.parent, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)",
    ): "the runs folder (the appliance's), the parent of the run folder; run_disk works from it by descriptor",
    (
        "server/runs/limits.py",
        "runs = os.open(self.run_dir.parent, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)",
    ): "the runs folder (the appliance's), the parent of the run folder; run_disk works from it by descriptor",
    (
        "server/runs/launch.py",
        "link.unlink()",
    ): "the appliance's own link directly in /dev/shm, beside the loop's folder, out of the loop's reach",
    (
        "server/runs/launch.py",
        'os.symlink(f"/proc/{os.getpid()}/fd/{shm_fd}", link)',
    ): "makes the appliance's own link directly in /dev/shm, out of the loop's reach",
    ("server/runs/launch.py", "os.fdopen(open_in(run_dir"): "opened through runfolder.open_in",
    (
        "server/runs/guest_spawn.py",
        "shm_dir.mkdir(mode=0o700, exist_ok=False)",
    ): "makes the run's /dev/shm folder, before the guest",
    (
        "server/runs/guest_spawn.py",
        "run_dir.mkdir()",
    ): "xrf doctor's probe: a temporary folder of its own, no guest yet",
    (
        "server/runs/guest_spawn.py",
        "shutil.rmtree(shm_dir, ignore_errors=True)",
    ): "xrf doctor's probe: /bin/true wrote nothing there",
    (
        "server/runs/orphans.py",
        "open_log(run_dir / rel, fd=fd)",
    ): "a name for messages; the file is the fd from open_mappable",
    (
        "server/http/logs.py",
        "return Path(data) / CACHE_ROOT",
    ): "<data>/log-cache: the appliance's folder, not the run's",
    ("server/http/logs.py", "if not target.exists():"): "the conversion in <data>/log-cache, not in the run folder",
    (
        "server/runs/orphans.py",
        "Path(row.run_dir).is_dir()",
    ): "the run folder's own path (the appliance's), nothing inside",
    (
        "guest.py",
        'os.chdir(cfg["run_dir"])',
    ): "the launcher, in the guest's namespace before it exists: the folder's own path",
    ("logs/host_writer.py", "RecordFile.open(self._run_dir, rel"): "record_file.py opens through runfolder.open_in",
    ("server/runs/ros_bridge.py", "with open(open_in(bp.run.run_dir"): "opened through runfolder.open_in",
    ("server/runs/ros_bridge.py", "str(Path(run.run_dir) / BRIDGE_OUTPUT)"): "a path shown in the status, never opened",
    (
        "logs/host_writer.py",
        "path = str(self._run_dir / rel)",
    ): "a path for messages; the file is opened by RecordFile.open",
    ("viz/recorder.py", "return Path(run_dir) / SUBDIR"): "a path for messages (Recorder.dir), never opened",
    (
        "viz/recorder.py",
        "Path(run_dir).mkdir(parents=True, exist_ok=True)",
    ): "the run folder's own path (tests: a fresh one)",
}


def offending_lines() -> list[str]:
    found = []
    for path in sorted(CODE.rglob("*.py")):
        if path in DESCRIPTOR_MODULES:
            continue
        rel = path.relative_to(CODE).as_posix()
        lines = path.read_text().splitlines()
        named, file_op = patterns(lines)
        for n, line in enumerate(lines, 1):
            code = line.split("#", 1)[0]
            if code.strip().startswith("def "):
                continue
            if not (named.search(code) and file_op.search(code)):
                continue
            if any(f == rel and fragment in code for f, fragment in ALLOWED):
                continue
            found.append(f"appliance/xrflab/{rel}:{n}: {line.strip()}")
    return found


def test_run_folders_are_touched_through_runfolder_only() -> None:
    found = offending_lines()
    assert not found, (
        "file operations on a run folder outside runfolder.py (use RunFolder / open_in, or list the line "
        "in ALLOWED with why it is safe):\n  " + "\n  ".join(found)
    )


def test_every_allowed_line_still_exists() -> None:
    """A stale entry would let a new line through unseen."""
    text = {p.relative_to(CODE).as_posix(): p.read_text() for p in CODE.rglob("*.py")}
    stale = [f"{f}: {fragment}" for f, fragment in ALLOWED if fragment not in text.get(f, "")]
    assert not stale, stale


def test_the_check_sees_a_path_based_open() -> None:
    """What main had (issue 26, hole 1) is caught."""
    for bad in (
        'path = Path(row.run_dir) / "timing.jsonl"',
        'with open(run.run_dir / "output.txt", "rb") as f:',
        "for dirpath, _dirs, files in os.walk(run_dir):",
        '(self._run_dir / "viz" / "meta.json").write_text(text)',
        "shutil.rmtree(shm_dir, ignore_errors=True)",
    ):
        named, file_op = patterns([bad])
        assert named.search(bad) and file_op.search(bad), bad
    # ...and through a name assigned from a run folder (main's 3D recorder and log listing).
    source = ["self.dir = recording_dir(run_dir)", '(self.dir / "meta.json").write_text(text)']
    named, file_op = patterns(source)
    assert named.search(source[1]) and file_op.search(source[1])
    source = ["root = Path(row.run_dir)", '"timing": (root / "timing.jsonl").is_file()']
    named, file_op = patterns(source)
    assert named.search(source[1]) and file_op.search(source[1])
