"""The run-folder helper (xrflab.runfolder) on a real file system, with both resolvers: the
kernel's openat2 (RESOLVE_BENEATH | RESOLVE_NO_SYMLINKS) and the O_NOFOLLOW walk used where
openat2 is missing. Everything a guest can plant in its folder - symlinks to files and folders,
on the way and at the end, FIFOs, hard links, files of its own where the appliance's should be,
deep trees, names that are not UTF-8 - and what the helper must do with it. The same against a
real appliance and a hostile controller: test_hostile_run_folder.py."""

from __future__ import annotations

import errno
import mmap
import os
import stat
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from xrflab import runfolder
from xrflab.runfolder import RunFolder, RunPathError, remove_folder, shown, unshown

SECRET = b"secret: not the run's\n"


@pytest.fixture(params=["openat2", "walk"])
def resolver(request: pytest.FixtureRequest) -> Iterator[str]:
    if request.param == "openat2" and not runfolder.openat2_available():
        pytest.skip("this kernel has no openat2 (the walk is tested)")
    runfolder.use_openat2(request.param == "openat2")
    yield request.param
    runfolder.use_openat2(None)


@pytest.fixture
def tree(tmp_path: Path) -> tuple[Path, Path]:
    """(run folder, a folder outside it holding `secret` and `logs/leak.bin`)."""
    run, outside = tmp_path / "runs" / "7", tmp_path / "outside"
    run.mkdir(parents=True)
    (outside / "logs").mkdir(parents=True)
    (outside / "secret").write_bytes(SECRET)
    (outside / "logs" / "leak.bin").write_bytes(SECRET)
    return run, outside


def _outside_unchanged(outside: Path) -> None:
    assert (outside / "secret").read_bytes() == SECRET
    assert sorted(p.name for p in outside.iterdir()) == ["logs", "secret"]
    assert [p.name for p in (outside / "logs").iterdir()] == ["leak.bin"]


def test_openat2_is_used_on_this_kernel() -> None:
    """Linux >= 5.6 (the Pi's 6.x, this machine's): the kernel does the confining."""
    runfolder.use_openat2(None)
    assert runfolder.openat2_available()


def test_links_anywhere_are_refused_for_reading_and_writing(resolver: str, tree: tuple[Path, Path]) -> None:
    run, outside = tree
    (run / "file-link").symlink_to(outside / "secret")
    (run / "dir-link").symlink_to(outside)
    (run / "a").mkdir()
    (run / "a" / "up").symlink_to("../../..")
    (run / "rel-link").symlink_to("a")
    create = os.O_WRONLY | os.O_CREAT | os.O_APPEND
    with RunFolder(run) as rf:
        for rel in ("file-link", "dir-link/secret", "dir-link/new", "a/up/outside/secret", "rel-link/x"):
            for flags in (os.O_RDONLY, create):
                with pytest.raises(OSError) as exc:
                    os.close(rf.open(rel, flags, create_dirs=True))
                assert exc.value.errno in (errno.ELOOP, errno.ENOTDIR, errno.EXDEV), (rel, exc.value)
            assert not rf.is_file(rel)
            with pytest.raises(OSError):
                rf.read_bytes(rel, 1 << 20)
        for rel in ("../outside/secret", "/etc/passwd", "a/../../x", "", "a//b", "./x", "x\0y"):
            with pytest.raises(RunPathError):
                rf.open(rel)
        # A link named where a whole file is written is replaced, never written through; a
        # folder link on the way is refused.
        rf.replace("file-link", b"the run's own")
        assert (run / "file-link").read_bytes() == b"the run's own" and not (run / "file-link").is_symlink()
        with pytest.raises(OSError):
            rf.replace("dir-link/secret", b"x")
        with pytest.raises(OSError):
            rf.makedirs("dir-link/deeper")
    _outside_unchanged(outside)


