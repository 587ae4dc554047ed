"""Checking an uploaded project archive, then unpacking it safely.

Nothing in an archive is trusted: not its names, not its entry types, not the sizes its headers
declare. The check is a full streaming pass over the archive that writes nothing (it reads and
counts every byte of every entry, so a header that lies about a size is caught by the count);
only an archive that passes it is unpacked, into a fresh folder, with every file opened
``O_CREAT | O_EXCL | O_NOFOLLOW`` relative to a directory descriptor, and the same limits
counted again while writing.

Accepted: zip, tar, tar.gz (gzip members may be concatenated). Refused, naming the entry:
absolute paths, ``..``, links of any kind (symbolic or hard: a project needs none), device
files, FIFOs, sockets, names that are not UTF-8, duplicate names, too many files, a file or a
total over the size limits, and compression ratios that only a zip bomb has: per entry, and for
the whole archive (many small entries, each harmless alone, add up to a bomb too).

What makes it a project is decided after unpacking, by build.locate_project bounded to the
unpacked folder (the same rules as `xrf build`): a project with CMakeLists.txt and msg/, an XRF2
controller package with its XRF2 framework folder or xrf2_msgs package, a whole ROS 2 workspace.
An archive that is not one is refused naming what is missing and where it looked, and the
unpacked folder is removed again. What an upload may hold is said once, in ``rules()``: the
Projects page shows it before an upload (GET /api/project-upload-rules), the refusals say it after.
"""

from __future__ import annotations

import gzip
import io
import os
import stat
import tarfile
import zipfile
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, BinaryIO

from ..errors import Invalid

CHUNK = 1 << 16
# Folders a project never needs from the student's machine; skipped when unpacking (still counted).
SKIPPED_DIRS = {"build", "install", "log", ".git", "__pycache__", ".vscode", ".idea"}


# File names the upload form offers (what detect_format reads is the content, not the name).
SUFFIXES = (".zip", ".tar.gz", ".tgz", ".tar")
# The layouts _check_project accepts (build.locate_project's rules), as a student reads them.
LAYOUTS = (
    "an XRF Lab project folder: CMakeLists.txt, src/, msg/Ros2Xeno.msg and msg/Xeno2Ros.msg "
    "(what the templates and `xrf new` make)",
    "an XRF2 controller package together with the XRF2 framework folder its CMakeLists.txt names "
    "(../XRF2, ../ros2-xenomai4-framework) or its xrf2_msgs package, which hold the messages",
    "a whole ROS 2 (colcon) workspace, src/ with XRF2 and exactly one XRF2 controller package "
    "(other ROS 2 nodes may be there): that package is built, and the project is named after it",
)


@dataclass(frozen=True)
class Limits:
    max_upload: int = 64 << 20  # bytes of the archive itself
    max_total: int = 256 << 20  # bytes of all files, uncompressed
    max_files: int = 5000  # entries (files and folders)
    max_file: int = 64 << 20  # bytes of one file, uncompressed
    max_ratio: float = 200.0  # uncompressed / compressed, for anything over ratio_floor
    ratio_floor: int = 4 << 20  # smaller than this, any ratio is fine (a file of spaces)
    max_name: int = 255  # bytes of one path component
    max_path: int = 1024  # bytes of a whole path
    max_depth: int = 32


class ArchiveRejected(Invalid):
    """The archive is refused (422). ``entry`` names the offending entry ('' for the archive
    itself), ``message`` the reason alone; str() is both. Its answer (server/http/errors.py) is the
    typed ``detail`` the dashboard shows: ``{"error": "archive refused: <entry>: <reason>", "entry",
    "message"}``. A route that names the path itself (the editor's) answers its own words."""

    def __init__(self, message: str, entry: str = "") -> None:
        text = f"{entry}: {message}" if entry else message
        super().__init__(text, detail={"error": "archive refused: " + text, "entry": entry, "message": message})
        self.message = message  # the reason alone, as callers quote it (XrfError's is the whole text)
        self.entry = entry


@dataclass
class Entry:
    name: str  # normalised relative POSIX path, top-level folder stripped later
    kind: str  # file | dir
    size: int = 0


@dataclass
class Manifest:
    format: str
    files: list[str] = field(default_factory=list)
    dirs: list[str] = field(default_factory=list)
    total: int = 0
    prefix: str = ""  # the single top-level folder stripped from every name, if any
    skipped: list[str] = field(default_factory=list)
    # A workspace upload: the controller package chosen in it, relative to the unpacked folder
    # ("src/my_controller"), and its name (package.xml's, else the folder's). '' when the archive
    # is the project itself.
    package: str = ""
    package_name: str = ""


