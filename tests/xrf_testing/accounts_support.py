"""Helpers of the accounts tests (tests/server/accounts): an account per role, logged in."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import httpx

from xrf_testing.harness import Server, WsClient


@dataclass
class Account:
    username: str
    password: str
    role: str
    http: httpx.Client
    ws: Callable[..., WsClient]
    id: int


def make_account(server: Server, username: str, role: str) -> Account:
    password = server.create_user(username, role)
    http, ws = server.login(username, password)
    return Account(username, password, role, http, ws, http.get("/api/me").json()["id"])
