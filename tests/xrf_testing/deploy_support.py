"""A throwaway Debian root for the installer tests.

A Debian 12 tree made with ``debootstrap --variant=minbase`` (plus python3, python3-venv,
cmake, g++, make and systemd - what the Pi's Ubuntu has), cached outside the repository in
``$XRF_DEBOOTSTRAP_CACHE`` (default ``~/.cache/xrf-lab/debootstrap-bookworm-<key>``) and
created on demand (about 1.5 min with a nearby mirror). Each test module copies it (cp -a,
a few seconds) and ``deploy/install --root`` enters the copy with chroot.

The mirror is the first ``deb.debian.org``-style URI in this machine's apt sources (what apt
uses here), else ``http://deb.debian.org/debian``. The copy gets this machine's CA bundle and
resolv.conf so pip inside the chroot reaches PyPI the way pip outside does (the package itself
is installed with ``--no-deps``; pip still fetches setuptools/wheel for its build).
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SUITE = "bookworm"
PACKAGES = ["python3", "python3-venv", "cmake", "g++", "make", "ca-certificates", "systemd"]


def apt_mirror() -> str:
    sources = []
    for p in [Path("/etc/apt/sources.list"), *sorted(Path("/etc/apt/sources.list.d").glob("*"))]:
        try:
            sources.append(p.read_text(errors="replace"))
        except OSError:
            pass
    text = "\n".join(sources)
    for m in re.finditer(r"(?:^URIs:\s*|^deb\s+(?:\[[^\]]*\]\s+)?)(\S+)", text, re.MULTILINE):
        uri = m.group(1).rstrip("/")
        if uri.endswith("/debian") and "security" not in uri:
            return uri
    return "http://deb.debian.org/debian"


def _cache_dir(packages: list[str]) -> Path:
    key = hashlib.sha256(" ".join([SUITE, *packages]).encode()).hexdigest()[:8]
    env = os.environ.get("XRF_DEBOOTSTRAP_CACHE")
    if env:  # the installer's tree there as before; any other list of packages beside it
        return Path(env) if packages == PACKAGES else Path(f"{env}-{key}")
    return Path.home() / ".cache" / "xrf-lab" / f"debootstrap-{SUITE}-{key}"


def ensure_debian_tree(packages: list[str] = PACKAGES) -> Path:
    """The cached tree of minbase plus ``packages`` (one cache folder per list)."""
    cache = _cache_dir(packages)
    if (cache / ".xrf-complete").exists():
        return cache
    if shutil.which("debootstrap") is None:
        subprocess.run(
            ["apt-get", "install", "-y", "-q", "debootstrap"],
            check=True,
            env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"},
            stdout=subprocess.DEVNULL,
        )
    tmp = cache.with_name(cache.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.parent.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run(
        ["debootstrap", "--variant=minbase", f"--include={','.join(packages)}", SUITE, str(tmp), apt_mirror()],
        capture_output=True,
        text=True,
        timeout=900,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"debootstrap failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    (tmp / ".xrf-complete").write_text(SUITE + "\n")
    shutil.rmtree(cache, ignore_errors=True)
    tmp.rename(cache)
    return cache


def fresh_root(dest: Path) -> Path:
    """A copy of the cached tree at ``dest`` with this machine's network trust settings."""
    src = ensure_debian_tree()
    subprocess.run(["cp", "-a", str(src), str(dest)], check=True)
    for f in ("etc/resolv.conf", "etc/ssl/certs/ca-certificates.crt"):
        host = Path("/") / f
        if host.exists():
            target = dest / f
            if target.is_symlink() or target.exists():
                target.unlink()
            shutil.copyfile(host, target)
    return dest


def source_snapshot(dest: Path) -> Path:
    """A frozen copy of the checkout's files (tracked and untracked, not ignored): others may
    edit the checkout while the tests run, and the idempotency test needs a source that
    does not change between the two runs. The copy has no .git, so the installer's
    non-git file listing is what runs."""
    files = subprocess.run(
        ["git", "-C", str(REPO), "ls-files", "-co", "--exclude-standard"], capture_output=True, text=True, check=True
    ).stdout.splitlines()
    dest.mkdir(parents=True)
    for f in files:
        src = REPO / f
        if src.is_file() and not src.is_symlink():
            (dest / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / f)
    return dest


def run_install(root: Path, *args: str, script: str = "install", source: Path = REPO) -> subprocess.CompletedProcess:
    # The host's PIP_* settings point at paths that do not exist inside the chroot.
    env = {k: v for k, v in os.environ.items() if not k.startswith("PIP_")}
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    proc = subprocess.run(
        [str(source / "deploy" / script), "--root", str(root), *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=900,
    )
    return proc


def tree_digest(root: Path, skip: tuple[str, ...] = ("proc", "sys", "dev", "run", "tmp")) -> dict[str, str]:
    """path -> 'type mode uid:gid content-hash|link-target' for every entry under root."""
    out: dict[str, str] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        rel_dir = os.path.relpath(dirpath, root)
        if rel_dir == ".":
            dirnames[:] = [d for d in dirnames if d not in skip]
        for name in dirnames + filenames:
            p = os.path.join(dirpath, name)
            st = os.lstat(p)
            rel = os.path.relpath(p, root)
            meta = f"{oct(st.st_mode)} {st.st_uid}:{st.st_gid}"
            if os.path.islink(p):
                out[rel] = f"link {meta} {os.readlink(p)}"
            elif os.path.isdir(p):
                out[rel] = f"dir {meta}"
            elif os.path.isfile(p):
                h = hashlib.sha256()
                with open(p, "rb") as f:
                    for chunk in iter(lambda: f.read(1 << 20), b""):
                        h.update(chunk)
                out[rel] = f"file {meta} {h.hexdigest()}"
            else:
                out[rel] = f"other {meta} {st.st_rdev}"
    return out
