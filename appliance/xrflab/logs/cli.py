"""`xrf decode FILE [--to csv|mat|parquet|rrd] [-o OUT]`: convert a log file (xrflog or XRF2 .bin).

Registered in xrflab.cli's EXTERNAL_SUBCOMMANDS; heavy imports stay inside run(). What the
reader skipped (truncated record, damaged regions) and the lost-record count go to stderr, so
`-o -` (CSV to stdout) stays clean for pipes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HELP = "decode a log file (xrflog or XRF2 .bin) to CSV, MAT, Parquet or rerun .rrd"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", type=Path, help="the log file")
    p.add_argument("--to", choices=["csv", "mat", "parquet", "rrd"], default="csv", help="output format (default csv)")
    p.add_argument("-o", "--output", help="output path (default: FILE with the format's suffix; '-' = CSV to stdout)")
    p.add_argument("--info", action="store_true", help="print what the file holds (JSON) and convert nothing")


def run(args: argparse.Namespace) -> int:
    from .convert import convert, iter_csv_chunks
    from .reader import LogFormatError, open_log

    try:
        log = open_log(args.file)
    except (OSError, LogFormatError) as exc:
        print(f"xrf decode: {exc}", file=sys.stderr)
        return 1
    if args.info:
        print(json.dumps(log.summary(), indent=1))
        return 0
    for note in log.skipped:
        print(f"xrf decode: {args.file}: skipped: {note}", file=sys.stderr)
    if log.lost:
        print(f"xrf decode: {args.file}: {log.lost} records lost (gaps in seq)", file=sys.stderr)
    try:
        if args.output == "-":
            if args.to != "csv":
                print("xrf decode: only CSV can go to stdout", file=sys.stderr)
                return 2
            for chunk in iter_csv_chunks(args.file, log=log):
                sys.stdout.buffer.write(chunk)
            sys.stdout.buffer.flush()
            return 0
        out = convert(args.file, args.to, args.output, log=log)
    except BrokenPipeError:  # `xrf decode F -o - | head`
        sys.stderr.close()
        return 0
    except (OSError, LogFormatError, ValueError) as exc:
        print(f"xrf decode: {exc}", file=sys.stderr)
        return 1
    print(out)
    print(f"xrf decode: {len(log)} records in {len(log.segments)} segment(s) -> {out}", file=sys.stderr)
    return 0
