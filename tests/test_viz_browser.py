"""The report in a real headless Chromium (Debian's `chromium`, driven by Playwright).

`bash scripts/dev.sh test` installs Chromium when it is missing, so CI runs this for real; it
skips only when no browser is installed (and says so).
"""

from __future__ import annotations

import io
import os
import shutil

import matplotlib.image as mpimg
import numpy as np
import pytest

from labelaudit.viz.report import build_report
from viz_data import make_eval_dir, simulate_with_a_dropped_label

CHROMIUM = os.environ.get("LABELAUDIT_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
TOP = 3

pytestmark = pytest.mark.skipif(
    CHROMIUM is None,
    reason="no Chromium browser installed (Debian package `chromium`; `bash scripts/dev.sh test` installs it with apt-get)",
)


MISSING = 2  # missing-label candidates pictured (the nearest car of frame 000001 lost its label; one weaker candidate)


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    root = tmp_path_factory.mktemp("viz_browser")
    _, results, _ = simulate_with_a_dropped_label(root)
    out = root / "report.html"
    summary = build_report(results, out, gate="default", top=TOP, eval_dir=make_eval_dir(root / "eval"))
    return out, summary


@pytest.fixture(scope="module")
def browser():
    playwright = pytest.importorskip(
        "playwright.sync_api", reason="Playwright (test dependency, `pip install -e .[test]`) is not installed"
    )
    with playwright.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        yield b
        b.close()


def test_report_renders_in_chromium(report, browser, tmp_path):
    out, summary = report
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    problems, requests = [], []
    page.on(
        "console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type in ("error", "warning") else None
    )
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.on("requestfailed", lambda r: problems.append(f"request failed: {r.url}"))
    page.on("request", lambda r: requests.append(r.url))
    page.goto(out.as_uri(), wait_until="load")

    widths = page.evaluate("Promise.all(Array.from(document.images).map(i => i.decode().then(() => i.naturalWidth)))")
    assert len(widths) == 5 + 2 * TOP + MISSING + 2  # plots, both galleries, the missing labels, the eval PNGs
    assert all(w > 0 for w in widths), widths
    for key in ("label_error", "jiou_gt"):
        assert page.locator(f"section[data-gallery={key}] article.entry").count() == TOP
        assert page.locator(f"section[data-gallery={key}] article.entry img").count() == TOP
    # Nothing but the file itself and its data: URIs is requested: no network.
    assert all(u.startswith(("file:", "data:")) for u in requests), requests

    # A pasted anchor lands on its object.
    anchor = page.locator("section[data-gallery=label_error] article.entry").first.get_attribute("data-object")
    page.goto(f"{out.as_uri()}#{anchor}", wait_until="load")
    assert page.evaluate("document.querySelector(':target').dataset.object") == anchor

    shot = page.screenshot(full_page=False)
    (tmp_path / "shot.png").write_bytes(shot)
    img = mpimg.imread(io.BytesIO(shot), format="png")[..., :3]
    assert img.shape[:2] == (900, 1280)
    assert img.std() > 0.05 and len(np.unique((img * 255).astype(np.uint8).reshape(-1, 3), axis=0)) > 200  # not blank
    assert problems == []
    page.close()


def test_missing_labels_section_renders_in_chromium(report, browser, tmp_path):
    out, summary = report
    assert summary.missing_pictures == MISSING
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    problems = []
    page.on(
        "console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type in ("error", "warning") else None
    )
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.goto(f"{out.as_uri()}#missing-000001-0", wait_until="load")
    assert page.evaluate("document.querySelector(':target').dataset.candidate") == "missing-000001-0"
    section = page.locator("section#missing")
    assert section.locator("article.candidate").count() == MISSING
    widths = page.evaluate(
        "Promise.all(Array.from(document.querySelectorAll('section#missing img')).map(i => i.decode().then(() => i.naturalWidth)))"
    )
    assert widths == [520] * MISSING
    assert section.locator("table#missing-counts").inner_text().count("Car") == 1
    box = section.locator("article.candidate img").first.bounding_box()
    assert box is not None and box["width"] > 300 and box["y"] < 900  # the target's picture is on screen
    shot = page.screenshot(full_page=False)
    (tmp_path / "missing.png").write_bytes(shot)
    img = mpimg.imread(io.BytesIO(shot), format="png")[..., :3]
    magenta = np.abs(img - np.array([1.0, 0x3D / 255, 0xF5 / 255])).max(axis=-1) < 0.1
    assert magenta.sum() > 100  # a candidate's outline is on the screen
    assert problems == []
    page.close()
