"""Each hostile archive is refused with a message naming the entry, and nothing is written
anywhere (the checker reads the whole archive before unpacking; unpack() removes its own folder
on a late failure)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from xrf_testing import hostile
from xrflab.projects import archive
from xrflab.projects.archive import ArchiveRejected

REPO = Path(__file__).resolve().parents[2]


CASES = {
    # name: (maker, expected entry (substring), expected words in the message)
    "traversal_tar": (hostile.traversal_tar, "../../etc/x", "'..'"),
    "traversal_zip": (hostile.traversal_zip, "src/../../../etc/x", "'..'"),
    "absolute_tar": (hostile.absolute_tar, "/etc/x", "absolute"),
    "absolute_zip": (hostile.absolute_zip, "/tmp/x", "absolute"),
    "symlink_to_root_tar": (hostile.symlink_tar, "src/root", "links are not accepted"),
    "symlink_zip": (hostile.symlink_zip, "src/root", "links are not accepted"),
    "hardlink_tar": (hostile.hardlink_tar, "src/passwd", "links are not accepted"),
    "device_node_tar": (hostile.device_tar, "src/null", "device files"),
    "fifo_tar": (hostile.fifo_tar, "src/pipe", "FIFO"),
    "non_utf8_tar": (hostile.non_utf8_tar, "src/caf", "UTF-8"),
    "non_utf8_zip": (hostile.non_utf8_zip, "src/", "UTF-8"),
    "no_cmakelists": (hostile.no_cmakelists, "CMakeLists.txt", "missing CMakeLists.txt"),
    "no_msg": (hostile.no_msg, "msg/Ros2Xeno.msg", "msg/Xeno2Ros.msg"),
    "two_gb_file": (hostile.two_gb_file, "data/recording.bin", "2.0 GB"),
    "hundred_thousand_files": (hostile.many_files, "many/f", "more than 5000"),
    "tar_gz_bomb_10GB": (hostile.tar_gz_bomb, "data/zeros", "zip bomb"),
    "tar_gz_declared_10GB": (hostile.tar_gz_one_big_declared, "data/huge.bin", "10.0 GB"),
    "zip_bomb_declared_10GB": (hostile.zip_bomb_declared, "data/zeros.bin", ""),
    "zip_bomb_lying_header": (hostile.zip_bomb_lying, "data/zeros.bin", ""),
    # each entry alone passes the per-entry ratio check; the archive as a whole is a bomb
    "zip_many_small_entries_bomb": (
        hostile.zip_many_small_bombs,
        "data/part",
        "the archive decompresses more than 200 times",
    ),
}


def _tree(path: Path) -> set[str]:
    return {str(p.relative_to(path)) for p in path.rglob("*")}


@pytest.mark.parametrize("case", sorted(CASES))
def test_hostile_archive_refused(case: str, tmp_path: Path) -> None:
    maker, entry, words = CASES[case]
    data = maker()
    assert len(data) < 16 << 20, f"{case}: the test archive itself should be small ({len(data)} bytes)"
    upload = tmp_path / "upload.bin"
    upload.write_bytes(data)
    root = tmp_path / "projects"
    root.mkdir()
    before = _tree(tmp_path)
    t0 = time.monotonic()
    with pytest.raises(ArchiveRejected) as info:
        archive.unpack(upload, root / "p1" / "src" if False else root / "src")
    elapsed = time.monotonic() - t0
    exc = info.value
    assert entry in exc.entry or entry in exc.message, (case, exc.entry, exc.message)
    assert words in exc.message, (case, exc.message)
    assert _tree(tmp_path) == before, f"{case}: something was written"
    assert not Path("/etc/x").exists()
    assert elapsed < 20, f"{case}: took {elapsed:.1f} s"
    print(f"{case}: {len(data)} bytes, refused in {elapsed * 1000:.0f} ms: {exc}")


def test_template_accepted_folder_stripped(tmp_path: Path) -> None:
    import io
    import tarfile  # noqa: E401

    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        t.add(hostile.BASE, arcname="my_project")
    up = tmp_path / "p.tgz"
    up.write_bytes(buf.getvalue())
    m = archive.unpack(up, tmp_path / "src")
    assert m.prefix == "my_project"
    assert (tmp_path / "src" / "CMakeLists.txt").is_file()
    assert (tmp_path / "src" / "msg" / "Ros2Xeno.msg").is_file()
    for p in (tmp_path / "src").rglob("*"):
        assert not p.is_symlink()


def test_zip_20sim_accepted(tmp_path: Path) -> None:
    up = tmp_path / "p.zip"
    up.write_bytes(hostile.zip_bytes(hostile.project_files(hostile.TWENTY)))
    m = archive.unpack(up, tmp_path / "src")
    assert "controller/LoopController_tokens.xml" in m.files


def test_duplicate_name_refused(tmp_path: Path) -> None:
    import io  # noqa: E401
    import tarfile

    files = hostile.project_files()
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        for name, data in list(files.items()) + [("CMakeLists.txt", b"# again\n")]:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            t.addfile(info, io.BytesIO(data))
    up = tmp_path / "p.tgz"
    up.write_bytes(buf.getvalue())
    with pytest.raises(ArchiveRejected, match="appears twice"):
        archive.unpack(up, tmp_path / "src")
    assert not (tmp_path / "src").exists()


def test_unpack_never_follows_a_planted_link(tmp_path: Path) -> None:
    """Even if a link appeared in the destination (it cannot come from an archive), O_NOFOLLOW
    refuses to write through it."""
    dest = tmp_path / "src"
    up = tmp_path / "p.tgz"
    up.write_bytes(hostile.tar_gz(hostile.project_files()))
    os.mkdir(dest)
    os.symlink("/etc", dest / "msg")
    fd = os.open(dest, os.O_RDONLY | os.O_DIRECTORY)
    try:
        with pytest.raises(OSError):
            archive._open_dir(fd, ["msg"])
    finally:
        os.close(fd)


def test_xrf_upload_of_an_xrf2_controller_packs_its_xrf2_messages(tmp_path: Path) -> None:
    """`xrf upload ws/src/ctrl` when the messages are in ../XRF2 (the folder its CMakeLists.txt
    names): the message folder is packed beside the controller, and the appliance's check finds
    the same files (issue 17). Without them the controller alone is refused, saying the XRF2
    folder is not in the upload."""
    import shutil

    from xrflab import build, projects_cli

    ws = tmp_path / "ws"
    ctrl = ws / "src" / "ctrl"
    shutil.copytree(REPO / "tests/fixtures/xrf2_v1_1_project", ctrl)
    msgs = ws / "src/XRF2/XenoRosFramework/Common/XRF2_msgs/msg"
    msgs.parent.mkdir(parents=True)
    shutil.move(str(ctrl / "msg"), str(msgs))
    (ws / "src/XRF2/XenoRosFramework/Common/XRF2_msgs/package.xml").write_text(
        "<package><name>xrf2_msgs</name></package>"
    )

    data, warnings = projects_cli.pack(ctrl)
    assert any("packed ../XRF2/XenoRosFramework/Common/XRF2_msgs/msg too" in w for w in warnings), warnings
    up = tmp_path / "p.tgz"
    up.write_bytes(data)
    archive.unpack(up, tmp_path / "src")
    found = build.locate_project(tmp_path / "src", within=tmp_path / "src")
    assert found.project == (tmp_path / "src/ctrl").resolve()
    assert found.msg_dir == (tmp_path / "src/XRF2/XenoRosFramework/Common/XRF2_msgs/msg").resolve()
    assert (found.msg_dir / "Ros2Xeno.msg").read_bytes() == (msgs / "Ros2Xeno.msg").read_bytes()

    alone = tmp_path / "alone.tgz"
    alone.write_bytes(
        hostile.tar_gz({str(p.relative_to(ctrl)): p.read_bytes() for p in ctrl.rglob("*") if p.is_file()})
    )
    with pytest.raises(ArchiveRejected) as info:
        archive.unpack(alone, tmp_path / "src2")
    assert (
        "Looked in: msg;" in info.value.message
        and "../XRF2/XenoRosFramework, which is not in the upload" in info.value.message
    ), info.value.message
    assert not (tmp_path / "src2").exists()
