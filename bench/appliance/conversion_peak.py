"""Peak RSS of a download's conversion child (logs/convert_child.py) per format and log length.

    .venv/bin/python bench/appliance/conversion_peak.py [--rows 20000,600000] [--formats csv,mat,parquet,rrd]

A synthetic log (8 doubles a record, 88-byte records, one segment) of each length is converted by
the child's own ``main`` as the appliance runs it (its environment: ``_child_env``), and the
child's VmHWM is printed: its peak RSS, not getrusage's ru_maxrss, which a process started by fork
and exec inherits from its parent. Run it from each checkout to compare (issue 30 item 4).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))

from xrf_testing.writers import xrflog_segment  # noqa: E402
from xrflab.logs.convert_child import _child_env  # noqa: E402

CHILD = (
    "import sys; from xrflab.logs.convert_child import main; rc = main(sys.argv[1:]); sys.stdout.flush(); "
    "print([l for l in open('/proc/self/status') if l.startswith('VmHWM')][0].split()[1], file=sys.stderr); "
    "sys.exit(rc)"
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", default="20000,600000")
    ap.add_argument("--formats", default="csv,mat,parquet,rrd")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="xrf-conv-peak-") as tmp:
        print(f"# load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}")
        print("| records | log MB | format | child peak RSS MB | seconds |")
        print("|---|---|---|---|---|")
        for rows in (int(r) for r in a.rows.split(",")):
            log = Path(tmp) / f"{rows}.xrflog"
            log.write_bytes(
                xrflog_segment(
                    [(f"g{i % 3}_v{i}", 5) for i in range(8)], [[r * 0.5 + i for i in range(8)] for r in range(rows)]
                )
            )
            for fmt in a.formats.split(","):
                fd = os.open(log, os.O_RDONLY)
                target = "-" if fmt == "csv" else str(Path(tmp) / f"out.{fmt}")
                t0 = time.monotonic()
                proc = subprocess.run(
                    [sys.executable, "-c", CHILD, str(fd), fmt, target, log.name],
                    input=b"[]",
                    pass_fds=(fd,),
                    capture_output=True,
                    env=_child_env(),
                    check=False,
                )
                os.close(fd)
                err = proc.stderr.decode(errors="replace").strip().splitlines()
                peak = f"{int(err[-1]) / 1024:.1f}" if proc.returncode == 0 else f"failed: {err[-1:]}"
                print(f"| {rows} | {log.stat().st_size / 1e6:.1f} | {fmt} | {peak} | {time.monotonic() - t0:.1f} |")


if __name__ == "__main__":
    main()
