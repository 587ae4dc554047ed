"""xrflab/projects/build_key.py's source hash: what decides whether a build is reused. Equal trees
hash equal wherever they are; any change of a file's content or name, or a file added, changes it."""

from __future__ import annotations

from pathlib import Path

from xrflab.projects.build_key import source_hash


def _tree(root: Path, files: dict[str, bytes]) -> Path:
    for rel, data in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    return root


BASE = {"CMakeLists.txt": b"project(x)\n", "src/main.cpp": b"int main(){}\n", "src/a.h": b"#pragma once\n"}


def test_same_tree_same_hash_wherever_and_in_whatever_order_written(tmp_path: Path) -> None:
    a = _tree(tmp_path / "a", BASE)
    b = _tree(tmp_path / "b", dict(reversed(list(BASE.items()))))
    assert source_hash(a) == source_hash(b)
    assert len(source_hash(a)) == 16


def test_every_kind_of_change_changes_it(tmp_path: Path) -> None:
    base = source_hash(_tree(tmp_path / "base", BASE))
    changed = {
        "content": {**BASE, "src/a.h": b"#pragma once \n"},
        "renamed": {**{k: v for k, v in BASE.items() if k != "src/a.h"}, "src/b.h": BASE["src/a.h"]},
        "moved": {**{k: v for k, v in BASE.items() if k != "src/a.h"}, "a.h": BASE["src/a.h"]},
        "added": {**BASE, "src/empty.txt": b""},
        # content shifted from one file to the next must not hash the same (names and ends are delimited)
        "shifted": {**BASE, "src/a.h": b"#pragma", "src/main.cpp": b" once\nint main(){}\n"},
    }
    hashes = {name: source_hash(_tree(tmp_path / name, files)) for name, files in changed.items()}
    assert base not in hashes.values(), hashes
    assert len(set(hashes.values())) == len(hashes)
