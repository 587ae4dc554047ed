"""``xrf param list|get|set``: the current run's tunable parameters through the appliance's API.

Through the appliance, not the segment: a set is checked there whole (name, number, range), only
the bench holder's token may set, and the change is logged with the run as every other set is.
Output: a table for people on stdout (``--json``: one JSON object), refusals on stderr with
exit 1.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

HELP = "list, read and set the running controller's tunable parameters (docs/students/tuning.md)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from .. import credentials

    p.add_argument("--url", default=credentials.url(), help="the appliance (default $XRF_URL or `xrf login`'s)")
    p.add_argument("--token", default=credentials.token(), help="API token (default $XRF_TOKEN or `xrf login`'s)")
    p.add_argument("--json", action="store_true", help="print the answer as JSON")
    sub = p.add_subparsers(dest="action", required=True)
    sub.add_parser("list", help="every parameter with its value, default, range and unit")
    g = sub.add_parser("get", help="one parameter")
    g.add_argument("name")
    s = sub.add_parser("set", help="NAME=VALUE ...: one atomic set, confirmed with the cycle it landed at")
    s.add_argument("assignments", nargs="+", metavar="NAME=VALUE")


def parse_assignments(items: list[str]) -> dict[str, Any]:
    """NAME=VALUE pairs; a value that is not a number is passed on as text, so the appliance
    refuses it with its own words (one rule for every client). The last `=` splits: 20-sim names
    hold no `=`."""
    values: dict[str, Any] = {}
    for item in items:
        name, sep, text = item.rpartition("=")
        if not sep or not name:
            raise ValueError(f"{item!r} is not NAME=VALUE")
        try:
            values[name] = float(text)
        except ValueError:
            values[name] = text
    return values


def _row(p: dict[str, Any]) -> str:
    rng = f"{p['min']:g} .. {p['max']:g}" + ("" if p["has_range"] else " (proposed)")
    return f"{p['name']:<32} {p['value']:>12g}  {p['unit']:<10} default {p['default']:g}, range {rng}"


def run(args: argparse.Namespace) -> int:
    import httpx

    headers = {"Authorization": f"Bearer {args.token}"} if args.token else {}
    try:
        with httpx.Client(base_url=args.url, headers=headers, timeout=30) as http:
            if args.action == "list":
                r = http.get("/api/params")
            elif args.action == "get":
                r = http.get("/api/params/" + args.name)
            else:
                try:
                    values = parse_assignments(args.assignments)
                except ValueError as exc:
                    print(f"xrf param set: {exc}", file=sys.stderr)
                    return 2
                r = http.post(
                    "/api/params", content=json.dumps({"values": values}), headers={"Content-Type": "application/json"}
                )
    except httpx.HTTPError as exc:
        print(f"xrf param: cannot reach the appliance at {args.url}: {exc}", file=sys.stderr)
        return 1
    try:
        body = r.json()
    except ValueError:
        body = {"detail": r.text}
    if r.status_code != 200:
        print(f"xrf param {args.action}: {body.get('detail', body)} (HTTP {r.status_code})", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(body))
    elif args.action == "list":
        if body.get("note"):
            print(body["note"], file=sys.stderr)
        for p in body["params"]:
            print(_row(p))
    elif args.action == "get":
        print(_row(body))
    else:
        for c in body["changes"]:
            print(f"{c['name']}: {c['old']:g} -> {c['new']:g}")
        print(f"applied at cycle {body['cycle']}")
    return 0
