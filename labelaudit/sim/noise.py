"""Known label noise: jitter and gross errors injected into true boxes, recorded per object.
Pure functions of seeded generators; no I/O.

Each vehicle label draws one uniform number ``u``: ``u < gross_fraction`` → a gross error (one of
``gross_kinds``, uniformly); else ``u < gross_fraction + fraction`` → Gaussian jitter; else the
label stays exact. So ``fraction`` and ``gross_fraction`` are the expected shares of jittered and
grossly wrong vehicle labels; other classes are never perturbed.

Random numbers are drawn for every object whatever its class and outcome, so the perturbation of
object *i* depends only on the frame's noise seed and *i*, not on the other objects.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.core.geometry import normalize_angle
from labelaudit.sim.scene import VEHICLE_CLASSES

FloatArray = NDArray[np.float64]

PERTURBATION_KINDS: tuple[str, ...] = ("none", "jitter", "shift", "swap_lw", "yaw90")
"""Values of the manifest's ``perturbation`` column."""
GROSS_KINDS: tuple[str, ...] = ("shift", "swap_lw", "yaw90")


@dataclass(frozen=True)
class NoiseSpec:
    """Label noise to inject (defaults: none).

    Attributes
    ----------
    fraction : expected share of vehicle labels with Gaussian jitter
    center_std : std of the centre jitter along x and y (m)
    center_std_z : std of the centre jitter along z (m); 0 keeps the height of the centre
    size_std : std of the length and width jitter (m)
    height_std : std of the height jitter (m); 0 keeps the height
    yaw_std : std of the yaw jitter (rad)
    gross_fraction : expected share of vehicle labels with a gross error
    gross_shift : distance of the "shift" gross error (m), in a uniformly random BEV direction
    gross_kinds : which gross errors to draw from: "shift" (centre moved by ``gross_shift``),
        "swap_lw" (length and width exchanged), "yaw90" (heading turned by ±90°). Note that
        "swap_lw" and "yaw90" give the same BEV footprint (the box turned by 90° about its
        centre); they differ in which side is called the length.
    classes : classes that may be perturbed
    min_size : perturbed sizes are clipped to at least this (m)
    """

    fraction: float = 0.0
    center_std: float = C.SIM_BENCH_NOISE[0]
    center_std_z: float = 0.0
    size_std: float = C.SIM_BENCH_NOISE[1]
    height_std: float = 0.0
    yaw_std: float = C.SIM_BENCH_NOISE[2]
    gross_fraction: float = 0.0
    gross_shift: float = C.SIM_GROSS_SHIFT
    gross_kinds: tuple[str, ...] = GROSS_KINDS
    classes: tuple[str, ...] = VEHICLE_CLASSES
    min_size: float = C.SIM_MIN_NOISY_SIZE

    def __post_init__(self) -> None:
        problems = []
        for name in ("fraction", "gross_fraction"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                problems.append(f"{name} must be in [0, 1], got {v}")
        if self.fraction + self.gross_fraction > 1.0:
            problems.append(f"fraction + gross_fraction must be <= 1, got {self.fraction} + {self.gross_fraction}")
        for name in ("center_std", "center_std_z", "size_std", "height_std", "yaw_std", "gross_shift"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                problems.append(f"{name} must be a finite number >= 0, got {v}")
        unknown = [k for k in self.gross_kinds if k not in GROSS_KINDS]
        if unknown or (self.gross_fraction > 0 and not self.gross_kinds):
            problems.append(f"gross_kinds must be a non-empty subset of {GROSS_KINDS}, got {self.gross_kinds}")
        if self.min_size <= 0:
            problems.append(f"min_size must be > 0, got {self.min_size}")
        if problems:
            raise ValueError("invalid NoiseSpec: " + "; ".join(problems))

    @classmethod
    def benchmark(cls) -> "NoiseSpec":
        """The label-error benchmark's noise: 20 % jitter (centre 0.3 m, size 0.2 m, yaw 0.1 rad) + 2 % gross."""
        return cls(
            fraction=C.SIM_BENCH_FRACTIONS[0],
            gross_fraction=C.SIM_BENCH_FRACTIONS[1],
            center_std=C.SIM_BENCH_NOISE[0],
            size_std=C.SIM_BENCH_NOISE[1],
            yaw_std=C.SIM_BENCH_NOISE[2],
        )

    @property
    def enabled(self) -> bool:
        return self.fraction > 0 or self.gross_fraction > 0


def perturb_boxes(
    boxes: FloatArray, class_names: list[str], spec: NoiseSpec, rng: np.random.Generator
) -> tuple[FloatArray, list[str]]:
    """Apply label noise to true boxes.

    Parameters
    ----------
    boxes : (K, 7) true boxes (cx, cy, cz, l, w, h, yaw)
    class_names : K class names; only ``spec.classes`` are perturbed
    spec : the noise to inject
    rng : the frame's label-noise generator

    Returns
    -------
    written : (K, 7) boxes to write as labels (yaw wrapped to [-π, π))
    kinds : K perturbation kinds, from :data:`PERTURBATION_KINDS`
    """
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 7)
    k = len(boxes)
    if len(class_names) != k:
        raise ValueError(f"{k} boxes but {len(class_names)} class names")
    # Fixed draws per object, whatever happens to it (see module doc).
    u = rng.random(k)
    normals = rng.standard_normal((k, 6))  # dx, dy, dz, dl, dw, dh
    dyaw = rng.standard_normal(k)
    gross_pick = rng.integers(0, max(len(spec.gross_kinds), 1), size=k)
    angle = rng.uniform(-np.pi, np.pi, size=k)
    sign = rng.choice([-1.0, 1.0], size=k)

    written = boxes.copy()
    kinds = ["none"] * k
    for i in range(k):
        if class_names[i] not in spec.classes or not spec.enabled:
            continue
        b = written[i]
        if u[i] < spec.gross_fraction:
            kind = spec.gross_kinds[gross_pick[i]]
            if kind == "shift":
                b[0] += spec.gross_shift * np.cos(angle[i])
                b[1] += spec.gross_shift * np.sin(angle[i])
            elif kind == "swap_lw":
                b[3], b[4] = b[4], b[3]
            else:  # yaw90
                b[6] += sign[i] * np.pi / 2
            kinds[i] = kind
        elif u[i] < spec.gross_fraction + spec.fraction:
            stds = np.array(
                [spec.center_std, spec.center_std, spec.center_std_z, spec.size_std, spec.size_std, spec.height_std]
            )
            b[:6] += stds * normals[i]
            b[3:6] = np.maximum(b[3:6], spec.min_size)
            b[6] += spec.yaw_std * dyaw[i]
            kinds[i] = "jitter"
        if kinds[i] in ("jitter", "yaw90"):  # only where yaw changed, so other boxes keep their exact yaw
            b[6] = normalize_angle(b[6])
    return written, kinds
