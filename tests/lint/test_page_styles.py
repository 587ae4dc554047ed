"""Every page's stylesheet is linked in index.html's head, and no page script adds one: a page
laid out before its rules arrived is measured wrong (CI: the Watch scope was sized before
watch.css laid out its grid, 1782 px in a 1280 px window)."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HREF = re.compile(r'<link rel="stylesheet" href="/static/(pages/[\w.-]+\.css)">')
# A page script making a <link> to one of the pages' stylesheets, whichever way it is written.
ADDED = re.compile(r"/static/pages/[\w.-]+\.css")


def page_style_faults(frontend: Path) -> list[str]:
    html = (frontend / "index.html").read_text()
    head = html[: html.index("</head>")]
    linked = set(HREF.findall(head))
    faults = [
        f"{css.relative_to(frontend)} is not linked in index.html's head"
        for css in sorted((frontend / "pages").glob("*.css"))
        if str(css.relative_to(frontend)) not in linked
    ]
    faults += [f"index.html links {h} outside its head" for h in HREF.findall(html[len(head) :])]
    faults += [
        f"{js.relative_to(frontend)} adds a page stylesheet itself"
        for js in sorted((frontend / "pages").glob("*.js"))
        if ADDED.search(js.read_text())
    ]
    return faults


def test_every_page_stylesheet_is_in_the_head() -> None:
    assert page_style_faults(ROOT / "frontend") == []


def test_a_stylesheet_left_out_or_added_late_is_found(tmp_path: Path) -> None:
    front = tmp_path / "frontend"
    shutil.copytree(ROOT / "frontend", front, ignore=shutil.ignore_patterns("vendor"))
    (front / "pages/late.css").write_text(".late { color: red; }\n")
    page = front / "pages/watch.js"
    page.write_text(page.read_text() + '\nconst l = "/static/pages/watch.css";\n')
    assert page_style_faults(front) == [
        "pages/late.css is not linked in index.html's head",
        "pages/watch.js adds a page stylesheet itself",
    ]