def rules(limits: Limits) -> dict[str, Any]:
    """What an upload may be and hold, from the definitions the check uses (the Projects page
    shows it before an upload; nothing is copied into the page)."""
    return {
        "formats": list(SUFFIXES),
        "layouts": list(LAYOUTS),
        "max_upload": limits.max_upload,
        "max_total": limits.max_total,
        "max_file": limits.max_file,
        "max_files": limits.max_files,
        "left_out": sorted(d + "/" for d in SKIPPED_DIRS),
    }


def _mb(n: float) -> str:
    return f"{n / (1 << 20):.1f} MB" if n < (1 << 30) else f"{n / (1 << 30):.1f} GB"


# ---- names --------------------------------------------------------------------------------------


def check_name(raw: str | bytes, limits: Limits, is_dir: bool = False) -> str:
    """A safe relative POSIX path from an archive name, or ArchiveRejected naming it."""
    if isinstance(raw, bytes):
        try:
            name = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise ArchiveRejected(
                "the name is not valid UTF-8; rename the file (plain letters, digits, - _ .)",
                raw.decode("utf-8", "replace"),
            ) from None
    else:
        name = raw
        try:
            name.encode("utf-8")
        except UnicodeEncodeError:  # surrogateescape'd bytes from a tar header
            shown = name.encode("utf-8", "surrogateescape").decode("utf-8", "replace")
            raise ArchiveRejected(
                "the name is not valid UTF-8; rename the file (plain letters, digits, - _ .)", shown
            ) from None
    shown = name
    if "\x00" in name or any(ord(c) < 32 or ord(c) == 127 for c in name):
        raise ArchiveRejected("the name contains control characters", repr(shown))
    if name.startswith("/") or name.startswith("\\") or (len(name) > 1 and name[1] == ":"):
        raise ArchiveRejected(
            "absolute paths are not accepted: pack the project folder's contents with relative names", shown
        )
    if "\\" in name:
        raise ArchiveRejected("backslashes are not accepted in names", shown)
    parts = [p for p in name.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise ArchiveRejected("names with '..' (leading out of the project folder) are not accepted", shown)
    if not parts:
        raise ArchiveRejected("an empty name", shown)
    if len(name.encode()) > limits.max_path:
        raise ArchiveRejected(f"the path is longer than {limits.max_path} bytes", shown[:80] + "…")
    if any(len(p.encode()) > limits.max_name for p in parts):
        raise ArchiveRejected(f"a name is longer than {limits.max_name} bytes", shown[:80] + "…")
    if len(parts) > limits.max_depth:
        raise ArchiveRejected(f"folders nested deeper than {limits.max_depth} levels", shown)
    return "/".join(parts)


# ---- reading archives as a stream of (entry, data chunks) ---------------------------------------


class _CountingReader(io.RawIOBase):
    """Counts the compressed bytes consumed, for the ratio check, and caps the archive's size."""

    def __init__(self, f: BinaryIO, limit: int) -> None:
        self.f = f
        self.count = 0
        self.limit = limit

    def readable(self) -> bool:
        return True

    def readinto(self, b: Any) -> int:
        n = self.f.readinto(b)  # type: ignore[attr-defined]  # every file object the uploads give has it
        self.count += n or 0
        if self.count > self.limit:
            raise ArchiveRejected(f"the archive is larger than {_mb(self.limit)}")
        return n or 0


def detect_format(path: Path) -> str:
    with open(path, "rb") as f:
        head = f.read(512)
    if head[:2] == b"\x1f\x8b":
        return "tar.gz"
    if head[:4] in (b"PK\x03\x04", b"PK\x05\x06"):
        return "zip"
    if len(head) >= 262 and head[257:262] == b"ustar":
        return "tar"
    raise ArchiveRejected("not a zip, tar or tar.gz archive (pack the folder with `xrf upload`, or as .zip / .tar.gz)")


Chunks = Iterator[bytes]


def _tar_entries(
    path: Path, limits: Limits, fmt: str, ratio: Callable[[], tuple[int, int]] | None = None
) -> Iterator[tuple[Entry, Chunks | None]]:
    raw_file = open(path, "rb")
    counting = _CountingReader(raw_file, limits.max_upload)
    buffered = io.BufferedReader(counting, CHUNK)
    stream: BinaryIO = gzip.GzipFile(fileobj=buffered, mode="rb") if fmt == "tar.gz" else buffered  # type: ignore[assignment]
    try:
        try:
            tf = tarfile.open(fileobj=stream, mode="r|", encoding="utf-8", errors="surrogateescape")
        except (tarfile.TarError, OSError, EOFError, zlib.error) as exc:
            raise ArchiveRejected(f"the archive cannot be read ({exc})") from None
        with tf:
            members = iter(tf)
            while True:
                try:
                    m = next(members)
                except StopIteration:
                    return
                except (tarfile.TarError, OSError, EOFError, zlib.error) as exc:
                    raise ArchiveRejected(f"the archive is damaged or truncated ({exc})") from None
                shown = m.name.encode("utf-8", "surrogateescape").decode("utf-8", "replace")
                if m.issym() or m.islnk():
                    raise ArchiveRejected(
                        f"links are not accepted (this one points to {m.linkname!r}); "
                        "put the file itself in the project",
                        shown,
                    )
                if m.ischr() or m.isblk():
                    raise ArchiveRejected("device files are not accepted", shown)
                if m.isfifo():
                    raise ArchiveRejected("FIFOs (named pipes) are not accepted", shown)
                if not (m.isreg() or m.isdir()):
                    raise ArchiveRejected(f"entries of type {m.type!r} are not accepted; only files and folders", shown)
                name = check_name(m.name, limits, m.isdir())
                if m.isdir():
                    yield Entry(name, "dir"), None
                    continue
                if m.size > limits.max_file:
                    raise ArchiveRejected(
                        f"the file is {_mb(m.size)}; one file may be at most {_mb(limits.max_file)}", shown
                    )
                fobj = tf.extractfile(m)
                assert fobj is not None

                def chunks(fobj=fobj, shown=shown) -> Chunks:
                    while True:
                        try:
                            b = fobj.read(CHUNK)
                        except (tarfile.TarError, OSError, EOFError, zlib.error) as exc:
                            raise ArchiveRejected(f"the archive is damaged or truncated ({exc})", shown) from None
                        if not b:
                            return
                        yield b
                        if counting.count and fmt == "tar.gz":
                            _ratio_check(stream_pos(), counting.count, limits, shown)

                def stream_pos() -> int:
                    return getattr(stream, "tell", lambda: 0)()

                yield Entry(name, "file", m.size), chunks()
    finally:
        raw_file.close()


def _ratio_check(out: int, inp: int, limits: Limits, shown: str) -> None:
    if out > limits.ratio_floor and inp and out / inp > limits.max_ratio:
        raise ArchiveRejected(
            f"decompresses more than {limits.max_ratio:.0f} times its size "
            f"({_mb(out)} from {_mb(inp)}): a zip bomb is refused",
            shown,
        )


def _total_ratio_check(total: int, archive_size: int, limits: Limits, shown: str) -> None:
    """The whole archive's ratio: many entries each small enough to pass on its own (under
    ``ratio_floor``) still add up to a bomb."""
    if total > limits.ratio_floor and total / max(archive_size, 1) > limits.max_ratio:
        raise ArchiveRejected(
            f"the archive decompresses more than {limits.max_ratio:.0f} times its size "
            f"({_mb(total)} from {_mb(archive_size)}): a zip bomb is refused",
            shown,
        )


def _zip_entries(path: Path, limits: Limits) -> Iterator[tuple[Entry, Chunks | None]]:
    archive_size = path.stat().st_size
    if archive_size > limits.max_upload:
        raise ArchiveRejected(f"the archive is larger than {_mb(limits.max_upload)}")
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise ArchiveRejected(f"the zip file cannot be read ({exc})") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > limits.max_files:
            raise ArchiveRejected(
                f"the archive has {len(infos)} entries; at most {limits.max_files} files and folders are accepted",
                infos[limits.max_files].filename,
            )
        declared = 0
        for info in infos:
            raw = info.filename
            if not info.flag_bits & 0x800:
                # Without the UTF-8 flag zipfile decoded the name as cp437: get the bytes back.
                try:
                    rawb = raw.encode("cp437")
                except UnicodeEncodeError:
                    rawb = raw.encode("utf-8", "replace")
                name_src: str | bytes = rawb
            else:
                name_src = raw
            mode = info.external_attr >> 16
            shown = raw
            if mode and stat.S_ISLNK(mode):
                raise ArchiveRejected("links are not accepted; put the file itself in the project", shown)
            if mode and (stat.S_ISCHR(mode) or stat.S_ISBLK(mode)):
                raise ArchiveRejected("device files are not accepted", shown)
            if mode and stat.S_ISFIFO(mode):
                raise ArchiveRejected("FIFOs (named pipes) are not accepted", shown)
            if mode and stat.S_ISSOCK(mode):
                raise ArchiveRejected("sockets are not accepted", shown)
            is_dir = info.is_dir()
            name = check_name(name_src, limits, is_dir)
            if is_dir:
                yield Entry(name, "dir"), None
                continue
            if info.file_size > limits.max_file:
                raise ArchiveRejected(
                    f"the file is {_mb(info.file_size)}; one file may be at most {_mb(limits.max_file)}", shown
                )
            declared += info.file_size
            if declared > limits.max_total:
                raise ArchiveRejected(f"the files add up to more than {_mb(limits.max_total)}", shown)
            _total_ratio_check(declared, archive_size, limits, shown)  # from the headers, before reading
            _ratio_check(info.file_size, max(info.compress_size, 1), limits, shown)
            if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
                raise ArchiveRejected("only stored or deflated zip entries are accepted", shown)

            def chunks(info=info, shown=shown) -> Chunks:
                produced = 0
                try:
                    with zf.open(info) as f:
                        while True:
                            b = f.read(CHUNK)
                            if not b:
                                return
                            produced += len(b)
                            if produced > info.file_size:
                                raise ArchiveRejected("the entry holds more data than its header says", shown)
                            yield b
                except (zipfile.BadZipFile, OSError, EOFError, zlib.error, NotImplementedError) as exc:
                    raise ArchiveRejected(f"the entry is damaged ({exc})", shown) from None

            yield Entry(name, "file", info.file_size), chunks()


def entries(path: Path, limits: Limits) -> tuple[str, Iterator[tuple[Entry, Chunks | None]]]:
    size = path.stat().st_size
    if size > limits.max_upload:
        raise ArchiveRejected(f"the archive is {_mb(size)}; at most {_mb(limits.max_upload)} is accepted")
    fmt = detect_format(path)
    it = _zip_entries(path, limits) if fmt == "zip" else _tar_entries(path, limits, fmt)
    return fmt, it


# ---- the check ----------------------------------------------------------------------------------


def _walk_checked(path: Path, limits: Limits, sink: Callable[[Entry, Chunks | None], None]) -> Manifest:
    archive_size = path.stat().st_size
    fmt, it = entries(path, limits)
    seen: dict[str, str] = {}
    count = 0
    total = 0
    manifest = Manifest(fmt)
    for entry, chunks in it:
        count += 1
        if count > limits.max_files:
            raise ArchiveRejected(
                f"more than {limits.max_files} files and folders; a project needs far "
                "fewer (did a build folder or a dataset get packed?)",
                entry.name,
            )
        prev = seen.get(entry.name)
        if prev is not None and not (prev == "dir" and entry.kind == "dir"):
            raise ArchiveRejected("the name appears twice in the archive", entry.name)
        # A file may not sit where a folder is, or under a file.
        parents = PurePosixPath(entry.name).parents
        for parent in list(parents)[:-1]:
            if seen.get(str(parent)) == "file":
                raise ArchiveRejected(f"{parent} is a file and a folder at once", entry.name)
            seen.setdefault(str(parent), "dir")
        seen[entry.name] = entry.kind
        if entry.kind == "dir":
            manifest.dirs.append(entry.name)
            sink(entry, None)
            continue
        actual = 0

        def counted(chunks=chunks, entry=entry) -> Chunks:
            nonlocal actual, total
            assert chunks is not None
            for b in chunks:
                actual += len(b)
                total += len(b)
                if actual > limits.max_file:
                    raise ArchiveRejected(f"the file is larger than {_mb(limits.max_file)}", entry.name)
                if total > limits.max_total:
                    raise ArchiveRejected(f"the files add up to more than {_mb(limits.max_total)}", entry.name)
                # Counted, not declared: holds for every format and for headers that lie.
                _total_ratio_check(total, archive_size, limits, entry.name)
                yield b

        sink(entry, counted())
        manifest.files.append(entry.name)
    manifest.total = total
    return manifest


def _strip_prefix(names: list[str]) -> str:
    """The one top-level folder to strip (a zipped 'my_project/' folder), or ''."""
    tops = {n.split("/", 1)[0] for n in names}
    if len(tops) == 1 and "CMakeLists.txt" not in names:
        top = next(iter(tops))
        if any(n.startswith(top + "/") for n in names):
            return top
    return ""


def _relative(name: str, prefix: str) -> str:
    return name[len(prefix) + 1 :] if prefix and name.startswith(prefix + "/") else ("" if name == prefix else name)


def check_stream(path: Path | str, limits: Limits = Limits()) -> Manifest:
    """Read the whole archive without writing anything; raise ArchiveRejected or return what it
    holds. Whether it is a complete project is not known yet (see check)."""
    path = Path(path)

    def drain(_entry: Entry, chunks: Chunks | None) -> None:
        if chunks is not None:
            for _ in chunks:
                pass

    manifest = _walk_checked(path, limits, drain)
    manifest.prefix = _strip_prefix(manifest.files + manifest.dirs)
    return manifest


def check(path: Path | str, limits: Limits = Limits()) -> Manifest:
    """What unpack() would accept, for an archive that is kept rather than unpacked (a room's
    assignment): the streaming check, then an unpack into a private temporary folder for the
    project check, removed again."""
    import tempfile

    path = Path(path)
    with tempfile.TemporaryDirectory(prefix=".check-", dir=path.parent) as tmp:
        return unpack(path, Path(tmp) / "src", limits)


def _check_project(dest: Path, manifest: Manifest) -> None:
    """The unpacked folder builds a controller and has its messages (build.locate_project, within
    the folder), or ArchiveRejected with its reason and the top level's names. A workspace's
    chosen controller package is noted in the manifest (the project is named after it: the
    archive's top folder of a workspace is "src" or "ws" for everyone)."""
    from .. import build
    from .source import package_of

    try:
        located = build.locate_project(dest, within=dest)
        manifest.package, manifest.package_name = package_of(located)
    except build.BuildError as exc:
        files = {_relative(n, manifest.prefix) for n in manifest.files}
        has = sorted({n.split("/", 1)[0] + ("/" if "/" in n else "") for n in files if n})[:12]
        missing = next((w for w in ("CMakeLists.txt", "msg/Ros2Xeno.msg", "Ros2Xeno.msg") if w in exc.message), "")
        raise ArchiveRejected(
            "this is not a complete project: "
            + exc.message.rstrip(".")
            + (". Top level has: " + ", ".join(has) if has else ". The archive holds no files"),
            missing,
        ) from None


# ---- unpacking ----------------------------------------------------------------------------------

_DIR_FLAGS = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
_FILE_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)


