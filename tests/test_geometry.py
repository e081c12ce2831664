"""Geometry: φ(y) round trips, J(v*)·φ = corners, Jacobians against finite differences, transforms."""

from __future__ import annotations

import numpy as np
import pytest

from labelaudit.core import geometry as g
from labelaudit.core import iou as IOU

RNG = np.random.default_rng(1)


def random_boxes(n: int) -> np.ndarray:
    boxes = np.empty((n, 7))
    boxes[:, 0:3] = RNG.uniform(-50, 50, (n, 3))
    boxes[:, 3:6] = RNG.uniform(0.3, 8.0, (n, 3))
    boxes[:, 6] = RNG.uniform(-np.pi, np.pi, n)
    return boxes


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_phi_round_trip(model):
    for box in random_boxes(50):
        phi = g.box_to_phi(box, model)
        assert phi.shape == (g.phi_dim(model),)
        back = g.phi_to_box(phi, model, cz=box[2], height=box[5])
        assert np.allclose(back[:6], box[:6])
        assert abs(g.normalize_angle(back[6] - box[6])) < 1e-12
        ext = g.box_to_extended(box, model)
        assert np.allclose(g.extended_to_phi(ext, model), phi)
        assert np.allclose(g.phi_to_extended(phi, model), ext, atol=1e-12)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_design_matrix_maps_unit_corners_to_box_corners(model):
    for box in random_boxes(20):
        corners = g.box_corners(box, model)
        d = g.point_dim(model)
        R = g.rotation_z(box[6])[:d, :d]
        # independent construction of the corners: centre + R · (±l/2, ±w/2[, ±h/2])
        if d == 2:
            unit = g.BEV_CORNERS_UNIT
        else:
            unit = np.vstack(
                [np.c_[g.BEV_CORNERS_UNIT, -0.5 * np.ones(4)], np.c_[g.BEV_CORNERS_UNIT, 0.5 * np.ones(4)]]
            )
        expected = (unit * box[3 : 3 + d]) @ R.T + box[:d]
        J = g.design_matrix(unit, model)
        assert np.allclose(J @ g.box_to_phi(box, model), expected)
        assert np.allclose(corners, expected)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_world_unit_round_trip(model):
    d = g.point_dim(model)
    for box in random_boxes(10):
        v = RNG.uniform(-0.7, 0.7, (30, d))
        pts = g.unit_to_world(v, box, model)
        assert np.allclose(g.world_to_unit(pts, box, model), v)


def _numeric_jacobian(f, x, eps=1e-6):
    cols = []
    for i in range(len(x)):
        dx = np.zeros_like(x)
        dx[i] = eps
        cols.append((f(x + dx) - f(x - dx)) / (2 * eps))
    return np.stack(cols, -1)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_dphi_dext_matches_finite_differences(model):
    for box in random_boxes(10):
        ext = g.box_to_extended(box, model)
        num = _numeric_jacobian(lambda e: g.extended_to_phi(e, model), ext)
        assert np.allclose(g.dphi_dext(box, model), num, atol=1e-6)
        assert np.allclose(g.dext_dphi(box, model) @ g.dphi_dext(box, model), np.eye(len(ext)), atol=1e-9)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_box_param_jacobian_matches_finite_differences(model):
    for box in random_boxes(10):
        phi = g.box_to_phi(box, model)
        K, names = g.box_param_jacobian(box, model)
        idx = [g.BOX_FIELDS.index(n) for n in names]

        def reported(f):
            y = g.phi_to_box(f, model, cz=box[2], height=box[5])
            y[6] = box[6] + g.normalize_angle(y[6] - box[6])  # unwrap near the label's yaw
            return y[idx]

        num = _numeric_jacobian(reported, phi)
        assert np.allclose(K, num, atol=1e-6)


def test_phi_axes_are_the_box_edges():
    box = np.array([1.0, 2.0, 0.5, 4.0, 2.0, 1.5, 0.3])
    centre, axes = g.phi_axes(g.box_to_phi(box, "bev"), "bev")
    assert np.allclose(centre, box[:2])
    assert np.allclose(axes, g.rotation_2d(box[6]) @ np.diag(box[3:5]))
    centre3, axes3 = g.phi_axes(g.box_to_phi(box, "3d"), "3d")
    assert np.allclose(centre3, box[:3])
    assert np.allclose(axes3, g.rotation_z(box[6]) @ np.diag(box[3:6]))


