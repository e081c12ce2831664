"""Label noise inside tracks: the ordinary per-frame scatter of labelling every frame anew, plus
the errors an annotator makes in single frames of a track (a size, a heading, a centre).
Pure functions of seeded generators; no I/O. Ground truth for the tracks benchmark
(``scripts/bench_tracks.py``), recorded per object-frame in the simulator's manifest.

Every vehicle label gets the ordinary noise (Gaussian: centre, length, width, yaw). With
probability ``error_fraction`` it also gets one injected error, drawn uniformly from ``kinds``:

=========  ===================================================================================
length     length off by ± U(``length_range``) (the centre kept)
width      width off by ± U(``width_range``)
yaw        heading off by ± U(``yaw_range``)
flip       heading turned by π
centre     centre moved by U(``centre_range``) in a uniformly random BEV direction
=========  ===================================================================================

Random numbers are drawn for every object whatever its class and outcome, so the noise of object
*i* depends only on the generator and *i*.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.core.geometry import normalize_angle
from labelaudit.sim.scene import VEHICLE_CLASSES

FloatArray = NDArray[np.float64]

TRACK_ERROR_KINDS: tuple[str, ...] = ("length", "width", "yaw", "flip", "centre")
"""Injected error kinds (the manifest's ``track_error_kind``; ``none`` for a clean label)."""
ISSUE_OF_KIND = {"length": "size", "width": "size", "yaw": "heading", "flip": "heading", "centre": "position"}
"""The ``track_issue`` each injected kind should be reported as."""


@dataclass(frozen=True)
class TrackNoiseSpec:
    """Per-frame label noise inside tracks (defaults: the tracks benchmark's, constants ``SIM_TRACK_*``).

    Attributes
    ----------
    center_std, length_std, width_std, yaw_std : ordinary per-frame noise (m, rad), every vehicle label
    error_fraction : expected share of vehicle labels with one injected error
    kinds : injected error kinds, from :data:`TRACK_ERROR_KINDS`
    length_range, width_range, yaw_range, centre_range : (low, high) magnitude of each kind (m, rad)
    classes : classes that may be perturbed
    """

    center_std: float = C.SIM_TRACK_NOISE[0]
    length_std: float = C.SIM_TRACK_NOISE[1]
    width_std: float = C.SIM_TRACK_NOISE[2]
    yaw_std: float = C.SIM_TRACK_NOISE[3]
    error_fraction: float = C.SIM_TRACK_ERROR_FRACTION
    kinds: tuple[str, ...] = TRACK_ERROR_KINDS
    length_range: tuple[float, float] = C.SIM_TRACK_ERRORS["length"]
    width_range: tuple[float, float] = C.SIM_TRACK_ERRORS["width"]
    yaw_range: tuple[float, float] = C.SIM_TRACK_ERRORS["yaw"]
    centre_range: tuple[float, float] = C.SIM_TRACK_ERRORS["centre"]
    classes: tuple[str, ...] = VEHICLE_CLASSES

    def __post_init__(self) -> None:
        problems = []
        for name in ("center_std", "length_std", "width_std", "yaw_std"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                problems.append(f"{name} must be a finite number >= 0, got {v}")
        if not 0.0 <= self.error_fraction <= 1.0:
            problems.append(f"error_fraction must be in [0, 1], got {self.error_fraction}")
        unknown = [k for k in self.kinds if k not in TRACK_ERROR_KINDS]
        if unknown or not self.kinds:
            problems.append(f"kinds must be a non-empty subset of {TRACK_ERROR_KINDS}, got {self.kinds}")
        for name in ("length_range", "width_range", "yaw_range", "centre_range"):
            lo, hi = getattr(self, name)
            if not (0 <= lo <= hi and np.isfinite(hi)):
                problems.append(f"{name} must be 0 <= low <= high, got {(lo, hi)}")
        if problems:
            raise ValueError("invalid TrackNoiseSpec: " + "; ".join(problems))


def perturb_track_labels(
    boxes: FloatArray, class_names: list[str], spec: TrackNoiseSpec, rng: np.random.Generator
) -> tuple[FloatArray, list[str], FloatArray]:
    """Ordinary noise and injected errors for one frame's labels.

    Parameters
    ----------
    boxes : (K, 7) true boxes (cx, cy, cz, l, w, h, yaw), any frame (the noise is isotropic in BEV)
    class_names : K class names; only ``spec.classes`` are perturbed
    spec : the noise
    rng : this frame's generator

    Returns
    -------
    written : (K, 7) labels (yaw wrapped to [-π, π))
    kinds : K injected kinds (``none`` for a clean label)
    magnitude : (K,) size of the injected error (m or rad; signed for length, width and yaw; 0 for none)
    """
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 7)
    k = len(boxes)
    if len(class_names) != k:
        raise ValueError(f"{k} boxes but {len(class_names)} class names")
    normals = rng.standard_normal((k, 4))  # centre x, centre y, length, width … (yaw below)
    dyaw = rng.standard_normal(k)
    u = rng.random(k)
    pick = rng.integers(0, len(spec.kinds), size=k)
    frac = rng.random(k)
    sign = rng.choice([-1.0, 1.0], size=k)
    angle = rng.uniform(-np.pi, np.pi, size=k)

    written = boxes.copy()
    kinds = ["none"] * k
    magnitude = np.zeros(k)
    ranges = {
        "length": spec.length_range,
        "width": spec.width_range,
        "yaw": spec.yaw_range,
        "centre": spec.centre_range,
    }
    for i in range(k):
        if class_names[i] not in spec.classes:
            continue
        b = written[i]
        b[0] += spec.center_std * normals[i, 0]
        b[1] += spec.center_std * normals[i, 1]
        b[3] += spec.length_std * normals[i, 2]
        b[4] += spec.width_std * normals[i, 3]
        b[6] += spec.yaw_std * dyaw[i]
        if u[i] < spec.error_fraction:
            kind = spec.kinds[pick[i]]
            kinds[i] = kind
            if kind == "flip":
                b[6] += np.pi
                magnitude[i] = np.pi
            else:
                lo, hi = ranges[kind]
                m = lo + (hi - lo) * frac[i]
                if kind == "centre":
                    b[0] += m * np.cos(angle[i])
                    b[1] += m * np.sin(angle[i])
                    magnitude[i] = m
                else:
                    magnitude[i] = sign[i] * m
                    b[{"length": 3, "width": 4, "yaw": 6}[kind]] += sign[i] * m
        b[3:6] = np.maximum(b[3:6], C.SIM_MIN_NOISY_SIZE)
        b[6] = normalize_angle(float(b[6]))
    return written, kinds, magnitude
