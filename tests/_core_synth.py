"""Synthetic LiDAR points on chosen faces of a box, for the core-model tests."""

from __future__ import annotations

import numpy as np

from labelaudit.core import geometry as g

# unit-box coordinate fixed by each face: (axis, value)
FACES = {"-x": (0, -0.5), "+x": (0, 0.5), "-y": (1, -0.5), "+y": (1, 0.5), "-z": (2, -0.5), "+z": (2, 0.5)}


def face_points(box, faces, n_per_face: int, noise: float = 0.0, seed: int = 0, z_spread: bool = True) -> np.ndarray:
    """Points (n, 3) spread uniformly over the given faces of a box, plus isotropic Gaussian noise.

    ``z_spread=False`` puts all points at the box's mid-height (a single scan line).
    """
    rng = np.random.default_rng(seed)
    box = np.asarray(box, dtype=float)
    out = []
    for face in faces:
        axis, value = FACES[face]
        v = rng.uniform(-0.5, 0.5, (n_per_face, 3))
        if not z_spread:
            v[:, 2] = 0.0
        v[:, axis] = value
        out.append(g.unit_to_world(v, box, "3d"))
    pts = np.vstack(out) if out else np.zeros((0, 3))
    return pts + rng.normal(0.0, noise, pts.shape) if noise > 0 else pts


def rigid_motion(box, points, yaw: float, shift, origin=(0.0, 0.0, 0.0)):
    """Rotate about z by ``yaw`` and translate by ``shift``: box, points and sensor origin together."""
    R = g.rotation_z(yaw)
    shift = np.asarray(shift, dtype=float)
    b = np.asarray(box, dtype=float).copy()
    b[:3] = R @ b[:3] + shift
    b[6] = float(g.normalize_angle(b[6] + yaw))
    pts = np.asarray(points, dtype=float) @ R.T + shift
    o = R @ np.asarray(origin, dtype=float) + shift
    return b, pts, o
