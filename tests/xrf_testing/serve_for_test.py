"""Run the appliance on uvicorn with Settings given as JSON (argv[1]); used by the test fixtures
to get a real server in its own process (its own event loop, child watcher and signals)."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

if os.environ.get("XRF_TRACEMALLOC"):  # a benchmark looking for growth: snapshots on SIGUSR2
    from memtrace import install  # this script's own folder (tests/xrf_testing) is on sys.path

    install(Path(os.environ["XRF_TRACEMALLOC"]))

if os.environ.get("XRF_IMPORT_LOG"):  # a test asking which packages the appliance imports: their top-level
    # names, appended to that file as each is first imported (a finder that finds nothing: the
    # import goes on as without it)
    class _ImportLog:
        def __init__(self, path: str) -> None:
            self.path = path

        def find_spec(self, name: str, path: object = None, target: object = None) -> None:
            if "." not in name:
                with open(self.path, "a") as f:
                    f.write(name + "\n")

    sys.meta_path.insert(0, _ImportLog(os.environ["XRF_IMPORT_LOG"]))  # type: ignore[arg-type]

from xrflab.server.app import create_app  # noqa: E402
from xrflab.server.cli.serve import serve  # noqa: E402
from xrflab.server.settings import Settings  # noqa: E402

PATH_FIELDS = {"data_dir", "frontend_dir", "projects_dir", "builds_root"}


def main() -> None:
    raw = json.loads(sys.argv[1])
    values = {k: Path(v) if k in PATH_FIELDS and v is not None else v for k, v in raw.items()}
    settings = Settings(**values)
    serve(create_app(settings), settings)


if __name__ == "__main__":
    main()
