"""Spatial distribution, probabilistic Jaccard, JIoU and JIoU-GT."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from _core_synth import face_points, rigid_motion
from labelaudit import constants as C
from labelaudit.config import ModelParams, SpatialParams
from labelaudit.core import geometry as g
from labelaudit.core import iou as IOU
from labelaudit.core import posterior as M
from labelaudit.core import spatial as sp

NEAR = np.array([15.0, 5.0, 0.75, 4.2, 1.7, 1.5, 0.0])  # sensor at the origin sees −x and −y
FAR = np.array([40.0, 12.0, 0.75, 4.2, 1.7, 1.5, 0.0])
SP = SpatialParams()


def jgt(box, pts, model="bev", spatial=SP, **model_kw):
    post = M.infer_label(box, pts, "Car", ModelParams(kind=model, **model_kw))
    return sp.jiou_gt(post, spatial)


# ---------------------------------------------------------------------------------------------
# probabilistic Jaccard
# ---------------------------------------------------------------------------------------------


def jaccard_brute(p, q):
    total = 0.0
    for i in range(len(p)):
        if p[i] > 0 and q[i] > 0:
            total += 1.0 / sum(max(p[j] / p[i], q[j] / q[i]) for j in range(len(p)))
    return total


def test_jaccard_matches_brute_force_on_random_inputs():
    rng = np.random.default_rng(0)
    for trial in range(200):
        n = int(rng.integers(1, 25))
        p = rng.exponential(size=n) * (rng.random(n) < 0.7)
        q = rng.exponential(size=n) * (rng.random(n) < 0.7)
        if trial % 4 == 0:  # exact ties of the ratio p/q
            q[: n // 2] = 2.0 * p[: n // 2]
        if trial % 5 == 0:
            p = np.round(p, 1)
            q = np.round(q, 1)
        assert sp.jaccard(p, q) == pytest.approx(jaccard_brute(p, q), rel=1e-9, abs=1e-12)


def test_jaccard_outside_masses_equal_listed_cells():
    rng = np.random.default_rng(2)
    for _ in range(50):
        n = int(rng.integers(2, 15))
        p = rng.exponential(size=n) * (rng.random(n) < 0.8)
        q = rng.exponential(size=n) * (rng.random(n) < 0.8)
        p_only = rng.exponential(size=3)
        q_only = rng.exponential(size=2)
        full = sp.jaccard(np.r_[p, p_only, 0, 0], np.r_[q, 0, 0, 0, q_only])
        assert sp.jaccard(p, q, p_outside=p_only.sum(), q_outside=q_only.sum()) == pytest.approx(full, rel=1e-12)


def test_jaccard_counts_equal_repeated_cells():
    rng = np.random.default_rng(1)
    for _ in range(50):
        n = int(rng.integers(1, 12))
        p = rng.exponential(size=n) * (rng.random(n) < 0.8)
        q = rng.exponential(size=n) * (rng.random(n) < 0.8)
        c = rng.integers(1, 5, n)
        expected = jaccard_brute(np.repeat(p, c), np.repeat(q, c))
        assert sp.jaccard(p, q, c) == pytest.approx(expected, rel=1e-9, abs=1e-12)


def test_jaccard_of_uniform_sets_is_iou_and_scale_free():
    a = np.zeros(100)
    b = np.zeros(100)
    a[10:60] = 1.0
    b[40:90] = 1.0
    assert sp.jaccard(a / a.sum(), 7 * b) == pytest.approx(20 / 80)
    assert sp.jaccard(a, a) == pytest.approx(1.0)
    c = np.zeros(100)
    c[70:90] = 1.0
    assert sp.jaccard(a, c) == 0.0
    with pytest.raises(ValueError):
        sp.jaccard(-a, b)


# ---------------------------------------------------------------------------------------------
# deterministic boxes: JIoU = IoU
# ---------------------------------------------------------------------------------------------


def _random_pairs(n, seed):
    rng = np.random.default_rng(seed)
    pairs = []
    for i in range(n):
        a = np.r_[
            rng.uniform(-2, 2, 2),
            rng.uniform(-0.6, 0.6),
            rng.uniform(1, 5),
            rng.uniform(0.5, 2.5),
            rng.uniform(0.5, 2),
            rng.uniform(-np.pi, np.pi),
        ]
        b = np.r_[
            rng.uniform(-2, 2, 2),
            rng.uniform(-0.6, 0.6),
            rng.uniform(1, 5),
            rng.uniform(0.5, 2.5),
            rng.uniform(0.5, 2),
            rng.uniform(-np.pi, np.pi),
        ]
        if i % 10 == 0:
            b[:2] = a[:2] + 8.0  # far apart: IoU 0
        pairs.append((a, b))
    return pairs


def test_deterministic_jiou_equals_exact_bev_iou():
    errors = []
    for a, b in _random_pairs(200, 0):
        j = sp.jiou(sp.BoxDistribution.deterministic(a, "bev"), sp.BoxDistribution.deterministic(b, "bev"), SP)
        errors.append(j - IOU.bev_iou_exact(a, b))
    assert np.max(np.abs(errors)) < 0.01


def test_deterministic_jiou_equals_exact_3d_iou():
    errors = []
    for a, b in _random_pairs(200, 1):
        j = sp.jiou(sp.BoxDistribution.deterministic(a, "3d"), sp.BoxDistribution.deterministic(b, "3d"), SP)
        errors.append(j - IOU.iou_3d_exact(a, b))
    assert np.max(np.abs(errors)) < 0.01


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_identical_and_disjoint_boxes(model):
    det = sp.BoxDistribution.deterministic(NEAR, model)
    assert sp.jiou(det, det, SP) == pytest.approx(1.0, abs=1e-12)
    shifted = NEAR + np.array([10.0, 0, 0, 0, 0, 0, 0])
    assert sp.jiou(sp.BoxDistribution.deterministic(shifted, model), det, SP) == 0.0


# ---------------------------------------------------------------------------------------------
# JIoU-GT: limits and known values
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_dense_points_on_all_faces_give_jiou_gt_near_one(model):
    faces = ["-x", "+x", "-y", "+y"] + (["-z", "+z"] if model == "3d" else [])
    pts = face_points(NEAR, faces, 400, 0.03)
    assert jgt(NEAR, pts, model) >= 0.97


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_zero_points_jiou_gt_is_the_prior_only_value(model):
    post = M.infer_label(NEAR, np.zeros((0, 3)), "Car", ModelParams(kind=model))
    value = sp.jiou_gt(post, SP)
    assert np.isfinite(value) and 0.0 < value < 1.0
    prior_cov = M.prior_covariance(NEAR, ModelParams().prior_for("Car"), 1.0, model)
    assert value == pytest.approx(sp.jiou_gt(dataclasses.replace(post, cov=prior_cov), SP), abs=1e-9)
    prior_only = sp.BoxDistribution(NEAR, model, prior_cov)
    assert value == pytest.approx(sp.jiou(sp.BoxDistribution.deterministic(NEAR, model), prior_only, SP), abs=0.005)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_jiou_gt_tends_to_one_as_covariance_vanishes(model):
    post = M.infer_label(NEAR, face_points(NEAR, ["-x", "-y"], 50, 0.03), "Car", ModelParams(kind=model))
    values = [sp.jiou_gt(dataclasses.replace(post, cov=post.cov * s), SP) for s in (1.0, 1e-2, 1e-4, 1e-8)]
    assert np.all(np.diff(values) > 0)
    assert values[-1] > 0.999


# ---------------------------------------------------------------------------------------------
# JIoU-GT: directions
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_more_points_on_the_same_faces_raise_jiou_gt(model):
    values = [jgt(NEAR, face_points(NEAR, ["-x", "-y"], n, 0.03), model) for n in (2, 10, 50, 300)]
    assert np.all(np.diff(values) > 0), values


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_larger_sigma_lowers_jiou_gt(model):
    pts = face_points(NEAR, ["-x", "-y"], 40, 0.03)
    values = [jgt(NEAR, pts, model, sigma=s) for s in (0.05, 0.2, 0.5)]
    assert np.all(np.diff(values) < 0), values


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_larger_prior_weight_raises_jiou_gt(model):
    pts = face_points(NEAR, ["-x"], 20, 0.03)
    values = [jgt(NEAR, pts, model, prior_weight=w) for w in (0.5, 1.0, 4.0)]
    assert np.all(np.diff(values) > 0), values


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_far_sparse_box_is_less_certain_than_near_dense(model):
    near = jgt(NEAR, face_points(NEAR, ["-x", "-y"], 150, 0.03), model)
    far = jgt(FAR, face_points(FAR, ["-x"], 10, 0.05, seed=2), model)
    assert far < near


# ---------------------------------------------------------------------------------------------
# invariance and numerical stability
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_jiou_gt_is_invariant_to_rigid_motion(model):
    pts = face_points(NEAR, ["-x", "-y"], 30, 0.03)
    params = ModelParams(kind=model)
    base = M.infer_label(NEAR, pts, "Car", params)
    for yaw, shift in ((0.7, (5.0, -3.0, 0.2)), (2.9, (-30.0, 20.0, -1.0))):
        b2, p2, o2 = rigid_motion(NEAR, pts, yaw, shift)
        moved = M.infer_label(b2, p2, "Car", params, sensor_origin=o2)
        assert sp.jiou_gt(moved, SP) == pytest.approx(sp.jiou_gt(base, SP), abs=0.01)
        assert np.allclose(moved.corner_tv, base.corner_tv, rtol=0.01)


CASES = {
    "dense two faces": (NEAR, lambda: face_points(NEAR, ["-x", "-y"], 300, 0.05)),
    "far sparse": (FAR, lambda: face_points(FAR, ["-x", "-y"], 5, 0.05)),
    "one face": (NEAR, lambda: face_points(NEAR, ["-y"], 60, 0.05)),
    "two points": (NEAR, lambda: face_points(NEAR, ["-x"], 2, 0.05)),
    "no points": (NEAR, lambda: np.zeros((0, 3))),
}


@pytest.mark.parametrize("model", ["bev", "3d"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_jiou_gt_is_stable_under_doubling_grid_and_samples(model, case):
    box, make = CASES[case]
    post = M.infer_label(box, make(), "Car", ModelParams(kind=model))
    base = sp.jiou_gt(post, SP)
    finer = sp.jiou_gt(post, dataclasses.replace(SP, cells_per_side=2 * SP.cells_per_side))
    more = sp.jiou_gt(post, dataclasses.replace(SP, num_samples=2 * SP.num_samples))
    other_seed = sp.jiou_gt(post, dataclasses.replace(SP, seed=SP.seed + 1))
    assert finer == pytest.approx(base, abs=0.01)
    assert more == pytest.approx(base, abs=0.01)
    assert other_seed == pytest.approx(base, abs=0.01)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_degenerate_boxes_give_finite_jiou_gt(model):
    params = ModelParams(kind=model)
    # a 1 mm box with the car prior (std 0.25 m): its uncertainty dwarfs it, JIoU-GT ≈ 0
    tiny = sp.jiou_gt(M.infer_label([1.0, 1.0, 0.0, 1e-3, 1e-3, 1e-3, 0.2], None, "Car", params), SP)
    assert np.isfinite(tiny) and 0.0 <= tiny < 0.01
    for box, pts in [
        (np.array([0.0, 0.0, 0.0, 1e3, 5e2, 1e2, 1.0]), face_points([0, 0, 0, 1e3, 5e2, 1e2, 1.0], ["+x"], 50)),
        (NEAR, np.tile([[13.0, 4.0, 0.8]], (50, 1))),
        (NEAR, np.array([[100.0, -50.0, 3.0], [-80.0, 40.0, -2.0]])),
    ]:
        value = sp.jiou_gt(M.infer_label(box, pts, "Car", params), SP)
        assert np.isfinite(value) and 0.0 < value <= 1.0


# ---------------------------------------------------------------------------------------------
# box distributions with covariance on y, spatial distribution
# ---------------------------------------------------------------------------------------------


def test_covariance_on_box_parameters_matches_the_same_covariance_on_phi():
    # A rectangular box with std on (cx, cy, l, w, yaw): sampled on y, or propagated to φ to first
    # order with a tiny shear — nearly the same distribution.
    std = np.array([0.2, 0.1, 0.3, 0.1, 0.1])
    on_y = sp.BoxDistribution(NEAR, "bev", np.diag(std**2), cov_on="box")
    G = g.dphi_dext(NEAR, "bev")
    S_ext = np.zeros((6, 6))
    S_ext[:4, :4] = np.diag(std[:4] ** 2)
    S_ext[4:, 4:] = std[4] ** 2 + 1e-8 * np.eye(2)
    on_phi = sp.BoxDistribution(NEAR, "bev", G @ S_ext @ G.T)
    det = sp.BoxDistribution.deterministic(NEAR, "bev")
    assert sp.jiou(det, on_y, SP) == pytest.approx(sp.jiou(det, on_phi, SP), abs=0.02)
    assert sp.jiou(on_y, on_phi, SP) > 0.9
    # BEV also takes the full 7×7 covariance (cz, h ignored)
    full = np.zeros((7, 7))
    idx = [0, 1, 3, 4, 6]
    full[np.ix_(idx, idx)] = np.diag(std**2)
    on_y7 = sp.BoxDistribution(NEAR, "bev", full, cov_on="box")
    assert sp.jiou(det, on_y7, SP) == pytest.approx(sp.jiou(det, on_y, SP), abs=1e-12)


def test_uncertain_detection_against_a_label():
    post = M.infer_label(NEAR, face_points(NEAR, ["-x", "-y"], 100, 0.03), "Car", ModelParams())
    label = sp.BoxDistribution.from_posterior(post)
    good = NEAR + np.array([0.1, 0.05, 0, 0, 0, 0, 0.02])
    bad = NEAR + np.array([1.0, 0.5, 0, 0, 0, 0, 0.2])
    j_good = sp.jiou(sp.BoxDistribution.deterministic(good, "bev"), label, SP)
    j_bad = sp.jiou(sp.BoxDistribution.deterministic(bad, "bev"), label, SP)
    assert 0 < j_bad < j_good < 1
    wide = sp.BoxDistribution(good, "bev", np.diag([0.3, 0.3, 0.2, 0.1, 0.1]) ** 2, cov_on="box")
    assert sp.jiou(wide, label, SP) < j_good


def test_box_distribution_validates_its_covariance():
    with pytest.raises(ValueError):
        sp.BoxDistribution(NEAR, "bev", np.eye(8))
    with pytest.raises(ValueError):
        sp.BoxDistribution(NEAR, "3d", np.eye(5), cov_on="box")
    with pytest.raises(ValueError):
        sp.BoxDistribution([0, 0, 0, -1, 1, 1, 0], "bev")
    with pytest.raises(ValueError):
        sp.jiou(sp.BoxDistribution.deterministic(NEAR, "bev"), sp.BoxDistribution.deterministic(NEAR, "3d"), SP)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_spatial_distribution_is_a_probability_on_the_grid(model):
    post = M.infer_label(NEAR, face_points(NEAR, ["-x"], 20, 0.03), "Car", ModelParams(kind=model))
    grid, mass = sp.spatial_distribution(sp.BoxDistribution.from_posterior(post), SP)
    assert mass.shape == grid.shape
    assert np.all(mass >= 0)
    assert mass.sum() == pytest.approx(1.0, abs=0.02)  # the tails beyond support_std are cut
    det_grid, det_mass = sp.spatial_distribution(sp.BoxDistribution.deterministic(NEAR, model), SP)
    assert det_mass.sum() == pytest.approx(1.0, abs=1e-9)
    centres = det_grid.cell_centres_world()
    inside = np.all(np.abs(g.world_to_unit(centres.reshape(-1, 2), NEAR, "bev")) < 0.5, axis=1).reshape(
        centres.shape[:2]
    )
    bev_mass = det_mass if model == "bev" else det_mass.sum(axis=2)
    assert np.all(bev_mass[~inside] == 0)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_jiou_gt_equals_the_generic_jiou(model):
    for n in (0, 3, 100):
        post = M.infer_label(NEAR, face_points(NEAR, ["-x", "-y"], n, 0.03), "Car", ModelParams(kind=model))
        generic = sp.jiou(sp.BoxDistribution.deterministic(NEAR, model), sp.BoxDistribution.from_posterior(post), SP)
        # jiou_gt rasterises inside the box only and takes the outside mass as 1 − inside (no
        # truncated tails); the generic grid cuts the tails beyond support_std: nearly equal.
        assert sp.jiou_gt(post, SP) == pytest.approx(generic, abs=0.005)


def test_stored_default_samples_equal_the_generated_ones():
    import labelaudit.core.spatial as S

    with np.load(S.SAMPLE_TABLE) as table:
        assert sorted(table.files) == [f"d{d}_n{C.DEFAULT_NUM_SAMPLES}_s{C.DEFAULT_QMC_SEED}" for d in (5, 6, 7, 8)]
        for key in table.files:
            d = int(key.split("_")[0][1:])
            assert np.array_equal(table[key], S.generate_normal_samples(d, C.DEFAULT_NUM_SAMPLES, C.DEFAULT_QMC_SEED))
    assert np.array_equal(S.normal_samples(6, 64, 3), S.generate_normal_samples(6, 64, 3))  # not stored: generated


def test_auditing_an_object_does_not_import_scipy_stats():
    # scipy.stats takes about a second to import in every worker process
    import subprocess
    import sys

    code = (
        "import sys, numpy as np\n"
        "from labelaudit.infer.rows import audit_object\n"
        "from labelaudit.config import load_config\n"
        "pts = np.random.default_rng(0).normal([15, 3, 0.7], 0.5, (50, 3))\n"
        "audit_object(np.array([15.0, 3.0, 0.75, 4.2, 1.7, 1.5, 0.3]), pts, 'Car', load_config(None, 'kitti'))\n"
        "print('scipy.stats' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_compiled_raster_equals_the_bincount_form():
    """The one-pass raster kernel sums exactly as the NumPy form it replaced (bit for bit)."""
    rng = np.random.default_rng(3)
    box = np.array([0.0, 0.0, 0.0, 4.2, 1.8, 1.5, 0.3])
    cov = np.diag([0.05, 0.04, 0.02, 0.02, 0.01, 0.01]) ** 2
    dist = sp.BoxDistribution(box, "bev", cov)
    s = sp.sample_boxes(dist, box, SpatialParams())
    for n in (16, 64, 150):
        xe = np.linspace(-3.5, 3.5 + rng.uniform(0, 0.1), n + 1)
        ye = np.linspace(-1.6, 1.6, n // 2 + 1)
        e = sp._events(s, xe, ye)
        nb = e.ny * (e.nx + 1)
        w = np.broadcast_to(s.weights[:, None], e.i_lo.shape)
        i_lo, i_hi = e.i_lo.ravel(), e.i_hi.ravel()
        wdx = (w * e.dx).ravel()
        steps = np.bincount(i_lo, weights=wdx, minlength=nb) - np.bincount(i_hi, weights=wdx, minlength=nb)
        direct = np.bincount(i_hi, weights=(w * e.f_hi).ravel(), minlength=nb) - np.bincount(
            i_lo, weights=(w * e.f_lo).ravel(), minlength=nb
        )
        want = (np.cumsum(steps.reshape(e.ny, e.nx + 1), axis=-1) + direct.reshape(e.ny, e.nx + 1))[:, : e.nx] * e.dy
        got = sp._raster_bev(s, xe, ye)
        assert got.shape == want.shape and np.array_equal(got, want) and got.sum() > 0.5


def _sample_stats_numpy(phis: np.ndarray, d: int):
    """The NumPy form of spatial._sample_kernel (S > 1), kept as the bit-exact reference."""
    o = d - 2
    centre = phis[:, :d]
    A = np.empty((len(phis), 2, 2))
    A[:, 0, 0], A[:, 1, 0] = phis[:, 2 + o], phis[:, 3 + o]
    A[:, 0, 1], A[:, 1, 1] = -phis[:, 5 + o], phis[:, 4 + o]
    size = np.abs(A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0])
    zint = None
    if d == 3:
        hh = 0.5 * np.abs(phis[:, 7])
        zint = np.stack([centre[:, 2] - hh, centre[:, 2] + hh], axis=1)
        size = size * 2.0 * hh
    S = len(A)
    ok = size > 1e-12 * max(float(size.max()), 1e-300)
    weights = np.where(ok, 1.0 / np.where(ok, size, 1.0), 0.0) / np.count_nonzero(ok)
    pts = np.matmul(A, sp._FACE_POINTS_UNIT) + centre[:, :2, None]
    mean = pts.mean(axis=0)
    dev = (pts - mean).reshape(S, 16)
    var = (np.einsum("ij,ij->j", dev, dev) / S).reshape(2, 8).T
    along_x = abs(A[:, 0, 0].sum()) >= abs(A[:, 1, 0].sum())
    x_mid, y_mid = (var[4:6], var[6:8]) if along_x else (var[6:8], var[4:6])
    blur = np.zeros(d)
    blur[0] = np.sqrt(min(float(var[:4, 0].min()), float(x_mid[:, 0].min())))
    blur[1] = np.sqrt(min(float(var[:4, 1].min()), float(y_mid[:, 1].min())))
    z_mean = z_std = None
    if zint is not None:
        z_mean, z_std = zint.mean(axis=0), zint.std(axis=0)
        blur[2] = float(z_std.min())
    return (
        centre[:, :2],
        A,
        zint,
        weights,
        mean[:, :4].T,
        float(np.sqrt(var[:4].sum(axis=1).max())),
        blur,
        z_mean,
        z_std,
    )


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_compiled_sample_statistics_equal_the_numpy_form(model):
    """The one-pass sample kernel gives the NumPy form's sample boxes and boundary statistics bit for
    bit: φ samples of boxes of all sizes and spreads, rotated, with degenerate samples mixed in."""
    rng = np.random.default_rng(11)
    d, p = g.point_dim(model), g.phi_dim(model)
    for trial in range(60):
        box = np.array([*rng.normal(0, 20, 3), *rng.uniform(0.3, 12, 3), rng.uniform(-4, 4)])
        S = int(rng.choice([2, 16, 128, 300]))
        L = rng.normal(size=(p, p)) * 10.0 ** rng.uniform(-4, 0.5)
        phis = g.box_to_phi(box, model) + rng.normal(size=(S, p)) @ L
        if trial % 5 == 0:
            phis[rng.integers(0, S, 1 + S // 4), 2 + (d - 2)] = 0.0  # zero-length samples: dropped
            phis[:, 3 + (d - 2)] *= phis[:, 2 + (d - 2)] != 0
        centres, A, zint, _, weights, corner_mean, corner_std, blur, z_mean, z_std = sp._sample_kernel(phis, d)
        want = _sample_stats_numpy(phis, d)
        got = (
            centres,
            A,
            zint if d == 3 else None,
            weights,
            corner_mean,
            corner_std,
            blur,
            z_mean if d == 3 else None,
            z_std if d == 3 else None,
        )
        for name, a, b in zip(
            ("centres", "A", "z", "weights", "corner_mean", "corner_std", "blur", "z_mean", "z_std"), got, want
        ):
            assert (a is None and b is None) or np.array_equal(np.asarray(a), np.asarray(b)), (trial, name)


def _jaccard_numpy(p, q, c, p_outside=0.0, q_outside=0.0):
    """The NumPy form of jaccard's sums, kept as the bit-exact reference of its compiled kernels."""
    both = (p > 0) & (q > 0)
    if not both.any():
        return 0.0
    p_only = float((c * p)[q == 0].sum()) + float(p_outside)
    q_only = float((c * q)[p == 0].sum()) + float(q_outside)
    pb, qb, cb = p[both], q[both], c[both]
    order = (pb / qb).argsort()
    ps, qs, cs = pb[order], qb[order], cb[order]
    suffix_p = np.cumsum((cs * ps)[::-1])[::-1] + p_only
    prefix_q = np.cumsum(cs * qs) - cs * qs + q_only
    return float((cs / (suffix_p / ps + prefix_q / qs)).sum())