def _open_dir(root_fd: int, parts: list[str]) -> int:
    """fd of root/parts..., creating folders; never follows a link (O_NOFOLLOW at every step)."""
    fd = os.dup(root_fd)
    try:
        for p in parts:
            try:
                os.mkdir(p, 0o755, dir_fd=fd)
            except FileExistsError:
                pass
            nfd = os.open(p, _DIR_FLAGS, dir_fd=fd)
            os.close(fd)
            fd = nfd
        return fd
    except BaseException:
        os.close(fd)
        raise


def unpack(path: Path | str, dest: Path | str, limits: Limits = Limits()) -> Manifest:
    """Check, then unpack into ``dest`` (which must not exist yet; its parent must). On any
    failure ``dest`` is removed again, so nothing is left behind."""
    path, dest = Path(path), Path(dest)
    manifest = check_stream(path, limits)
    os.mkdir(dest, 0o755)
    root_fd = os.open(dest, _DIR_FLAGS)
    prefix = manifest.prefix
    skipped: list[str] = []

    def write(entry: Entry, chunks: Chunks | None) -> None:
        rel = _relative(entry.name, prefix)
        if not rel:
            if chunks is not None:
                for _ in chunks:
                    pass
            return
        parts = rel.split("/")
        if parts[0] in SKIPPED_DIRS:
            if chunks is not None:
                for _ in chunks:
                    pass
            if parts[0] + "/" not in skipped:
                skipped.append(parts[0] + "/")
            return
        if entry.kind == "dir":
            os.close(_open_dir(root_fd, parts))
            return
        dfd = _open_dir(root_fd, parts[:-1])
        try:
            fd = os.open(parts[-1], _FILE_FLAGS, 0o644, dir_fd=dfd)
        finally:
            os.close(dfd)
        with os.fdopen(fd, "wb") as out:
            assert chunks is not None
            for b in chunks:
                out.write(b)

    try:
        result = _walk_checked(path, limits, write)
        result.prefix = prefix
        _check_project(dest, result)
    except BaseException:
        os.close(root_fd)
        import shutil

        shutil.rmtree(dest, ignore_errors=True)
        raise
    os.close(root_fd)
    result.prefix = prefix
    result.skipped = skipped
    return result
