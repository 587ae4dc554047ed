"""The System page in a real browser (issue 10): the `xrf doctor` checks with their status and
fix, and the appliance's facts."""

from __future__ import annotations

from xrf_testing.harness import Server

DOCTOR_IDS = ["evl", "isolcpus", "governor", "throttling", "spi", "fpga", "clock", "disk", "ros2", "confinement"]


def test_system_page_lists_the_doctor_checks(server: Server, browser) -> None:
    page = browser.new_page()
    page.goto(server.url + "/#system")
    page.wait_for_selector("#sys-checks tr[data-id=confinement]", timeout=30000)
    rows = page.locator("#sys-checks tr[data-id]").evaluate_all("rs => rs.map(r => [r.dataset.id, r.dataset.status])")
    assert [i for i, _ in rows] == DOCTOR_IDS
    assert all(s in ("ok", "warning", "failure", "not checked") for _, s in rows)
    # anything not ok shows its fix
    for cid, status in rows:
        if status in ("warning", "failure"):
            row = page.locator(f"#sys-checks tr[data-id={cid}]")
            fix = page.evaluate(
                "id => fetch('/api/system/doctor').then(r => r.json()).then(d => d.checks.find(c => c.id === id).fix)",
                cid,
            )
            if fix:
                assert "fix:" in row.inner_text()
            break
    facts = page.inner_text("#sys-facts")
    assert "XRF Lab" in facts and str(server.data_dir) in facts and "sim" in page.inner_text("[data-fact=transport]")
    page.click("#sys-refresh")
    page.wait_for_function("!document.querySelector('#sys-refresh').disabled")
    assert page.locator("#sys-checks tr[data-id]").count() == len(DOCTOR_IDS)
    page.close()