def test_fifos_sockets_and_hard_links_are_not_plain_files(resolver: str, tree: tuple[Path, Path]) -> None:
    run, outside = tree
    os.mkfifo(run / "fifo.bin")
    os.link(outside / "secret", run / "hard.bin")
    with RunFolder(run) as rf:
        for rel in ("fifo.bin", "hard.bin"):
            for flags in (os.O_RDONLY, os.O_WRONLY | os.O_APPEND, os.O_RDWR):
                t0 = time.monotonic()
                with pytest.raises(OSError) as exc:
                    os.close(rf.open(rel, flags))
                # EPERM: refused after the open; ENXIO: a FIFO without a reader refuses O_NONBLOCK writers
                assert exc.value.errno in (errno.EPERM, errno.ENXIO), exc.value
                assert time.monotonic() - t0 < 1.0, f"{rel}: the open blocked"
            assert not rf.is_file(rel)
        # A FIFO where a whole file is written: replaced, nothing blocks.
        t0 = time.monotonic()
        rf.replace("fifo.bin", b"data")
        assert time.monotonic() - t0 < 1.0 and (run / "fifo.bin").read_bytes() == b"data"
        # Truncation happens after the checks: the hard link's other file keeps its bytes.
        with pytest.raises(OSError):
            rf.open("hard.bin", os.O_WRONLY, truncate=True)
        with pytest.raises(ValueError):
            rf.open("x", os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    _outside_unchanged(outside)


@pytest.mark.skipif(os.geteuid() != 0, reason="making a file of another user needs root")
def test_a_file_of_the_guest_where_the_appliance_writes_is_refused(resolver: str, tree: tuple[Path, Path]) -> None:
    run, _ = tree
    (run / "timing.jsonl").write_bytes(b"the guest's\n")
    os.chown(run / "timing.jsonl", 65534, 65534)
    with RunFolder(run) as rf:
        with pytest.raises(OSError, match="not the appliance's file"):
            rf.open("timing.jsonl", os.O_WRONLY | os.O_CREAT | os.O_APPEND, own=True)
        os.close(rf.open("timing.jsonl"))  # reading it is fine: it is the run's, shown to its owner
        fd = rf.open("mine.jsonl", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o666, own=True)
        os.close(fd)
    mode = (run / "mine.jsonl").stat().st_mode
    assert not mode & 0o027, "the appliance's files: never writable by the group, never others'"


def test_reads_are_bounded(resolver: str, tree: tuple[Path, Path]) -> None:
    run, _ = tree
    (run / "big").write_bytes(b"x" * 5000)
    with RunFolder(run) as rf:
        assert rf.read_bytes("big", 5000) == b"x" * 5000
        with pytest.raises(OSError) as exc:
            rf.read_bytes("big", 4999)
        assert exc.value.errno == errno.EFBIG


def test_a_folder_swapped_for_a_link_during_a_listing_is_not_entered(resolver: str, tree: tuple[Path, Path]) -> None:
    run, outside = tree
    (run / "d").mkdir()
    (run / "d" / "own.bin").write_bytes(b"own")
    (run / "link").symlink_to(outside)
    os.mkfifo(run / "fifo")
    with RunFolder(run) as rf:
        seen = {}
        walk = rf.walk()
        for rel, st_ in walk:
            seen[rel] = st_
            if rel == "d":  # listed; before it is entered, the guest swaps it for a link
                os.rename(run / "d", run / "d-old")
                (run / "d").symlink_to(outside / "logs")
        assert "d/leak.bin" not in seen and "link/secret" not in seen, sorted(seen)
        assert stat.S_ISLNK(seen["link"].st_mode) and stat.S_ISFIFO(seen["fifo"].st_mode)
        files = dict(rf.walk_files())
        assert set(files) == {"d-old/own.bin"}, sorted(files)


def test_listings_are_bounded_in_depth_and_entries(tree: tuple[Path, Path]) -> None:
    run, _ = tree
    for i in range(50):
        (run / f"f{i}").write_bytes(b"")
    deep = run
    for _ in range(runfolder.MAX_DEPTH + 5):
        deep = deep / "d"
    deep.mkdir(parents=True)
    (deep / "deepest.bin").write_bytes(b"")
    with RunFolder(run) as rf:
        assert len(list(rf.walk(max_entries=20))) == 20
        assert not [r for r, _ in rf.walk() if r.endswith("deepest.bin")]


def _deep_chain(top: Path, depth: int) -> None:
    """`depth` nested folders below `top`, longer than any path (made fd by fd)."""
    fd = os.open(top, os.O_RDONLY | os.O_DIRECTORY)
    try:
        for _ in range(depth):
            os.mkdir("dd", dir_fd=fd)
            nxt = os.open("dd", os.O_RDONLY | os.O_DIRECTORY, dir_fd=fd)
            os.close(fd)
            fd = nxt
        with open(os.open("f", os.O_WRONLY | os.O_CREAT, 0o600, dir_fd=fd), "wb") as f:
            f.write(b"x")
    finally:
        os.close(fd)


def _fds_into(root: Path) -> list[str]:
    """This process's descriptors open on something under `root`: what a walk of the run folder
    would leak. (Not a count of all descriptors: other threads of the test process open and close
    their own meanwhile; CI once saw 14 where 17 were before.)"""
    found = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue  # closed meanwhile (the listing's own descriptor, another thread's)
        if target == str(root) or target.startswith(f"{root}/"):
            found.append(f"{fd} -> {target}")
    return found


def test_removal_follows_no_link_and_takes_deep_trees(resolver: str, tree: tuple[Path, Path]) -> None:
    run, outside = tree
    (run / "logs").mkdir()
    (run / "logs" / "log.bin").write_bytes(b"run's")
    (run / "logs" / "to-secret").symlink_to(outside / "secret")
    (run / "to-outside").symlink_to(outside)
    (run / "nested" / "deeper").mkdir(parents=True)
    (run / "nested" / "deeper" / "to-outside").symlink_to(outside)
    os.mkfifo(run / "nested" / "fifo")
    os.link(outside / "secret", run / "hard")
    _deep_chain(run, 3000)
    locked = run / "locked"
    locked.mkdir()
    (locked / "x").write_bytes(b"")
    os.chmod(locked, 0o500)  # a folder the guest made read-only
    try:
        with RunFolder(run) as rf:
            rf.remove_tree("nested")
            assert not (run / "nested").exists()
            if os.geteuid() != 0:
                os.chmod(locked, 0o700)
            rf.clear()
            assert list(run.iterdir()) == []
        remove_folder(run)
        assert not run.exists()
        remove_folder(run)  # gone already: nothing to do
    finally:
        if locked.exists():
            os.chmod(locked, 0o700)
    assert _fds_into(run.parent) == []
    _outside_unchanged(outside)


def test_removing_a_folder_that_is_a_link_removes_the_link(tree: tuple[Path, Path]) -> None:
    run, outside = tree
    shm = run.parent / "shm-link"
    shm.symlink_to(outside)
    remove_folder(shm)
    assert not shm.is_symlink()
    _outside_unchanged(outside)


def test_only_files_nobody_else_can_change_are_mapped(resolver: str, tree: tuple[Path, Path]) -> None:
    """A guest that truncates a mapped file kills the reader (SIGBUS): its files are copied."""
    run, _ = tree
    mine, theirs = run / "mine.bin", run / "theirs.bin"
    for p in (mine, theirs):
        p.write_bytes(b"0123456789" * 1000)
    os.chmod(mine, 0o640)
    os.chmod(theirs, 0o660)  # the group (the guest) may write it
    with RunFolder(run) as rf:
        fd = rf.open_mappable("mine.bin")
        try:
            assert os.fstat(fd).st_ino == mine.stat().st_ino
        finally:
            os.close(fd)
        fd = rf.open_mappable("theirs.bin")
        try:
            assert os.fstat(fd).st_ino != theirs.stat().st_ino and os.fstat(fd).st_nlink == 0
            m = mmap.mmap(fd, 0, access=mmap.ACCESS_READ)
        finally:
            os.close(fd)
        os.truncate(theirs, 0)  # the guest cuts its file: the copy keeps every byte
        assert m[:] == b"0123456789" * 1000
        m.close()


def test_usage_counts_the_folder_not_what_links_point_to(tree: tuple[Path, Path]) -> None:
    run, outside = tree
    (outside / "logs" / "huge").write_bytes(b"x" * (4 << 20))
    (run / "to-outside").symlink_to(outside)
    (run / "own").write_bytes(b"x" * (1 << 20))
    used = runfolder.folder_bytes(run)
    assert (1 << 20) <= used < (2 << 20), used
    assert runfolder.folder_bytes(run / "missing") == 0
    (outside / "logs" / "huge").unlink()


@pytest.mark.parametrize(
    "raw, text",
    [
        (b"plain.bin", "plain.bin"),
        (b"bad\xff.bin", "bad\\xff.bin"),
        (b"back\\slash.bin", "back\\\\slash.bin"),
        (b"caf\xc3\xa9/log.xrf", "café/log.xrf"),
        (b"\\xff", "\\\\xff"),
    ],
)
def test_names_are_shown_escaped_and_taken_back_exactly(raw: bytes, text: str) -> None:
    name = os.fsdecode(raw)
    assert shown(name) == text
    text.encode("utf-8")  # any JSON or header holds it
    assert unshown(text) == name


@given(st.binary(min_size=1, max_size=40).filter(lambda b: b"\0" not in b))
def test_every_file_system_name_round_trips(raw: bytes) -> None:
    name = os.fsdecode(raw)
    text = shown(name)
    text.encode("utf-8")
    assert os.fsencode(unshown(text)) == raw


def test_a_name_that_is_not_utf8_is_opened_by_its_shown_form(resolver: str, tree: tuple[Path, Path]) -> None:
    run, _ = tree
    (run / os.fsdecode(b"bad\xff.bin")).write_bytes(b"log")
    with RunFolder(run) as rf:
        (rel,) = [r for r, _ in rf.walk_files()]
        assert shown(rel) == "bad\\xff.bin"
        assert rf.read_bytes(unshown("bad\\xff.bin"), 10) == b"log"


def test_a_planted_recording_is_read_within_bounds(tree: tuple[Path, Path]) -> None:
    """The 3D replay reads what the loop may have written in place of the recorder's files."""
    from xrflab.viz.recorder import load_recording, recording_size, write_recording

    run, outside = tree
    write_recording(run, {"profile": None}, [(i * 1_000_000, (i, 0, 0, 0)) for i in range(10)])
    assert recording_size(run) == 10 * 20 and len(load_recording(run)) == 10
    (run / "viz" / "meta.json").write_bytes(b"[" * 500_000)
    with pytest.raises(ValueError):
        load_recording(run)
    (run / "viz" / "meta.json").unlink()
    (run / "viz" / "meta.json").symlink_to(outside / "secret")
    assert recording_size(run) is None
    with pytest.raises(OSError):
        load_recording(run)


def test_decoding_a_file_the_guest_keeps_truncating_never_faults(tmp_path: Path) -> None:
    """The reader's whole path (open_mappable, open_log, the CSV stream) against a file cut to
    nothing and grown back every 0.5 ms, as the hostile controller does: a mapping of the file
    itself would fault (SIGBUS kills this test process, which is the failure)."""
    import threading

    from xrflab.logs import LogFormatError, iter_csv_chunks
    from xrflab.server.http.logs import open_run_log

    run = tmp_path / "run"
    run.mkdir()
    head, n = b"x,y\n5,5\n", 1 << 16
    (run / "big.bin").write_bytes(head + b"\0" * 16 * n)
    os.chmod(run / "big.bin", 0o660)  # the group (the guest) may write it
    stop = threading.Event()

    def cut_and_regrow() -> None:
        fd = os.open(run / "big.bin", os.O_RDWR)
        try:
            while not stop.is_set():
                os.ftruncate(fd, 0)
                os.pwrite(fd, head, 0)
                os.ftruncate(fd, len(head) + 16 * n)
                time.sleep(0.0005)  # the attacker's pace: cut and regrow as the reader decodes
        finally:
            os.close(fd)

    t = threading.Thread(target=cut_and_regrow)
    t.start()
    decoded = 0
    try:
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline:
            with RunFolder(run) as rf:
                try:
                    log = open_run_log(rf, "big.bin")
                except LogFormatError:  # caught with no header: not a log at that instant
                    continue
            decoded += sum(chunk.count(b"\n") for chunk in iter_csv_chunks(log.path, log=log)) > 0
    finally:
        stop.set()
        t.join()
    assert decoded > 0


def test_the_segment_name_in_the_runs_shm_folder_is_not_followed(tree: tuple[Path, Path]) -> None:
    """The run's /dev/shm folder is the guest's too: a link where its segment should be (to a
    file of the appliance's, big enough to map) is refused, never mapped read-write."""
    from xrflab.channels import ChannelsError
    from xrflab.channels.segment import SHM_SIZE, try_map

    run, outside = tree
    big = outside / "logs" / "big"
    big.write_bytes(b"\0" * SHM_SIZE)
    (run / "xrf").symlink_to(big)
    os.mkfifo(run / "fifo")
    for name in ("xrf", "fifo"):
        t0 = time.monotonic()
        with pytest.raises(ChannelsError, match="not the loop's shared memory object"):
            try_map(run / name)
        assert time.monotonic() - t0 < 1.0
    big.unlink()


def test_usage_counts_deep_trees_without_a_descriptor_leak(tree: tuple[Path, Path]) -> None:
    run, _ = tree
    _deep_chain(run, 200)  # below the disk guard's 256 levels: the deepest file is counted
    before = runfolder.folder_bytes(run)
    (run / ("dd/" * 200) / "f").write_bytes(os.urandom(1 << 20))
    grown = runfolder.folder_bytes(run) - before
    assert _fds_into(run.parent) == []
    assert (1 << 20) - 8192 <= grown <= (1 << 20) + 65536, grown
