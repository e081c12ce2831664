"""``labelaudit simulate``: write a synthetic KITTI-layout dataset with injected label noise."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.markup import escape

from labelaudit import constants as C
from labelaudit.cli.app import app, err, handle_errors


@app.command()
def simulate(
    out: Path = typer.Argument(..., help="Folder to write the KITTI-format dataset to."),
    frames: int = typer.Option(20, "--frames", help="Number of frames."),
    seed: int = typer.Option(0, "--seed", help="Random seed (same seed, same dataset)."),
    noise_fraction: float = typer.Option(0.2, "--noise-fraction", help="Share of vehicle labels with Gaussian jitter."),
    noise_center_std: float = typer.Option(C.SIM_BENCH_NOISE[0], "--noise-center-std", help="Jitter std of the centre (m)."),
    noise_size_std: float = typer.Option(C.SIM_BENCH_NOISE[1], "--noise-size-std", help="Jitter std of length and width (m)."),
    noise_yaw_std: float = typer.Option(C.SIM_BENCH_NOISE[2], "--noise-yaw-std", help="Jitter std of the yaw (rad)."),
    gross_fraction: float = typer.Option(0.02, "--gross-fraction", help="Share of vehicle labels with a gross error (shifted 1 m, swapped l/w, turned 90°)."),
    workers: int = typer.Option(1, "--workers", help="Worker processes (same files for any count)."),
    detections: bool = typer.Option(False, "--detections", help="Also write a synthetic detector's output (OUT/detections/, KITTI result format) for `labelaudit eval`."),
    detections_cov: bool = typer.Option(False, "--detections-cov", help="With --detections: a probabilistic detector, per-detection std in OUT/detections.parquet."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a simulated dataset already in OUT."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """Write a synthetic LiDAR dataset in KITTI layout with known, injected label noise.

    manifest.parquet in OUT records every object's true box, written box and perturbation (docs/simulator.md). --detections adds a synthetic detector (localisation noise growing with distance, misses, false positives, scores that follow quality; docs/eval.md).

    [bold]Examples[/bold]

      labelaudit simulate sim/ --frames 100 --seed 1

      labelaudit simulate sim/ --noise-fraction 0.3 --noise-center-std 0.2 --gross-fraction 0.05

      labelaudit simulate sim/ --frames 50 --detections && labelaudit eval sim/ sim/detections
    """
    from labelaudit.sim.dataset import simulate_dataset
    from labelaudit.sim.noise import NoiseSpec

    with handle_errors(debug):
        if frames < 1:
            raise typer.BadParameter(f"must be ≥ 1, got {frames}", param_hint="--frames")
        if workers < 1:
            raise typer.BadParameter(f"must be ≥ 1, got {workers}", param_hint="--workers")
        if detections_cov and not detections:
            raise typer.BadParameter("needs --detections", param_hint="--detections-cov")
        try:
            spec = NoiseSpec(fraction=noise_fraction, center_std=noise_center_std, size_std=noise_size_std, yaw_std=noise_yaw_std, gross_fraction=gross_fraction)
        except ValueError as exc:
            raise typer.BadParameter(str(exc), param_hint="--noise-*/--gross-fraction") from None
        simulate_dataset(out, frames=frames, seed=seed, noise=spec, progress=not quiet, workers=workers, overwrite=overwrite)
        err().print(f"wrote {frames} frames to {escape(str(out))} (next: labelaudit infer {escape(str(out))})", soft_wrap=True)
        if detections:
            from labelaudit.sim.detector import DetectorSpec, simulate_detections

            det = simulate_detections(out, DetectorSpec(probabilistic=detections_cov), seed=seed)
            extra = f" and {det.parquet}" if det.parquet else ""
            err().print(
                f"wrote {det.detections} synthetic detections to {escape(str(det.folder))}{escape(extra)} "
                f"(next: labelaudit eval {escape(str(out))} {escape(str(det.parquet or det.folder))})", soft_wrap=True,
            )
