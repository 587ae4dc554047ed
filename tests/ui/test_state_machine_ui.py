"""The dashboard's state machine is the one the appliance serves (GET /api/state-machine, read out
of rt_core's C command table), and the Bench page handles every WebSocket message kind of the
published schema (GET /api/ws-schema) (issue 20)."""

from __future__ import annotations

import json
from typing import Any

from xrf_testing.harness import Server


def drawn_edges(page: Any) -> list[tuple[str, str, bool]]:
    """(from, command or '' for a completion, enabled) of every edge drawn."""
    return [
        tuple(e)
        for e in page.eval_on_selector_all(
            "#state-machine .edge",
            "els => els.map(e => [e.dataset.from, e.dataset.cmd, e.classList.contains('enabled')])",
        )
    ]


def expected_edges(machine: dict[str, Any]) -> set[tuple[str, str]]:
    edges = {(t["from"], t["cmd"]) for t in machine["transitions"]}
    pairs = {(t["from"], t["to"]) for t in machine["transitions"]}
    # A completion along a command's edge is drawn as that edge (app.js edgesOf).
    edges |= {(c["from"], "") for c in machine["completions"] if (c["from"], c["to"]) not in pairs}
    return edges


def test_drawing_and_buttons_follow_the_served_machine(server: Server, browser) -> None:
    server.stop_run()
    machine = server.http.get("/api/state-machine").json()
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url + "/")
    page.wait_for_function("window.xrf && window.xrf.machine")
    assert page.evaluate("window.xrf.machine") == machine

    edges = drawn_edges(page)
    assert len(edges) == len(set((f, c) for f, c, _ in edges))  # each edge once
    assert {(f, c) for f, c, _ in edges} == expected_edges(machine)
    for s in machine["states"]:
        assert page.locator(f"#node-{s['name']}").count() == 1
    buttons = set(page.eval_on_selector_all("#commands button", "bs => bs.map(b => b.dataset.cmd)"))
    assert buttons == {c["name"] for c in machine["commands"]}
    assert not page.eval_on_selector_all("#commands button", "bs => bs.filter(b => !b.disabled).length")

    # Through a run: in every state reached, the enabled buttons and the highlighted edges are
    # exactly the served transitions out of that state.
    page.wait_for_selector("#build-select option[value=relbot]", state="attached")
    page.select_option("#build-select", "relbot")
    page.click("#btn-start-run")
    visited = []
    for cmd, reached in [
        (None, "IDLE"),
        ("initialise", "INITIALISED"),
        ("start", "RUN"),
        ("pause", "PAUSED"),
        ("stop", "STOPPED"),
        ("reset", "INITIALISED"),
        ("start", "RUN"),
    ]:
        if cmd is not None:
            page.click(f"#commands [data-cmd={cmd}]")
        page.wait_for_function(
            f"document.getElementById('state-name').textContent === {reached!r}",
            timeout=120_000 if cmd is None else 10_000,
        )
        page.wait_for_function(f"document.querySelector('#node-{reached}').classList.contains('current')")
        out = {t["cmd"] for t in machine["transitions"] if t["from"] == reached}
        enabled = set(
            page.eval_on_selector_all("#commands button", "bs => bs.filter(b => !b.disabled).map(b => b.dataset.cmd)")
        )
        assert enabled == out, (reached, enabled, out)
        lit = {(f, c) for f, c, on in drawn_edges(page) if on}
        assert lit == {(reached, c) for c in out}, (reached, lit)
        visited.append(reached)
    assert server.stop_run()["status"] == "ended"
    page.close()

    # The drawing has no table of its own: serve a different machine and the page draws that.
    other = json.loads(json.dumps(machine))
    other["transitions"] = [t for t in other["transitions"] if t["cmd"] != "pause"]
    other["states"].append({"number": 11, "name": "PARKED"})
    other["transitions"].append({"from": "STOPPED", "cmd": "park", "to": "PARKED"})
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    page.route(
        "**/api/state-machine",
        lambda route: route.fulfill(status=200, content_type="application/json", body=json.dumps(other)),
    )
    page.goto(server.url + "/")
    page.wait_for_function("window.xrf && window.xrf.machine")
    assert {(f, c) for f, c, _ in drawn_edges(page)} == expected_edges(other)
    assert page.locator("#node-PARKED").count() == 1
    assert not [e for e in drawn_edges(page) if e[1] == "pause"]
    page.close()
    assert not errors, errors


def test_every_message_kind_has_a_handler(server: Server, browser) -> None:
    schema = server.http.get("/api/ws-schema").json()
    page = browser.new_page()
    page.goto(server.url + "/")
    page.wait_for_function("window.xrf && window.xrf.handlers")
    handled = set(page.evaluate("Object.keys(window.xrf.handlers)"))
    assert handled == set(schema["kinds"]["server"])
    page.close()