def test_compiled_jaccard_equals_the_numpy_form():
    """jaccard's compiled split and sums (which the BEV JIoU-GT shares) give the NumPy form's value
    bit for bit. Sparse supports, tied ratios, merged cells (counts) and mass outside the listed cells."""
    rng = np.random.default_rng(8)
    for trial in range(80):
        n = int(rng.integers(1, 5000))
        p = rng.exponential(size=n) * (rng.random(n) < rng.uniform(0.2, 1.0))
        q = rng.exponential(size=n) * (rng.random(n) < rng.uniform(0.2, 1.0))
        if trial % 3 == 0:  # many equal cells, as the interior of a raster
            p[rng.random(n) < 0.5] = 0.25
            q[rng.random(n) < 0.5] = 0.5
        c = np.ones(n) if trial % 2 else rng.integers(1, 9, n).astype(float)
        po, qo = (0.0, 0.0) if trial % 4 else tuple(rng.uniform(0, 3, 2))
        want = _jaccard_numpy(p, q, c, po, qo)
        assert sp.jaccard(p, q, c, po, qo) == want, trial


def test_compiled_aligned_raster_and_clean_equal_the_numpy_form():
    """The single aligned box's separable raster and the round-off cleaning equal their NumPy forms."""
    rng = np.random.default_rng(4)

    def overlap(lo, hi, edges):
        return np.clip(np.minimum(hi, edges[1:]) - np.maximum(lo, edges[:-1]), 0.0, None)

    for _ in range(30):
        xe, ye = (
            np.sort(rng.normal(0, 3, int(rng.integers(2, 90)))),
            np.sort(rng.normal(0, 2, int(rng.integers(2, 60)))),
        )
        cx, cy, hx, hy, w = (
            rng.normal(0, 1),
            rng.normal(0, 1),
            rng.uniform(0.1, 3),
            rng.uniform(0.1, 2),
            rng.uniform(0.1, 5),
        )
        want = np.outer(overlap(cy - hy, cy + hy, ye), overlap(cx - hx, cx + hx, xe)) * w
        assert np.array_equal(sp._aligned_kernel(cx, cy, hx, hy, xe, ye, w), want)
        mass = want * (1.0 + rng.normal(0, 1e-11, want.shape)) - 1e-13 * want.max() * rng.random(want.shape)
        ref = mass.copy()
        ref[ref <= 1e-12 * float(ref.max())] = 0.0
        assert np.array_equal(sp._clean(mass), ref)


