"""The plant list the API and the dashboard use is rt_core's plant table: GET /api/plants (behind
the login) gives its rows, and the Bench page's plant menu offers exactly those, in table order.
The page has no list of its own, so a plant added to the C table appears here with no edit."""

from __future__ import annotations

import httpx

from xrf_testing.harness import Server
from xrflab import plants


def test_api_lists_the_plant_table_behind_the_login(server: Server) -> None:
    anon = httpx.Client(base_url=server.url, timeout=10)
    try:
        assert anon.get("/api/plants").status_code == 401
    finally:
        anon.close()
    server.create_user("plantwatcher", role="observer", password="plantwatcher-pw-1")
    http, _ = server.login("plantwatcher", "plantwatcher-pw-1")
    try:
        r = http.get("/api/plants")
    finally:
        http.close()
    assert r.status_code == 200, r.text
    assert r.json() == [p.as_dict() for p in plants.plants()]
    assert [p["name"] for p in r.json()][:2] == ["relbot", "jiwy"]


def test_bench_plant_menu_is_the_table(server: Server, browser) -> None:  # noqa: ANN001
    page = browser.new_page()
    try:
        page.goto(server.url + "/")
        names = list(plants.names())
        page.wait_for_function(f"document.querySelectorAll('#sim-select option').length === {len(names) + 1}")
        options = page.eval_on_selector_all("#sim-select option", "os => os.map(o => [o.value, o.title])")
        assert options[0][0] == ""  # "plant: default": the build's own plant
        assert [v for v, _ in options[1:]] == names
        assert [t for _, t in options[1:]] == [p.title for p in plants.plants()]
    finally:
        page.context.close()
