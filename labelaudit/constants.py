"""Tunables and their defaults, one comment each. Per-dataset values live in ``configs/*.toml``."""

from __future__ import annotations

# --- model (DESIGN.md §4) ---
DEFAULT_MODEL = "bev"  # BEV is what the paper evaluates and what most label tools show
DEFAULT_SIGMA = 0.2  # LiDAR noise std in metres; the paper uses 0.2 for KITTI, 0.3 for Waymo
DEFAULT_NUM_NEAREST = 3  # M: surface points each LiDAR point may be registered to (paper: 3)
DEFAULT_PRIOR_WEIGHT = 1.0  # w: the prior covariance is divided by w (larger = trust annotators more)
DEFAULT_MIN_POINTS = 3  # boxes with fewer points get status "few_points" (still inferred; prior dominates)

# --- spatial distribution p_G and JIoU (DESIGN.md §5) ---
DEFAULT_CELLS_PER_SIDE = 64  # grid cells across the longer box side; JIoU stable ±0.01 when doubled
DEFAULT_NUM_SAMPLES = 256  # quasi-random (Sobol) samples of φ for form (b) of p_G
DEFAULT_SUPPORT_STD = 3.0  # grid extends this many corner stds beyond the box
DEFAULT_QMC_SEED = 0  # fixed so results are reproducible run to run

# --- crop (DESIGN.md §2) ---
DEFAULT_CROP_MARGIN = 0.1  # BEV margin in metres added around each box when selecting points
DEFAULT_GROUND_CUT = 0.1  # points within this height above the box bottom are ground, dropped

# --- classes ---
DEFAULT_CLASSES = ("Car", "Van", "Truck")  # vehicles: the paper's evaluation classes


# Prior std per class (metres, radians), before the weight w.
DEFAULT_PRIORS: dict[str, dict[str, float]] = {
    # KITTI car, from the authors' code: centre 0.25 m per axis, l 0.44, w 0.11, yaw 0.17 rad.
    # Height is not in the paper; 0.11 m (like width) is our choice.
    "default": {"center": 0.25, "length": 0.44, "width": 0.11, "height": 0.11, "yaw": 0.17},
    # Not in the paper: people and bikes are small, and their heading is harder to annotate.
    "Pedestrian": {"center": 0.10, "length": 0.10, "width": 0.10, "height": 0.10, "yaw": 0.50},
    "Cyclist": {"center": 0.15, "length": 0.20, "width": 0.10, "height": 0.10, "yaw": 0.25},
}