def _raster_3d_sparse(s, xe, ye, zw):
    """spatial._raster_3d's SciPy sparse form, kept as the bit-exact reference of its kernel."""
    from scipy.sparse import coo_matrix

    e = sp._events(s, xe, ye)
    nb = e.ny * (e.nx + 1)
    S = e.i_lo.shape[0]
    sidx = np.broadcast_to(np.arange(S)[:, None], e.i_lo.shape)[e.valid]
    i_lo, i_hi = e.i_lo[e.valid], e.i_hi[e.valid]
    rows = np.concatenate([i_lo, i_hi, i_hi + nb, i_lo + nb])
    n = len(i_lo)
    vals = np.concatenate([np.full(n, e.dx), np.full(n, -e.dx), e.f_hi[e.valid], -e.f_lo[e.valid]])
    M = coo_matrix((vals, (rows, np.concatenate([sidx] * 4))), shape=(2 * nb, S)).tocsr()
    out = np.asarray(M @ zw).reshape(2, e.ny, e.nx + 1, zw.shape[1])
    return (np.cumsum(out[0], axis=1) + out[1])[:, : e.nx] * e.dy


def test_compiled_3d_raster_equals_the_sparse_form():
    """The 3D raster kernel gives SciPy's sparse product bit for bit: rotated, blurred and thin
    boxes (intervals inside one cell), one or many z columns."""
    assert C.SUBROWS_PER_CELL == 1  # the kernel's case
    rng = np.random.default_rng(12)
    for trial in range(30):
        box = np.array(
            [*rng.normal(0, 2, 3), rng.uniform(0.3, 8), rng.uniform(0.05, 3), rng.uniform(0.5, 3), rng.uniform(-4, 4)]
        )
        ref = np.array([*box[:3], *box[3:6], box[6] + rng.normal(0, 0.3)])
        L = rng.normal(size=(8, 8)) * 10.0 ** rng.uniform(-3, -0.5)
        s = sp.sample_boxes(
            sp.BoxDistribution(box, "3d", L @ L.T), ref, SpatialParams(num_samples=int(rng.choice([16, 128])))
        )
        n = int(rng.integers(4, 90))
        xe = np.linspace(-0.6 * box[3] - 0.3, 0.6 * box[3] + 0.3, n + 1)
        ye = np.linspace(-0.6 * box[4] - 0.3, 0.6 * box[4] + 0.3, int(rng.integers(2, 60)) + 1)
        zw = s.weights[:, None] * rng.uniform(0, 1, (len(s.weights), int(rng.integers(1, 6))))
        got = sp._raster_3d(s, xe, ye, zw)
        assert np.array_equal(got, _raster_3d_sparse(s, xe, ye, zw)), trial


