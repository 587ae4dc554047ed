"""``xrf new --template base|20sim DIR``: a new project folder from a template, to edit locally."""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

HELP = "start a new controller project from a template (base or 20sim)"
TEMPLATES_DIR = Path(__file__).resolve().parents[3] / "student_projects" / "templates"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--template", choices=("base", "20sim"), default="base")
    p.add_argument("dir", type=Path, help="the new project folder (must not exist, or be empty)")


def run(args: argparse.Namespace) -> int:
    src = TEMPLATES_DIR / args.template
    dest: Path = args.dir
    if not src.is_dir():
        print(f"error: template {args.template} not found at {src}", file=sys.stderr)
        return 1
    if dest.exists() and any(dest.iterdir()):
        print(f"error: {dest} exists and is not empty", file=sys.stderr)
        return 1
    if dest.exists():
        dest.rmdir()
    shutil.copytree(src, dest, ignore=shutil.ignore_patterns("build", ".git", "__pycache__"))
    print(f"{dest}: new project from the {args.template} template")
    print(f"  edit {dest}/src, {dest}/msg/*.msg; then `xrf build {dest}` here or `xrf upload {dest} --build`")
    return 0
