"""``xrf login``: get an API token for this user from an appliance and keep it for the CLI.

    xrf login --url http://192.168.1.20:8000            # asks for username and password
    echo "$PW" | xrf login --url ... --user ada --password-stdin
    xrf login --forget                                  # revoke the token and delete it

The token goes to ~/.config/xrf-lab/token (0600); later commands send it as
``Authorization: Bearer``. A new login replaces the user's previous token on the appliance.
"""

from __future__ import annotations

import argparse
import getpass
import os
import sys

HELP = "log in to an appliance and keep an API token for the CLI (~/.config/xrf-lab/token)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from ... import credentials

    p.add_argument(
        "--url", default=None, help=f"the appliance (default: the last one, $XRF_URL or {credentials.DEFAULT_URL})"
    )
    p.add_argument("--user", default=None, help="username (default: asked, suggesting $USER)")
    p.add_argument("--password-stdin", action="store_true", help="read the password from stdin (scripts)")
    p.add_argument("--forget", action="store_true", help="revoke the stored token on the appliance and delete it")


def run(args: argparse.Namespace) -> int:
    import httpx

    from ... import credentials

    url = (args.url or credentials.url()).rstrip("/")
    if args.forget:
        headers = credentials.auth_headers()
        if headers:
            try:
                httpx.delete(f"{url}/api/auth/token", headers=headers, timeout=30)
            except httpx.HTTPError as exc:
                print(f"warning: could not revoke the token on {url}: {exc}", file=sys.stderr)
        credentials.forget()
        print("forgot the stored token")
        return 0
    user = args.user or input(f"username [{os.environ.get('USER', '')}]: ").strip() or os.environ.get("USER", "")
    password = sys.stdin.readline().rstrip("\n") if args.password_stdin else getpass.getpass("password: ")
    try:
        r = httpx.post(f"{url}/api/auth/token", json={"username": user, "password": password}, timeout=60)
    except httpx.HTTPError as exc:
        print(f"error: cannot reach {url}: {exc}", file=sys.stderr)
        return 1
    if r.status_code != 200:
        try:
            detail = r.json().get("detail", r.text)
        except ValueError:
            detail = r.text
        print(f"error: login refused ({r.status_code}): {detail}", file=sys.stderr)
        return 1
    body = r.json()
    path = credentials.save(url, body["token"])
    print(f"logged in to {url} as {body['username']} ({body['role']}); token in {path}")
    return 0