def test_validate_box_rejects_bad_boxes():
    with pytest.raises(ValueError, match="length"):
        g.validate_box([0, 0, 0, 0.0, 1, 1, 0])
    with pytest.raises(ValueError, match="non-finite"):
        g.validate_box([0, np.nan, 0, 1, 1, 1, 0])
    with pytest.raises(ValueError, match="7 numbers"):
        g.validate_box([0, 0, 0, 1, 1, 1])


def test_transforms_round_trip():
    R = g.rotation_z(0.7) @ np.array([[1, 0, 0], [0, np.cos(0.2), -np.sin(0.2)], [0, np.sin(0.2), np.cos(0.2)]])
    T = g.make_transform(R, [1.0, -2.0, 3.0])
    pts = RNG.normal(size=(20, 4))
    back = g.transform_points(g.invert_transform(T), g.transform_points(T, pts))
    assert np.allclose(back, pts)
    assert np.allclose(g.invert_transform(T) @ T, np.eye(4))


def test_exact_ious():
    a = np.array([0, 0, 0, 4, 2, 2, 0.0])
    b = np.array([1, 0, 0.5, 4, 2, 2, 0.0])
    # overlap 3 × 2 in BEV, and 1.5 in z
    assert IOU.bev_iou_exact(a, b) == pytest.approx(6 / (8 + 8 - 6))
    assert IOU.iou_3d_exact(a, b) == pytest.approx(9 / (16 + 16 - 9))
    assert IOU.bev_iou_exact(a, a + [100, 0, 0, 0, 0, 0, 0]) == 0.0
    rotated = a.copy()
    rotated[6] = np.pi  # same rectangle
    assert IOU.bev_iou_exact(a, rotated) == pytest.approx(1.0)


def test_clean_columns_is_clean_points_transposed():
    """The fit's (d, N) layout of a crop: the finite rows' first d coordinates as columns, exactly
    clean_points' values, whatever the input type; float crops take the compiled pass."""
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(50, 4)) * 20.0
    pts[[3, 17], 1] = np.nan
    pts[8, 2] = np.inf
    for arr in (
        pts,
        pts.astype(np.float32),
        np.round(np.nan_to_num(pts[:, :3])).clip(-9, 9).astype(np.int64),
        pts.tolist(),
    ):
        for d in (2, 3):
            want = g.clean_points(arr, d)
            got = g.clean_columns(arr, d)
            assert got.shape == (d, len(want)) and got.dtype == np.float64 and got.flags.c_contiguous
            assert got.tobytes() == np.ascontiguousarray(want.T).tobytes()
    assert g.clean_columns(pts, 3).shape == (3, 47)  # the rows with a NaN or inf in x, y, z are dropped
    assert g.clean_columns(pts, 2).shape == (2, 48)  # the inf in z does not count in 2D
    for empty in (None, np.zeros((0, 3)), np.zeros((0, 3), dtype=np.float32)):
        assert g.clean_columns(empty, 3).shape == (3, 0)
    with pytest.raises(ValueError):
        g.clean_columns(np.zeros((4, 2)), 3)


def test_cos_sin_is_numpys_and_keeps_the_sign_of_zero():
    """cos_sin gives NumPy's values, asked once or twice in a row, and a yaw of −0.0 after 0.0
    (equal as floats) gets sin −0.0."""
    rng = np.random.default_rng(2)
    for yaw in [*rng.uniform(-7, 7, 200), 0.0, -0.0, 0.0, np.pi, np.pi]:
        for _ in range(2):  # asked again: the same values
            c, s = g.cos_sin(yaw)
            assert np.float64(c).tobytes() == np.cos(yaw).tobytes()
            assert np.float64(s).tobytes() == np.sin(yaw).tobytes()
    g.cos_sin(0.0)
    assert str(g.cos_sin(-0.0)[1]) == "-0.0" and str(g.cos_sin(np.float64(0.0))[1]) == "0.0"
