"""Regenerate the pictures of docs/review.md from a simulated dataset (nothing is drawn by hand).

Simulates a small KITTI-format dataset with injected label errors, audits it with ``infer``, then
runs the real commands: ``labelaudit show`` on one object and on its frame, and ``labelaudit
report``, whose page is screenshot in headless Chromium (Playwright driving /usr/bin/chromium).
The simulator leaves out 15 % of the vehicle labels (their points kept), so the search of ``infer``
finds objects nobody labelled: ``show --candidate`` draws the likeliest and the report's section
is screenshot too. Writes docs/img/review-show.png, review-frame.png, review-report.png (the
gallery), review-plots.png, review-missing.png and review-missing-report.png.

    python scripts/make_review_figures.py [--frames 8] [--seed 5]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
IMG = REPO / "docs" / "img"
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


def cli(*args: str) -> str:
    proc = subprocess.run(
        [sys.executable, "-m", "labelaudit.cli", *map(str, args)], capture_output=True, text=True, cwd=REPO
    )
    if proc.returncode not in (0, 1):
        sys.exit(f"labelaudit {' '.join(map(str, args))} failed ({proc.returncode}):\n{proc.stderr}")
    return proc.stdout.strip()


def pick_object(results: Path) -> dict:
    """A likely wrong label with few points, so both the p_G blur and the suggested box show:
    label_error ≥ 0.5 and 8–120 points, the least certain of those (else the most likely wrong)."""
    from labelaudit.results import open_results

    rows = [r for r in open_results(results).read().to_pylist() if r["status"] == "ok" and r["label_error"] is not None]
    wrong = [r for r in rows if r["label_error"] >= 0.5 and 8 <= r["num_points"] <= 120]
    return min(wrong, key=lambda r: r["jiou_gt"]) if wrong else max(rows, key=lambda r: r["label_error"])


def pick_candidate(results: Path) -> dict:
    """The likeliest missing-label candidate with a few hundred points at most (its L-shape shows)."""
    from labelaudit.results import read_missing

    rows = read_missing(results).to_pylist()
    if not rows:
        sys.exit("the search found no candidate: no missing-label figure")
    near = [r for r in rows if 40 <= r["num_points"] <= 600] or rows
    return max(near, key=lambda r: (r["score"], r["num_points"]))


def screenshot(html: Path, anchor: str, out: Path) -> None:
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium") or "/usr/bin/chromium"
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=ARGS, headless=True)
        page = browser.new_page(viewport={"width": 1240, "height": 1080})
        page.goto(f"{html.as_uri()}#{anchor}", wait_until="load")
        page.evaluate("Promise.all(Array.from(document.images).map(i => i.decode()))")
        page.screenshot(path=str(out))
        browser.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--seed", type=int, default=5)
    args = ap.parse_args()
    IMG.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="review-figures-") as tmp:
        work = Path(tmp)
        data, results = work / "sim", work / "results"
        cli(
            "simulate",
            data,
            "--frames",
            args.frames,
            "--seed",
            args.seed,
            "--gross-fraction",
            "0.08",
            "--drop-fraction",
            "0.15",
            "--quiet",
        )
        cli("infer", data, "-o", results, "--workers", "2", "--quiet")
        row = pick_object(results)
        frame, index = row["frame_id"], row["object_index"]
        print(
            f"object: frame {frame} object {index} ({row['class_name']}, {row['num_points']} points, label_error {row['label_error']:.3f})"
        )
        cli("show", results, frame, index, "-o", IMG / "review-show.png")
        cli("show", results, frame, "--by", "label_error", "-o", IMG / "review-frame.png", "--size", "1000x640")
        html = Path(cli("report", results, "-o", work / "report.html", "--top", "6", "--gate", "default", "--quiet"))
        screenshot(html, "by-label_error", IMG / "review-report.png")
        screenshot(html, "plots", IMG / "review-plots.png")
        screenshot(html, "missing", IMG / "review-missing-report.png")
        cand = pick_candidate(results)
        print(
            f"candidate: frame {cand['frame_id']} candidate {cand['candidate_index']} ({cand['class_name']}, {cand['num_points']} points, score {cand['score']:.3f})"
        )
        cli("show", results, cand["frame_id"], "--candidate", cand["candidate_index"], "-o", IMG / "review-missing.png")
    for name in (
        "review-show.png",
        "review-frame.png",
        "review-report.png",
        "review-plots.png",
        "review-missing.png",
        "review-missing-report.png",
    ):
        print(f"wrote {IMG / name} ({(IMG / name).stat().st_size / 1e3:.0f} kB)")


if __name__ == "__main__":
    main()
