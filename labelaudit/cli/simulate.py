"""``labelaudit simulate``: write a synthetic dataset (KITTI, Waymo v1/v2, Argoverse 2) with injected label noise."""

from __future__ import annotations

from enum import Enum
from pathlib import Path

import typer
from rich.markup import escape

from labelaudit import constants as C
from labelaudit.cli.app import app, err, handle_errors


class SimFormat(str, Enum):
    kitti = "kitti"
    waymo_v2 = "waymo-v2"
    waymo_v1 = "waymo-v1"
    av2 = "av2"


class SensorSize(str, Enum):
    real = "real"
    small = "small"


@app.command()
def simulate(
    out: Path = typer.Argument(..., help="Folder to write the dataset to."),
    dataset_format: SimFormat = typer.Option(
        SimFormat.kitti,
        "--dataset-format",
        help="kitti (single frames), or sequences with track ids and a moving ego vehicle: waymo-v2, waymo-v1, av2.",
    ),
    frames: int = typer.Option(20, "--frames", help="Number of frames (per sequence for waymo-v2, waymo-v1, av2)."),
    sequences: int = typer.Option(2, "--sequences", help="waymo-v2, waymo-v1, av2: number of segments / logs."),
    size: SensorSize = typer.Option(
        SensorSize.real,
        "--size",
        help="waymo-v2, waymo-v1, av2: the sensors' real resolution, or small (fewer rays, quick).",
    ),
    seed: int = typer.Option(0, "--seed", help="Random seed (same seed, same dataset)."),
    noise_fraction: float = typer.Option(0.2, "--noise-fraction", help="Share of vehicle labels with Gaussian jitter."),
    noise_center_std: float = typer.Option(
        C.SIM_BENCH_NOISE[0], "--noise-center-std", help="Jitter std of the centre (m)."
    ),
    noise_size_std: float = typer.Option(
        C.SIM_BENCH_NOISE[1], "--noise-size-std", help="Jitter std of length and width (m)."
    ),
    noise_yaw_std: float = typer.Option(C.SIM_BENCH_NOISE[2], "--noise-yaw-std", help="Jitter std of the yaw (rad)."),
    gross_fraction: float = typer.Option(
        0.02,
        "--gross-fraction",
        help="Share of vehicle labels with a gross error (shifted 1 m, swapped l/w, turned 90°).",
    ),
    clutter: bool = typer.Option(
        False,
        "--clutter",
        help="KITTI: add unlabelled surroundings: building walls beside the road, poles and bushes (docs/simulator.md).",
    ),
    drop_fraction: float = typer.Option(
        0.0,
        "--drop-fraction",
        metavar="F",
        help="KITTI: leave out this share of the vehicle labels (their points stay): missing labels, recorded in manifest.parquet (column dropped).",
    ),
    see_through: float = typer.Option(
        0.0,
        "--see-through",
        metavar="F",
        help="KITTI: this share of the rays that meet a car's or van's windows pass through them (on to the interior, the road behind or beyond), as through real glass; manifest columns glass_rays.",
    ),
    under_chassis: float = typer.Option(
        0.0,
        "--under-chassis",
        metavar="F",
        help="KITTI: this share of the rays that meet a vehicle lower than its ground clearance (cars 0.15–0.3 m, trucks 0.4–0.9 m) pass under it; manifest columns under_rays, clearance.",
    ),
    track_noise: bool = typer.Option(
        False,
        "--track-noise",
        help="waymo-v2, waymo-v1, av2: label noise inside tracks — every vehicle label a few cm / 0.02 rad off (ordinary per-frame scatter) and 5 % with one annotator error (length ±0.25–0.5 m, width ±0.15–0.3 m, heading ±0.1–0.25 rad or flipped, centre 0.3–0.6 m), in the manifest's track_error_kind; the tracks benchmark's noise (use with --noise-fraction 0 --gross-fraction 0).",
    ),
    moving: float = typer.Option(
        0.0,
        "--moving",
        help="waymo-v2, waymo-v1, av2: share of the vehicles that drive (3–12 m/s, turning gently); the rest are parked.",
    ),
    workers: int = typer.Option(1, "--workers", help="KITTI: worker processes (same files for any count)."),
    detections: bool = typer.Option(
        False,
        "--detections",
        help="Also write a synthetic detector's output for `labelaudit eval`: KITTI OUT/detections/ (result files), av2 OUT/detections.feather.",
    ),
    detections_cov: bool = typer.Option(
        False,
        "--detections-cov",
        help="With --detections: a probabilistic detector, per-detection std in OUT/detections.parquet.",
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a simulated dataset already in OUT."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """Write a synthetic LiDAR dataset (KITTI, Waymo v2/v1 or Argoverse 2 layout) with known, injected label noise.

    manifest.parquet in OUT records every object's true box, written box and perturbation (docs/simulator.md). Waymo segments and AV2 logs are sequences: a static scene seen from an ego vehicle driving through it, each object one track id, ego poses in the files; the noise options perturb the vehicle labels of every frame. --detections adds a synthetic detector (localisation noise growing with distance, misses, false positives, scores that follow quality; docs/eval.md).

    [bold]Examples[/bold]

      labelaudit simulate sim/ --frames 100 --seed 1

      labelaudit simulate sim-av2/ --dataset-format av2 --sequences 4 --frames 50 && labelaudit infer sim-av2/

      labelaudit simulate sim-av2/ --dataset-format av2 --detections && labelaudit eval sim-av2/ sim-av2/detections.feather

      labelaudit simulate sim-waymo/ --dataset-format waymo-v2 --sequences 2 --frames 20 --size small

      labelaudit simulate sim-tracks/ --dataset-format waymo-v2 --track-noise --moving 0.5 --noise-fraction 0 --gross-fraction 0 --frames 40 --size small

      labelaudit simulate sim/ --noise-fraction 0.3 --noise-center-std 0.2 --gross-fraction 0.05

      labelaudit simulate sim/ --frames 50 --detections && labelaudit eval sim/ sim/detections

      labelaudit simulate sim/ --clutter --drop-fraction 0.15 && labelaudit infer sim/ -o results/

      labelaudit simulate sim/ --see-through 0.5 --under-chassis 1 && labelaudit infer sim/ -o results/
    """
    from labelaudit.sim.dataset import simulate_dataset, simulate_sequences
    from labelaudit.sim.noise import NoiseSpec

    with handle_errors(debug):
        if frames < 1:
            raise typer.BadParameter(f"must be ≥ 1, got {frames}", param_hint="--frames")
        if workers < 1:
            raise typer.BadParameter(f"must be ≥ 1, got {workers}", param_hint="--workers")
        if sequences < 1:
            raise typer.BadParameter(f"must be ≥ 1, got {sequences}", param_hint="--sequences")
        if detections_cov and not detections:
            raise typer.BadParameter("needs --detections", param_hint="--detections-cov")
        sequence = dataset_format is not SimFormat.kitti
        if detections and dataset_format in (SimFormat.waymo_v2, SimFormat.waymo_v1):
            raise typer.BadParameter(
                f"the synthetic detector writes KITTI result files or AV2 detections; not available for {dataset_format.value}",
                param_hint="--detections",
            )
        if detections_cov and sequence:
            raise typer.BadParameter(
                "AV2 detections carry no per-detection std; KITTI only", param_hint="--detections-cov"
            )
        if sequence and workers > 1:
            raise typer.BadParameter(
                f"{dataset_format.value} sequences are simulated in one process", param_hint="--workers"
            )
        try:
            spec = NoiseSpec(
                fraction=noise_fraction,
                center_std=noise_center_std,
                size_std=noise_size_std,
                yaw_std=noise_yaw_std,
                gross_fraction=gross_fraction,
            )
        except ValueError as exc:
            raise typer.BadParameter(str(exc), param_hint="--noise-*/--gross-fraction") from None
        if not 0.0 <= drop_fraction <= 1.0:
            raise typer.BadParameter(f"must be in [0, 1], got {drop_fraction}", param_hint="--drop-fraction")
        if sequence and (clutter or drop_fraction > 0 or see_through > 0 or under_chassis > 0):
            raise typer.BadParameter(
                f"KITTI only, not {dataset_format.value} sequences",
                param_hint="--clutter/--drop-fraction/--see-through/--under-chassis",
            )
        for value, hint in ((see_through, "--see-through"), (under_chassis, "--under-chassis")):
            if not 0.0 <= value <= 1.0:
                raise typer.BadParameter(f"must be a share in [0, 1], got {value}", param_hint=hint)
        if not sequence and (track_noise or moving):
            raise typer.BadParameter(
                "KITTI frames are not sequences; use --dataset-format waymo-v2, waymo-v1 or av2",
                param_hint="--track-noise/--moving",
            )
        if not 0.0 <= moving <= 1.0:
            raise typer.BadParameter(f"must be a fraction in [0, 1], got {moving}", param_hint="--moving")
        if sequence:
            from labelaudit.sim.detector import DetectorSpec
            from labelaudit.sim.tracknoise import TrackNoiseSpec

            summary = simulate_sequences(
                out,
                dataset_format.value,
                sequences=sequences,
                frames=frames,
                seed=seed,
                noise=spec,
                size=size.value,
                progress=not quiet,
                overwrite=overwrite,
                detections=DetectorSpec() if detections else None,
                track_noise=TrackNoiseSpec() if track_noise else None,
                moving_fraction=moving,
            )
            what = f"{sequences} {'log' if dataset_format is SimFormat.av2 else 'segment'}(s) of {frames} frames ({summary.num_labels} labels)"
        else:
            from labelaudit.sim.raycast import SeeThrough
            from labelaudit.sim.scene import SceneSpec

            scene = SceneSpec(num_clutter=C.SIM_CLUTTER) if clutter else SceneSpec()
            see = SeeThrough(glass=see_through, under=under_chassis)
            simulate_dataset(
                out,
                frames=frames,
                seed=seed,
                noise=spec,
                progress=not quiet,
                workers=workers,
                overwrite=overwrite,
                scene=scene,
                drop_fraction=drop_fraction,
                see_through=see if see.active else None,
            )
            what = f"{frames} frames"
        err().print(f"wrote {what} to {escape(str(out))} (next: labelaudit infer {escape(str(out))})", soft_wrap=True)
        if sequence and summary.detections is not None:
            det = summary.detections
            path = out / "detections.feather"
            err().print(
                f"wrote {det.detections} synthetic detections to {escape(str(path))} (next: labelaudit eval {escape(str(out))} {escape(str(path))})",
                soft_wrap=True,
            )
        elif detections:
            from labelaudit.sim.detector import DetectorSpec, simulate_detections

            det = simulate_detections(out, DetectorSpec(probabilistic=detections_cov), seed=seed)
            extra = f" and {det.parquet}" if det.parquet else ""
            err().print(
                f"wrote {det.detections} synthetic detections to {escape(str(det.folder))}{escape(extra)} "
                f"(next: labelaudit eval {escape(str(out))} {escape(str(det.parquet or det.folder))})",
                soft_wrap=True,
            )
