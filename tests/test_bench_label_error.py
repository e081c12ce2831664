"""The label-error benchmark script runs end to end on a tiny simulated dataset (numbers: docs/label-error.md)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "bench_label_error.py"


def _load():
    spec = importlib.util.spec_from_file_location("bench_label_error", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
def test_bench_runs_on_a_tiny_dataset(tmp_path, capsys):
    bench = _load()
    md = tmp_path / "tables.md"
    assert (
        bench.main(
            [
                "--frames",
                "3",
                "--workers",
                "1",
                "--out",
                str(tmp_path / "work"),
                "--realdata",
                str(tmp_path / "absent"),
                "--markdown",
                str(md),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "Synthetic, benchmark definition" in out and "AUROC label_error" in out
    assert "label_error AUROC on ≥ 10 points" in out
    assert "real data:" in out and "skipped" in out  # the real-data part skips cleanly
    text = md.read_text()
    assert text.count("| all |") >= 2  # headline and extra view