def test_axis_edges_in_python_floats_equal_the_numpy_scalar_form():
    """axis_edges computes in Python floats what it computed on NumPy scalars, bit for bit (also
    when the cell cap applies)."""
    import math

    def numpy_form(half, lo, hi, cell):
        n_box = max(1, int(round(2 * half / cell)))
        step = 2 * half / n_box
        n_lo = max(0, math.ceil((-half - lo) / step - 1e-9))
        n_hi = max(0, math.ceil((hi - half) / step - 1e-9))
        total = n_lo + n_box + n_hi
        if total > C.MAX_CELLS_PER_AXIS:
            lo, hi = min(lo, -half), max(hi, half)
            return np.linspace(lo, hi, C.MAX_CELLS_PER_AXIS + 1)
        return -half - n_lo * step + step * np.arange(total + 1)

    rng = np.random.default_rng(9)
    for _ in range(500):
        half = np.float64(rng.uniform(0.05, 10))
        lo, hi = np.float64(-half - rng.exponential(half)), np.float64(half + rng.exponential(half))
        cell = np.float64(2 * half / rng.uniform(1, 400))
        got, want = sp.axis_edges(half, lo, hi, cell), numpy_form(half, lo, hi, cell)
        assert got.shape == want.shape and np.array_equal(got, want)


