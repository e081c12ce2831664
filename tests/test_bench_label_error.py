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


@pytest.mark.slow
def test_bench_see_through_and_the_road_behind(tmp_path, capsys):
    """--see-through / --under-chassis simulate see-through vehicles and report the rays that passed;
    --ground-behind appends second returns on the road, each behind a vehicle on its own ray."""
    import numpy as np

    from labelaudit.datasets.kitti import read_velodyne
    from labelaudit.sim.dataset import SeeThrough, simulate_dataset

    bench = _load()
    md = tmp_path / "tables.md"
    args = ["--frames", "2", "--workers", "1", "--out", str(tmp_path / "w"), "--skip-real", "--markdown", str(md)]
    assert bench.main(args + ["--see-through", "0.5", "--under-chassis", "1", "--ground-behind", "0.5"]) == 0
    out = capsys.readouterr().out
    assert "rays through the windows and" in out and "second returns on the road" in out
    text = md.read_text()
    assert "see-through: glass 0.5, under the chassis 1.0" in text and "STRESS TEST" in text
    # the helper on its own: the added points lie on the road, farther than a vehicle on the same ray
    sim = tmp_path / "s"
    simulate_dataset(sim, frames=1, seed=4, progress=False)
    before = read_velodyne(sim / "training" / "velodyne" / "000000.bin")
    added = bench.add_ground_behind(sim, 1, 4, 1.0, SeeThrough())
    after = read_velodyne(sim / "training" / "velodyne" / "000000.bin")
    assert added > 500 and len(after) == len(before) + added
    new = after[len(before) :, :3].astype(float)
    assert np.all(np.abs(new[:, 2] + 1.73) < 0.1)  # the road (2 cm range noise)
    old = before[:, :3].astype(float)
    u_new = new / np.linalg.norm(new, axis=1, keepdims=True)
    u_old = old / np.linalg.norm(old, axis=1, keepdims=True)
    probe = u_new[:200]
    nearest = np.argmax(probe @ u_old.T, axis=1)  # the first return on the same ray …
    same = np.einsum("ij,ij->i", probe, u_old[nearest]) > np.cos(1e-3)
    assert same.mean() > 0.9  # … unless the sensor's dropout (2–12 %) lost it
    assert np.all(np.linalg.norm(old[nearest[same]], axis=1) < np.linalg.norm(new[:200][same], axis=1))
