"""Hostile archives, made in memory or streamed: nothing here writes gigabytes.

- the 10 GB bombs are 10 MB at most: gzip members / deflate blocks of zeros repeated (a full
  flush makes each 1 MB block of zeros compress to the same bytes, so one is computed and
  repeated);
- the 2 GB file is a tar header that declares 2 GB followed by a few blocks (the checker must
  refuse it from the header, before reading);
- the 100 000 files are tar headers generated in a loop into a gzip stream.
"""

from __future__ import annotations

import gzip
import io
import struct
import tarfile
import time
import zipfile
import zlib
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
BASE = REPO / "student_projects/templates/base"
TWENTY = REPO / "student_projects/templates/20sim"
MB = 1 << 20


def project_files(root: Path = BASE) -> dict[str, bytes]:
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and "build" not in p.relative_to(root).parts
    }


def tar_gz(files: dict[str, bytes], extra: list[tarfile.TarInfo] | None = None, fmt: int = tarfile.GNU_FORMAT) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz", format=fmt, encoding="utf-8", errors="surrogateescape") as t:
        for name, data in files.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            info.mtime = int(time.time())
            t.addfile(info, io.BytesIO(data))
        for info in extra or []:
            t.addfile(info)
    return buf.getvalue()


def zip_bytes(files: dict[str, bytes], raw_infos: list[tuple[zipfile.ZipInfo, bytes]] | None = None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in files.items():
            z.writestr(name, data)
        for info, data in raw_infos or []:
            z.writestr(info, data)
    return buf.getvalue()


def with_entry(info: tarfile.TarInfo) -> bytes:
    return tar_gz(project_files(), [info])


def traversal_tar() -> bytes:
    return tar_gz({**project_files(), "../../etc/x": b"pwned\n"})


def traversal_zip() -> bytes:
    return zip_bytes({**project_files(), "src/../../../etc/x": b"pwned\n"})


def absolute_tar() -> bytes:
    return tar_gz({**project_files(), "/etc/x": b"pwned\n"})


def absolute_zip() -> bytes:
    return zip_bytes({**project_files(), "/tmp/x": b"pwned\n"})


def symlink_tar(target: str = "/") -> bytes:
    info = tarfile.TarInfo("src/root")
    info.type = tarfile.SYMTYPE
    info.linkname = target
    return with_entry(info)


def hardlink_tar() -> bytes:
    info = tarfile.TarInfo("src/passwd")
    info.type = tarfile.LNKTYPE
    info.linkname = "/etc/passwd"
    return with_entry(info)


def symlink_zip() -> bytes:
    info = zipfile.ZipInfo("src/root")
    info.external_attr = 0o120777 << 16
    return zip_bytes(project_files(), [(info, b"/")])


def device_tar() -> bytes:
    info = tarfile.TarInfo("src/null")
    info.type = tarfile.CHRTYPE
    info.devmajor, info.devminor = 1, 3
    return with_entry(info)


def fifo_tar() -> bytes:
    info = tarfile.TarInfo("src/pipe")
    info.type = tarfile.FIFOTYPE
    return with_entry(info)


def non_utf8_tar() -> bytes:
    name = b"src/caf\xe9.cpp".decode("utf-8", "surrogateescape")
    return tar_gz({**project_files(), name: b"int x;\n"})


def non_utf8_zip() -> bytes:
    buf = io.BytesIO(zip_bytes(project_files()))
    with zipfile.ZipFile(buf, "a") as z:
        info = zipfile.ZipInfo("src/x.cpp")
        z.writestr(info, b"int x;\n")
    data = buf.getvalue()
    # Patch the name bytes in place (same length) in the local header and the central directory.
    return data.replace(b"src/x.cpp", b"src/\xff.cpp")


def no_cmakelists() -> bytes:
    files = project_files()
    del files["CMakeLists.txt"]
    return tar_gz(files)


def no_msg() -> bytes:
    return tar_gz({k: v for k, v in project_files().items() if not k.startswith("msg/")})


def _tar_header(name: str, size: int) -> bytes:
    info = tarfile.TarInfo(name)
    info.size = size
    info.mtime = 0
    return info.tobuf(format=tarfile.GNU_FORMAT)


def two_gb_file() -> bytes:
    """A tar.gz whose third entry declares 2 GB; only 64 KB of data follow (never 2 GB)."""
    out = io.BytesIO()
    with gzip.GzipFile(fileobj=out, mode="wb", compresslevel=1) as gz:
        for name, data in project_files().items():
            gz.write(_tar_header(name, len(data)) + data + b"\0" * (-len(data) % 512))
        gz.write(_tar_header("data/recording.bin", 2 * 1024 * MB))
        gz.write(b"\0" * 65536)
    return out.getvalue()


def many_files(n: int = 100_000) -> bytes:
    out = io.BytesIO()
    with gzip.GzipFile(fileobj=out, mode="wb", compresslevel=1) as gz:
        for name, data in project_files().items():
            gz.write(_tar_header(name, len(data)) + data + b"\0" * (-len(data) % 512))
        block = b"x" + b"\0" * 511
        for i in range(n):
            gz.write(_tar_header(f"many/f{i:06d}", 1) + block)
        gz.write(b"\0" * 1024)
    return out.getvalue()


def tar_gz_bomb(total_gb: int = 10, file_mb: int = 32) -> bytes:
    """tar.gz of honest headers, ``total_gb`` GB of zeros in ``file_mb`` MB files: concatenated gzip
    members, the zeros' member computed once. About 10 MB for 10 GB."""
    zeros = gzip.compress(b"\0" * (file_mb * MB), compresslevel=9)
    out = io.BytesIO()
    out.write(
        gzip.compress(
            b"".join(_tar_header(n, len(d)) + d + b"\0" * (-len(d) % 512) for n, d in project_files().items())
        )
    )
    for i in range(total_gb * 1024 // file_mb):
        out.write(gzip.compress(_tar_header(f"data/zeros{i:04d}.bin", file_mb * MB)))
        out.write(zeros)
    out.write(gzip.compress(b"\0" * 1024))
    return out.getvalue()


def tar_gz_one_big_declared(gb: int = 10) -> bytes:
    """One entry declaring 10 GB, followed by a gzip stream of zeros that stops early."""
    out = io.BytesIO()
    with gzip.GzipFile(fileobj=out, mode="wb") as gz:
        for name, data in project_files().items():
            gz.write(_tar_header(name, len(data)) + data + b"\0" * (-len(data) % 512))
        gz.write(_tar_header("data/huge.bin", gb * 1024 * MB))
        gz.write(b"\0" * MB)
    return out.getvalue()


def _deflate_zeros(total: int) -> bytes:
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    block = c.compress(b"\0" * MB) + c.flush(zlib.Z_FULL_FLUSH)
    again = c.compress(b"\0" * MB) + c.flush(zlib.Z_FULL_FLUSH)
    # After a full flush, identical input gives identical output: repeat it instead of compressing.
    assert again == block or len(again) == len(block)
    return block + again * (total // MB - 2) + c.flush()


def _zip_raw(name: str, comp: bytes, declared_size: int, crc: int = 0) -> bytes:
    """A one-entry deflated zip with a header of our choosing (declared size, CRC)."""
    n = name.encode()
    local = struct.pack("<4sHHHHHIIIHH", b"PK\x03\x04", 20, 0, 8, 0, 0, crc, len(comp), declared_size, len(n), 0) + n
    central = (
        struct.pack(
            "<4sHHHHHHIIIHHHHHII",
            b"PK\x01\x02",
            20,
            20,
            0,
            8,
            0,
            0,
            crc,
            len(comp),
            declared_size,
            len(n),
            0,
            0,
            0,
            0,
            0,
            0,
        )
        + n
    )
    end = struct.pack("<4sHHHHIIH", b"PK\x05\x06", 0, 0, 1, 1, len(central), len(local) + len(comp), 0)
    return local + comp + central + end


def _zip_with_project(extra: bytes) -> bytes:
    """The project's files as a normal zip, with ``extra`` (a one-entry raw zip) appended as entry."""
    base = zip_bytes(project_files())
    # Simplest robust way: build the bomb zip standalone; projects files are not needed for the
    # checker to refuse the bomb (it refuses at the entry, before the completeness check).
    del base
    return extra


def zip_bomb_declared(gb: int = 10) -> bytes:
    """Honest header: 10 GB declared, ~10 MB of deflate data."""
    comp = _deflate_zeros(gb * 1024 * MB)
    return _zip_with_project(_zip_raw("data/zeros.bin", comp, min(gb * 1024 * MB, 0xFFFFFFFF)))


def zip_bomb_lying(gb: int = 10) -> bytes:
    """Lying header: 1 KB declared, but the deflate stream inflates to 10 GB."""
    comp = _deflate_zeros(gb * 1024 * MB)
    return _zip_with_project(_zip_raw("data/zeros.bin", comp, 1024))


def zip_many_small_bombs(entries: int = 60, entry_mb: int = 3) -> bytes:
    """A complete project plus ``entries`` files of ``entry_mb`` MB of zeros each: every entry is
    under the per-entry ratio floor (4 MB), the total (180 MB) under the size limit (256 MB), but
    the whole archive (~0.2 MB) decompresses ~1000 times its size."""
    zeros = b"\0" * (entry_mb * MB)
    return zip_bytes({**project_files(), **{f"data/part{i:03d}.bin": zeros for i in range(entries)}})