@pytest.mark.parametrize("n", [0, 2, 7, 40, 400])
def test_compiled_bev_jiou_gt_equals_the_generic_steps(n):
    """The BEV JIoU-GT's compiled pass (its own symmetric root; NumPy's sort and the shared sums)
    gives the generic steps' value within the last bits, on posteriors of boxes at every yaw, near
    and far, sparse and dense."""
    rng = np.random.default_rng(n)
    params = ModelParams()
    worst = 0.0
    for trial in range(25):
        cx, cy, length, width, yaw = rng.uniform([3, -20, 0.5, 0.4, -4], [60, 20, 12, 3, 4])
        box = np.array([cx, cy, 0.8, length, width, 1.6, yaw])
        faces = [["-x", "-y"], ["+x"], ["-y", "+y", "-x"]][trial % 3]
        post = M.infer_label(box, face_points(box, faces, n, 0.05), "Car", params)
        got, want = sp.jiou_gt(post, SP), sp.jiou_gt_generic(post.box, "bev", np.asarray(post.cov), SP)
        assert 0 < got <= 1
        worst = max(worst, abs(got - want))
    assert worst <= 1e-12


def test_compiled_axis_edges_refuse_non_finite_input():
    with pytest.raises(ValueError, match="must be finite"):
        sp.axis_edges(1.0, -np.inf, 1.0, 0.1)
    with pytest.raises(ValueError, match="cell > 0"):
        sp.axis_edges(1.0, -1.0, 1.0, 0.0)


def test_jaccard_split_merges_equal_neighbours_of_a_row_only():
    """The BEV JIoU-GT's split merges consecutive equal cells of a row into one cell with its count
    (never across rows, never cells that differ), keeps the totals of the unmerged cells, and its
    Jaccard equals the unmerged cells' within the rounding of the sums."""
    p = np.array([[1.0, 1.0, 1.0, 0.5], [1.0, 1.0, 0.0, 1.0], [2.0, 2.0, 2.0, 2.0]]).ravel()
    q = np.array([[0.2, 0.2, 0.2, 0.2], [0.2, 0.2, 0.3, 0.0], [0.1, 0.1, 0.3, 0.1]]).ravel()
    negative, pb, qb, cb, ratio, p_only, q_only = sp._jaccard_split(p, q, np.ones(p.size), 0.0, 0.25, 4)
    assert not negative
    assert cb.tolist() == [3.0, 1.0, 2.0, 2.0, 1.0, 1.0]  # the run ends at the row's end and at 0.5
    assert pb.tolist() == [1.0, 0.5, 1.0, 2.0, 2.0, 2.0] and qb.tolist() == [0.2, 0.2, 0.2, 0.1, 0.3, 0.1]
    assert p_only == 1.0 and q_only == 0.3 + 0.25  # p where q = 0; q where p = 0, plus q outside
    rng = np.random.default_rng(3)
    for _ in range(20):  # rasters with long runs, as the interior of a JIoU-GT raster
        nx = int(rng.integers(2, 30))
        p = np.repeat(rng.choice([0.0, 0.5, 1.0], 60), rng.integers(1, 6, 60))[: 12 * nx]
        q = np.repeat(rng.choice([0.0, 0.2, 0.7], 60), rng.integers(1, 6, 60))[: 12 * nx]
        n = min(len(p), len(q)) // nx * nx
        p, q = p[:n], q[:n]
        merged = sp._jaccard_split(p, q, np.ones(n), 0.0, 0.0, nx)
        plain = sp._jaccard_split(p, q, np.ones(n), 0.0, 0.0, 0)
        assert merged[3].sum() == plain[3].size  # every cell counted once
        assert (merged[1] * merged[3]).sum() == pytest.approx(plain[1].sum(), rel=1e-13)  # and its mass
        assert merged[5:] == plain[5:]
        if plain[1].size:
            want = sp._jaccard_sum(*plain[1:4], plain[4].argsort(), *plain[5:])
            got = sp._jaccard_sum(*merged[1:4], merged[4].argsort(), *merged[5:])
            assert got == pytest.approx(want, rel=1e-13)


def test_ratio_keys_order_the_cells_by_ratio():
    """The BEV JIoU-GT's sort keys (_ratio_keys): sorted, they give back a permutation of the cells
    in the order of their ratios (ties and ratios within the dropped low bits by cell index)."""
    rng = np.random.default_rng(3)
    for n in (1, 2, 7, 990, 5000):
        ratio = np.concatenate([rng.uniform(1e-3, 1e3, n - n // 3), np.full(n // 3, 2.5)])
        rng.shuffle(ratio)
        keys, shift = sp._ratio_keys(ratio)
        assert (1 << shift) >= n > (1 << shift) // 2 or n == 1
        order = np.sort(keys).view(np.int64) & ((1 << shift) - 1)
        assert np.array_equal(np.sort(order), np.arange(n))
        r = ratio[order]
        assert np.all(r[1:] >= r[:-1] * (1.0 - 2.0 ** (shift - 52)))  # by ratio, up to the dropped bits
        tied = order[r == 2.5]
        assert np.all(np.diff(tied) > 0)  # equal ratios: by cell
