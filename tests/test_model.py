"""Core model: golden worked example, registration, prior, posterior, noise EM, corner variance."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from _core_synth import face_points, rigid_motion
from labelaudit import constants as C
from labelaudit.config import ClassPrior, ModelParams
from labelaudit.core import fit as LF
from labelaudit.core import geometry as g
from labelaudit.core import iou as IOU
from labelaudit.core import linalg
from labelaudit.core import posterior as M

CAR = np.array([15.0, 5.0, 0.75, 4.2, 1.7, 1.5, 0.0])  # near faces seen from the origin: −x and −y

# The paper's worked example (docs/method.md §4): y = (x_min, y_min, l, w); each point observes one corner.
GOLDEN_J = np.array(
    [
        [[1, 0, 1, 0], [0, 1, 0, 0]],  # (x_min + l, y_min)      observed at (1.8, 0)
        [[1, 0, 1, 0], [0, 1, 0, 1]],  # (x_min + l, y_min + w)  observed at (1.8, 0.9)
        [[1, 0, 0, 0], [0, 1, 0, 1]],  # (x_min, y_min + w)      observed at (0, 0.9)
    ],
    dtype=float,
)
GOLDEN_X = np.array([[1.8, 0.0], [1.8, 0.9], [0.0, 0.9]])
GOLDEN_COV = np.array([[0.04, 0, -0.04, 0], [0, 0.04, 0, -0.04], [-0.04, 0, 0.06, 0], [0, -0.04, 0, 0.06]])


# ---------------------------------------------------------------------------------------------
# golden example
# ---------------------------------------------------------------------------------------------


def test_golden_example_flat_prior_is_exact():
    mean, cov, _ = M.linear_gaussian_posterior(GOLDEN_J, GOLDEN_X, 0.2, np.zeros(4), prior_precision=np.zeros((4, 4)))
    assert np.max(np.abs(cov - GOLDEN_COV)) < 1e-9
    assert np.allclose(mean, [0, 0, 1.8, 0.9], atol=1e-9)


def test_golden_example_with_vague_prior():
    # Prior std 1e6: the prior's pull is ~1e-14, far below 1e-9.
    _, cov, _ = M.linear_gaussian_posterior(GOLDEN_J, GOLDEN_X, 0.2, np.zeros(4), prior_cov=np.eye(4) * 1e12)
    assert np.max(np.abs(cov - GOLDEN_COV)) < 1e-9
    eig_std = np.sqrt(np.linalg.eigvalsh(cov))
    assert np.allclose(np.unique(np.round(eig_std, 3)), [0.094, 0.302])


def test_golden_example_paper_prior_std_100():
    # With the paper's prior std 100 the printed (2-decimal) matrix holds to ~5e-7: the prior adds
    # 1e-4 to the precision, which moves the covariance by 1e-4 · Σ² ≈ 5e-7.
    _, cov, _ = M.linear_gaussian_posterior(GOLDEN_J, GOLDEN_X, 0.2, np.zeros(4), prior_cov=np.eye(4) * 100.0**2)
    assert np.max(np.abs(cov - GOLDEN_COV)) < 1e-6
    expected = GOLDEN_COV - 1e-4 * GOLDEN_COV @ GOLDEN_COV  # first-order correction
    assert np.max(np.abs(cov - expected)) < 1e-9
    assert np.allclose(np.unique(np.round(np.sqrt(np.linalg.eigvalsh(cov)), 3)), [0.094, 0.302])


def test_posterior_needs_one_prior_and_a_proper_result():
    with pytest.raises(ValueError):
        M.linear_gaussian_posterior(GOLDEN_J, GOLDEN_X, 0.2, np.zeros(4))
    with pytest.raises(ValueError, match="positive definite"):
        M.linear_gaussian_posterior(GOLDEN_J[:1], GOLDEN_X[:1], 0.2, np.zeros(4), prior_precision=np.zeros((4, 4)))


# ---------------------------------------------------------------------------------------------
# registration
# ---------------------------------------------------------------------------------------------


def _dense_surface(box, model, step=0.002):
    """Brute-force surface sampling in the box frame (metres)."""
    d = g.point_dim(model)
    half = np.asarray(box[3 : 3 + d]) / 2
    pts = []
    for a in range(d):
        others = [i for i in range(d) if i != a]
        grids = np.meshgrid(*[np.arange(-half[i], half[i] + step / 2, step) for i in others], indexing="ij")
        for sign in (-1, 1):
            p = np.zeros((grids[0].size, d))
            p[:, a] = sign * half[a]
            for i, gr in zip(others, grids):
                p[:, i] = gr.ravel()
            pts.append(p)
    return np.vstack(pts)


def test_registration_nearest_point_matches_brute_force_bev():
    box = np.array([1.0, -2.0, 0.0, 4.0, 1.6, 1.5, 0.4])
    rng = np.random.default_rng(3)
    pts = g.unit_to_world(rng.uniform(-0.9, 0.9, (200, 2)), box, "bev")
    reg = M.register(box, pts, "bev", num_nearest=3, sigma=0.2)
    surf = _dense_surface(box, "bev")
    local = g.world_to_unit(pts, box, "bev") * box[3:5]
    brute = np.min(np.sum((local[:, None, :] - surf[None]) ** 2, axis=-1), axis=1)
    assert np.allclose(reg.sqdist[:, 0], brute, atol=2e-3 * np.sqrt(brute + 1e-6) + 1e-6)
    # candidates lie on the surface (one unit coordinate at ±½, the others inside)
    v = reg.vstar
    assert np.all(np.abs(v) <= 0.5 + 1e-12)
    assert np.all(np.isclose(np.max(np.abs(v), axis=-1), 0.5))


def test_registration_nearest_point_matches_brute_force_3d():
    box = np.array([0.0, 0.0, 1.0, 3.0, 1.5, 1.2, -0.7])
    rng = np.random.default_rng(4)
    pts = g.unit_to_world(rng.uniform(-0.9, 0.9, (60, 3)), box, "3d")
    reg = M.register(box, pts, "3d", num_nearest=3)
    surf = _dense_surface(box, "3d", step=0.02)
    local = g.world_to_unit(pts, box, "3d") * box[3:6]
    brute = np.min(np.sum((local[:, None, :] - surf[None]) ** 2, axis=-1), axis=1)
    assert np.all(reg.sqdist[:, 0] <= brute + 1e-12)  # exact nearest is never farther than a sampled one
    assert np.allclose(np.sqrt(reg.sqdist[:, 0]), np.sqrt(brute), atol=0.02)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_registration_candidates_are_distinct_and_sorted(model):
    box = np.array([0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.3])
    d = g.point_dim(model)
    # points outside a corner (where two faces clamp to the same corner), inside, and on an edge
    v = np.array([[0.8, 0.9, 0.7], [0.1, -0.2, 0.0], [0.5, 0.5, 0.0], [-0.7, 0.2, 0.1]])[:, :d]
    pts = g.unit_to_world(v, box, model)
    reg = M.register(box, pts, model, num_nearest=3)
    for row_v, row_d in zip(reg.vstar, reg.sqdist):
        finite = np.isfinite(row_d)
        cand = row_v[finite]
        assert len({tuple(np.round(c, 9)) for c in cand}) == len(cand)
        assert np.all(np.diff(row_d[finite]) >= -1e-12)
    assert np.allclose(reg.resp.sum(axis=1), 1.0)


def test_registration_caps_m_at_the_number_of_faces():
    box = np.array([0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0])
    reg = M.register(box, [[0.1, 0.2]], "bev", num_nearest=10)
    assert reg.vstar.shape == (1, 4, 2)


def test_outlier_term_downweights_far_points():
    box = np.array([0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0])
    pts = np.array([[2.0, 0.0], [6.0, 0.0]])  # on the +x face, and 4 m outside it
    plain = M.register(box, pts, "bev", sigma=0.2, outlier_prob=0.0)
    robust = M.register(box, pts, "bev", sigma=0.2, outlier_prob=0.05)
    assert np.allclose(plain.resp.sum(axis=1), 1.0)
    assert robust.resp[0].sum() > 0.99
    assert robust.resp[1].sum() < 1e-6


# ---------------------------------------------------------------------------------------------
# prior and posterior
# ---------------------------------------------------------------------------------------------


def test_prior_covariance_and_precision_are_inverse_and_match_the_class_std():
    prior = ClassPrior(center=0.25, length=0.44, width=0.11, height=0.13, yaw=0.17)
    for model in ("bev", "3d"):
        S0 = M.prior_covariance(CAR, prior, 2.0, model)
        P0 = M.prior_precision(CAR, prior, 2.0, model)
        assert np.allclose(S0 @ P0, np.eye(len(S0)), atol=1e-9)
        std = M.box_std(CAR, S0, model)
        # w divides the variance: std / sqrt(2)
        assert std["cx"] == pytest.approx(0.25 / np.sqrt(2))
        assert std["length"] == pytest.approx(0.44 / np.sqrt(2))
        assert std["width"] == pytest.approx(0.11 / np.sqrt(2))
        assert std["yaw"] == pytest.approx(0.17 / np.sqrt(2))
        if model == "3d":
            assert std["height"] == pytest.approx(0.13 / np.sqrt(2))
            assert std["cz"] == pytest.approx(0.25 / np.sqrt(2))
        else:
            assert np.isnan(std["cz"]) and np.isnan(std["height"])


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_zero_points_gives_the_prior(model):
    params = ModelParams(kind=model)
    post = M.infer_label(CAR, np.zeros((0, 3)), "Car", params)
    assert post.num_points == 0
    assert np.isnan(post.sigma_hat)
    assert np.allclose(post.cov, post.prior_cov, rtol=1e-9, atol=1e-12)
    prior = params.prior_for("Car")  # w = 1: the reported stds are the class prior's own
    assert post.std_box["cx"] == pytest.approx(prior.center)
    assert post.std_box["length"] == pytest.approx(prior.length)
    assert post.std_box["width"] == pytest.approx(prior.width)
    assert post.std_box["yaw"] == pytest.approx(prior.yaw)


def _assert_spd(cov):
    assert np.all(np.isfinite(cov))
    assert np.allclose(cov, cov.T, atol=0)
    assert np.min(np.linalg.eigvalsh(cov)) > 0


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_covariances_are_spd_and_finite_for_degenerate_inputs(model):
    params = ModelParams(kind=model)
    cases = {
        "normal": (CAR, face_points(CAR, ["-x", "-y"], 100, 0.03)),
        "one spot": (CAR, np.tile([[13.0, 4.0, 0.8]], (50, 1))),
        "far outside": (CAR, np.array([[100.0, -50.0, 3.0], [-80.0, 40.0, -2.0], [15.0, 5.0, 40.0]])),
        "single point": (CAR, np.array([[13.0, 5.0, 0.7]])),
        "tiny box": (np.array([1.0, 1.0, 0.0, 1e-3, 1e-3, 1e-3, 0.2]), np.array([[1.0, 1.0, 0.0], [1.0005, 1.0, 0.0]])),
        "huge box": (
            np.array([0.0, 0.0, 0.0, 1e3, 5e2, 1e2, 1.0]),
            face_points([0, 0, 0, 1e3, 5e2, 1e2, 1.0], ["+x"], 50),
        ),
        "nan rows": (CAR, np.array([[13.0, 4.0, 0.8], [np.nan, 1.0, 1.0], [13.0, 5.0, np.inf]])),
    }
    for name, (box, pts) in cases.items():
        post = M.infer_label(box, pts, "Car", params)
        _assert_spd(post.cov)
        assert np.all(np.isfinite(post.corner_tv)), name
        assert all(np.isfinite(v) for k, v in post.std_box.items() if model == "3d" or k not in ("cz", "height")), name
    # BEV uses x, y only: the row with z = inf still counts there
    assert M.infer_label(CAR, cases["nan rows"][1], "Car", params).num_points == (2 if model == "bev" else 1)


@pytest.mark.parametrize(
    "bad", [[0, 0, 0, 0.0, 1, 1, 0], [0, 0, 0, 4, -1, 1, 0], [0, np.nan, 0, 4, 2, 1, 0], [0, 0, 0, 4, 2, 1, np.inf]]
)
def test_invalid_box_raises(bad):
    with pytest.raises(ValueError):
        M.infer_label(bad, np.zeros((3, 3)), "Car", ModelParams())


def test_malformed_points_raise():
    with pytest.raises(ValueError, match="points"):
        M.infer_label(CAR, np.zeros((3, 1)), "Car", ModelParams())


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_more_points_shrink_the_covariance(model):
    params = ModelParams(kind=model)
    few = M.infer_label(CAR, face_points(CAR, ["-x", "-y"], 5, 0.03), "Car", params)
    many = M.infer_label(CAR, face_points(CAR, ["-x", "-y"], 200, 0.03), "Car", params)
    assert np.trace(many.cov) < np.trace(few.cov) < np.trace(few.prior_cov)
    assert np.all(many.corner_tv < few.corner_tv)


# ---------------------------------------------------------------------------------------------
# corners
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_l_shape_nearest_corner_has_least_variance(model):
    pts = face_points(CAR, ["-x", "-y"], 150, 0.03)  # the two faces the sensor at the origin sees
    post = M.infer_label(CAR, pts, "Car", ModelParams(kind=model))
    # C1 is the corner nearest the sensor: unit (−½, −½), index 2 in box_corners' order
    assert post.corner_order[0] == 2
    corners = g.box_corners(CAR, "bev")[post.corner_order]
    assert np.all(np.diff(np.linalg.norm(corners, axis=1)) >= 0)
    assert post.corner_tv[0] < post.corner_tv[3]
    assert post.corner_tv[0] == pytest.approx(np.min(post.corner_tv))


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_corner_tv_and_std_are_invariant_to_rigid_motion(model):
    pts = face_points(CAR, ["-x", "-y"], 80, 0.03)
    params = ModelParams(kind=model)
    base = M.infer_label(CAR, pts, "Car", params)
    for yaw, shift in ((0.9, (3.0, -7.0, 0.5)), (-2.5, (-40.0, 12.0, -1.0))):
        b2, p2, o2 = rigid_motion(CAR, pts, yaw, shift)
        moved = M.infer_label(b2, p2, "Car", params, sensor_origin=o2)
        assert np.allclose(moved.corner_tv, base.corner_tv, rtol=1e-6, atol=1e-12)
        for k in ("length", "width", "yaw"):
            assert moved.std_box[k] == pytest.approx(base.std_box[k], rel=1e-6)


# ---------------------------------------------------------------------------------------------
# noise EM
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_em_recovers_the_noise_level(model):
    for true in (0.03, 0.1):
        pts = face_points(CAR, ["-x", "-y", "+x", "+y"], 400, true, seed=7)
        est = M.estimate_sigma(CAR, pts, model)
        assert est == pytest.approx(true, rel=0.15)
        post = M.infer_label(CAR, pts, "Car", ModelParams(kind=model))
        assert post.sigma_hat == pytest.approx(est, rel=1e-3)


def test_em_sigma_grows_when_the_label_is_off():
    pts = face_points(CAR, ["-x", "-y"], 200, 0.03)
    good = M.estimate_sigma(CAR, pts, "bev")
    off = CAR.copy()
    off[0] += 0.5
    bad = M.estimate_sigma(off, pts, "bev")
    assert bad > 3 * good


def test_dataset_sigma_pools_objects():
    rng = np.random.default_rng(0)
    objs = []
    for i in range(8):
        box = np.array([10.0 + 5 * i, rng.uniform(-5, 5), 0.8, 4.0, 1.8, 1.5, rng.uniform(-3, 3)])
        objs.append((box, face_points(box, ["-x", "+y"], int(rng.integers(5, 60)), 0.08, seed=i)))
    est = M.estimate_sigma_dataset(objs, "bev")
    assert est == pytest.approx(0.08, rel=0.15)
    assert np.isnan(M.estimate_sigma_dataset([(CAR, np.zeros((0, 3)))], "bev"))


def test_sigma_hat_is_nan_below_two_points():
    assert np.isnan(M.infer_label(CAR, [[13.0, 4.0, 0.8]], "Car", ModelParams()).sigma_hat)
    assert np.isnan(M.estimate_sigma(CAR, [[13.0, 4.0, 0.8]], "bev"))


def test_estimate_sigma_option_uses_the_fit_residual():
    pts = face_points(CAR, ["-x", "-y"], 200, 0.05)
    fixed = M.infer_label(CAR, pts, "Car", ModelParams(sigma=0.2))
    est = M.infer_label(CAR, pts, "Car", ModelParams(sigma=0.2, estimate_sigma=True))
    assert est.sigma == pytest.approx(est.sigma_hat)
    assert est.sigma < fixed.sigma
    assert np.trace(est.cov) < np.trace(fixed.cov)  # smaller noise → more confident


def test_unknown_class_uses_the_default_prior():
    params = ModelParams()
    a = M.infer_label(CAR, None, "Tram", params)
    b = M.infer_label(CAR, None, "Car", dataclasses.replace(params))
    assert np.allclose(a.cov, b.cov)


# ---------------------------------------------------------------------------------------------
# audit_object (the per-object entry point of the pipeline)
# ---------------------------------------------------------------------------------------------

from labelaudit.config import load_config  # noqa: E402
from labelaudit.infer.rows import audit_object  # noqa: E402
from labelaudit.results import MODEL_COLUMNS  # noqa: E402


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_audit_object_row(model):
    cfg = load_config(None, "kitti")
    cfg = cfg.with_overrides(model=dataclasses.replace(cfg.model, kind=model))
    row = audit_object(CAR, face_points(CAR, ["-x", "-y"], 100, 0.03), "Car", cfg, (0.0, 0.0, 0.0))
    assert set(row) == set(MODEL_COLUMNS)  # a row's model columns are defined once, in labelaudit/results.py
    assert row["status"] == "ok" and row["num_points"] == 200
    assert row["model"] == model
    p = 6 if model == "bev" else 8
    assert row["cov_dim"] == p and len(row["cov"]) == p * p
    cov = np.array(row["cov"]).reshape(p, p)
    _assert_spd(cov)
    assert len(row["corner_tv"]) == 4 and row["corner_tv"][0] < row["corner_tv"][3]
    assert 0.5 < row["jiou_gt"] < 1.0
    assert row["sigma"] == 0.2 and 0 < row["sigma_hat"] < 0.1
    assert 0.0 <= row["label_error"] < 0.1 and row["fit_offset_m"] < 0.05  # the label is exact
    assert row["fit_length"] == pytest.approx(CAR[3], abs=0.05) and np.isfinite(row["fit_cz"])
    assert 0.0 < row["hull_iou"] < 1.0 and row["mahalanobis"] >= 0.0
    assert np.isnan(row["std_cz"]) == (model == "bev")
    assert all(isinstance(row[k], float) for k in ("std_cx", "std_length", "std_yaw", "jiou_gt"))


def test_audit_object_status_by_point_count():
    cfg = load_config(None, "kitti")
    empty = audit_object(CAR, np.zeros((0, 4)), "Car", cfg)
    assert empty["status"] == "no_points" and empty["num_points"] == 0
    assert 0 < empty["jiou_gt"] < 1 and np.isnan(empty["sigma_hat"])
    assert audit_object(CAR, None, "Car", cfg)["jiou_gt"] == empty["jiou_gt"]
    few = audit_object(CAR, face_points(CAR, ["-x"], 2), "Car", cfg)
    assert few["status"] == "few_points"
    assert few["jiou_gt"] > empty["jiou_gt"]
    with pytest.raises(ValueError, match="width"):
        audit_object([0, 0, 0, 4, 0, 1, 0], None, "Car", cfg)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_moment_form_equals_the_generic_posterior(model):
    # infer_label builds Σ r JᵀJ from moments of v*; it must equal the generic posterior on J(v*).
    pts = face_points(CAR, ["-x", "-y", "+z"], 40, 0.05)
    params = ModelParams(kind=model)
    post = M.infer_label(CAR, pts, "Car", params)
    d = g.point_dim(model)
    reg = M.register(CAR, pts, model, num_nearest=params.num_nearest, sigma=params.sigma)
    m = reg.vstar.shape[1]
    J = g.design_matrix(reg.vstar.reshape(-1, d), model)
    mean, cov, _ = M.linear_gaussian_posterior(
        J,
        np.repeat(reg.points, m, axis=0),
        params.sigma,
        post.phi,
        prior_precision=M.prior_precision(CAR, params.prior_for("Car"), params.prior_weight, model),
        weights=reg.resp.reshape(-1),
    )
    assert np.allclose(post.cov, cov, rtol=1e-9, atol=1e-14)
    assert np.allclose(post.fit_mean, mean, rtol=1e-9, atol=1e-9)


# ---------------------------------------------------------------------------------------------
# label error: suggested box, offsets, score, symmetries, hull baseline
# ---------------------------------------------------------------------------------------------

ALL_SIDES = ["-x", "+x", "-y", "+y", "+z", "-z"]


def _shifted(box, **delta):
    out = np.asarray(box, dtype=float).copy()
    for name, value in delta.items():
        out[g.BOX_FIELDS.index(name)] += value
    return out


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_label_error_orders_exact_slight_bad(model):
    pts = face_points(CAR, ["-x", "-y"], 150, 0.03)
    params = ModelParams(kind=model)
    scores = [
        LF.fit_label(b, pts, "Car", params).label_error
        for b in (CAR, _shifted(CAR, cx=0.15), _shifted(CAR, cx=0.5, cy=0.3))
    ]
    assert scores[0] < scores[1] < scores[2]
    assert scores[0] < 0.05 and scores[2] > 0.99
    for bad in (_shifted(CAR, yaw=0.15), _shifted(CAR, cy=0.4)):
        assert LF.fit_label(bad, pts, "Car", params).label_error > 0.9
    # The same 0.4 m towards the seen −y face leaves its points 0.4 m *inside* the label: without
    # rays that is a loose label (surfaces lie inside their boxes), not an error — the points
    # outside (the −x face's end) pull it only part of the way. Free-space rays tell the two apart
    # (tests/test_freespace.py).
    loose = LF.fit_label(_shifted(CAR, cy=-0.4), pts, "Car", params).label_error
    assert loose < LF.fit_label(_shifted(CAR, cy=0.4), pts, "Car", params).label_error


def test_suggested_box_recovers_a_known_perturbation():
    # A label inside its points on every face (smaller, shifted, turned and lower than the car):
    # every point is outside it, so every face is pulled out to its points. (Faces *beyond* their
    # points are moved only by free-space rays: deep points fix the orientation of their face, they
    # never pull it in — docs/label-error.md.)
    pts = face_points(CAR, ALL_SIDES, 200, 0.03, seed=1)
    label = _shifted(CAR, cx=0.2, cy=-0.1, cz=0.04, length=-0.5, width=-0.3, height=-0.2, yaw=0.03)
    fit = LF.fit_label(label, pts, "Car", ModelParams())
    assert fit.converged
    assert np.allclose(fit.box[:6], CAR[:6], atol=0.03)
    assert abs(g.normalize_angle(fit.box[6] - CAR[6])) < 0.01
    assert fit.offset_m == pytest.approx(np.linalg.norm(label[:3] - fit.box[:3]))
    assert fit.offsets["cx"] == pytest.approx(-0.2, abs=0.03)
    assert fit.label_error > 0.99 and fit.mahalanobis > 10


def test_deep_points_fix_the_orientation_but_never_pull_a_face_in():
    # A loose label (0.3 m beyond the car's seen faces, turned by 0.06 rad): the seen faces' points
    # lie deep inside it. They turn the fit back to the car's heading …
    pts = face_points(CAR, ["-x", "-y"], 200, 0.02, seed=2)
    loose = _shifted(CAR, cx=-0.15, cy=-0.15, length=0.3, width=0.3, yaw=0.06)
    fit = LF.fit_label(loose, pts, "Car", ModelParams())
    assert abs(g.normalize_angle(fit.box[6] - CAR[6])) < 0.02
    # … but the faces stay where the label put them (a loose label is not an error)
    assert fit.box[3] == pytest.approx(loose[3], abs=0.05) and fit.box[4] == pytest.approx(loose[4], abs=0.05)


@pytest.mark.parametrize("n", [0, 1, 2, 3])
def test_sparse_correct_labels_are_not_false_alarms(n):
    rng = np.random.default_rng(n)
    for seed in range(10):
        pts = face_points(CAR, ["-x", "-y"], 10, 0.05, seed=seed)[rng.choice(20, n, replace=False)]
        fit = LF.fit_label(CAR, pts, "Car", ModelParams())
        assert fit.label_error < 0.1
    # a sparse wrong label scores lower than the same error on a dense box: low confidence
    wrong = _shifted(CAR, cx=0.5, cy=0.3)
    sparse = LF.fit_label(wrong, face_points(CAR, ["-x", "-y"], 10, 0.05)[:n], "Car", ModelParams())
    dense = LF.fit_label(wrong, face_points(CAR, ["-x", "-y"], 100, 0.05), "Car", ModelParams())
    assert sparse.label_error < dense.label_error
    if n == 0:
        assert sparse.label_error < 1e-9 and sparse.offset_m < 1e-9 and np.isnan(sparse.sigma_hat)


def test_symmetric_forms_of_the_same_rectangle_are_not_errors():
    pts = face_points(CAR, ["-x", "-y", "+z"], 150, 0.03)
    base = LF.fit_label(CAR, pts, "Car", ModelParams())
    flipped = _shifted(CAR, yaw=np.pi)  # heading reversed: same rectangle
    turned = CAR.copy()
    turned[3], turned[4], turned[6] = CAR[4], CAR[3], CAR[6] + np.pi / 2  # l/w swapped and turned 90°
    for label in (flipped, turned):
        fit = LF.fit_label(label, pts, "Car", ModelParams())
        assert fit.label_error == pytest.approx(base.label_error, abs=0.02)
        assert abs(g.normalize_angle(fit.box[6] - label[6])) < 0.05  # reported in the label's form
        assert fit.box[3] == pytest.approx(label[3], abs=0.1)


def test_swapped_length_and_width_is_an_error():
    pts = face_points(CAR, ["-x", "-y", "+z"], 150, 0.03)
    swapped = CAR.copy()
    swapped[3], swapped[4] = CAR[4], CAR[3]
    fit = LF.fit_label(swapped, pts, "Car", ModelParams())
    assert fit.label_error > 0.99
    ninety = _shifted(CAR, yaw=np.pi / 2)
    assert LF.fit_label(ninety, pts, "Car", ModelParams()).label_error > 0.99


def test_fit_without_z_is_bev():
    pts = face_points(CAR, ["-x", "-y"], 100, 0.03)[:, :2]
    fit = LF.fit_label(_shifted(CAR, cx=0.3), pts, "Car", ModelParams())
    assert fit.model == "bev" and np.isnan(fit.offsets["cz"])
    # the seen −x face goes back to its points; the unseen +x face is held by the prior
    assert fit.box[0] - fit.box[3] / 2 == pytest.approx(CAR[0] - CAR[3] / 2, abs=0.03)
    assert fit.label_error > 0.5


def test_hull_iou_equals_qhull_and_shapely():
    """The compiled hull/clip/area equals the SciPy (Qhull) hull intersected by Shapely."""
    from scipy.spatial import ConvexHull
    from shapely.geometry import Polygon

    rng = np.random.default_rng(11)
    for trial in range(200):
        box = np.array(
            [
                rng.uniform(-40, 40),
                rng.uniform(-40, 40),
                0.8,
                rng.uniform(1, 8),
                rng.uniform(0.5, 3),
                1.5,
                rng.uniform(-4, 4),
            ]
        )
        n = int(rng.integers(3, 150))
        spread = [0.5, 0.7, 1.5][trial % 3]  # inside, around, mostly outside the box
        pts = g.unit_to_world(rng.uniform(-spread, spread, (n, 3)) + [0.4 * (trial % 2), 0, 0], box, "3d")
        xy = pts[:, :2]
        hull = Polygon(xy[ConvexHull(xy).vertices])
        rect = Polygon(g.box_corners(box, "bev"))
        inter = hull.intersection(rect).area
        expected = inter / (hull.area + rect.area - inter)
        assert IOU.hull_iou(box, pts) == pytest.approx(expected, rel=1e-10, abs=1e-12), trial


def test_hull_iou_corners_as_numpy():
    """The hull kernel's box corners are NumPy's ``J @ φ − centre`` bit for bit (boxes of every
    heading, size and place, and exact zeros)."""
    rng = np.random.default_rng(5)
    boxes = [np.array([0.0, -0.0, 0.0, 4.0, 2.0, 1.5, 0.0]), np.array([-3.0, 2.0, 0.0, 1.0, 1.0, 1.0, np.pi / 2])]
    for _ in range(2000):
        boxes.append(
            np.array(
                [
                    rng.uniform(-90, 90),
                    rng.uniform(-90, 90),
                    0.0,
                    rng.uniform(0.2, 15),
                    rng.uniform(0.2, 4),
                    1.5,
                    rng.uniform(-7, 7),
                ]
            )
        )
    for box in boxes:
        phi = g.phi_of_valid_box(box, "bev")
        expected = IOU._BEV_CORNER_J @ phi - box[:2]
        got = IOU._local_corners(IOU._BEV_CORNER_J, phi, float(box[0]), float(box[1]))
        assert np.array_equal(got.view(np.int64), expected.view(np.int64)), box


def test_hull_iou_baseline():
    rng = np.random.default_rng(0)
    inside = g.unit_to_world(rng.uniform(-0.5, 0.5, (500, 2)), CAR, "bev")
    assert IOU.hull_iou(CAR, inside) > 0.95
    assert (
        IOU.hull_iou(_shifted(CAR, cx=1.0), inside)
        < IOU.hull_iou(_shifted(CAR, cx=0.2), inside)
        < IOU.hull_iou(CAR, inside)
    )
    assert IOU.hull_iou(CAR, inside[:2]) == 0.0
    assert IOU.hull_iou(CAR, np.c_[np.linspace(13, 17, 5), np.full(5, 5.0)]) == 0.0  # collinear
    assert IOU.hull_iou(CAR, None) == 0.0


def test_audit_object_can_fit_on_a_wider_crop():
    cfg = load_config(None, "kitti")
    pts = face_points(CAR, ["-x", "-y", "+z"], 100, 0.03)
    label = _shifted(CAR, cy=0.6)  # shifted away: its own tight crop misses the −y face points
    tight = pts[np.all(np.abs(g.world_to_unit(pts, label, "3d") * label[3:6]) <= label[3:6] / 2 + 0.1, axis=1)]
    own = audit_object(label, tight, "Car", cfg)
    wide = audit_object(label, tight, "Car", cfg, fit_points=pts)
    assert wide["label_error"] > own["label_error"]
    assert wide["label_error"] > 0.99
    assert wide["num_points"] == own["num_points"] == len(tight)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_plane_rows_are_design_matrix_rows_along_the_normal(model):
    # the fit's hand-written rows a = J(v*)ᵀ n must match geometry.design_matrix
    d = g.point_dim(model)
    pts = face_points(CAR, ["-x", "+y", "+z"], 20, 0.2, seed=3)[:, :d]
    a, b, sqd = LF._plane_rows(CAR, pts, model)
    reg = M.register(CAR, pts, model, num_nearest=1)
    J = g.design_matrix(reg.vstar[:, 0, :], model)  # (N, d, p)
    phi = g.box_to_phi(CAR, model)
    resid = pts - J @ phi
    n = resid / np.linalg.norm(resid, axis=1, keepdims=True)
    u = np.einsum("kdp,kd->kp", J, n)
    w = np.sum(a * u, axis=1) / np.sum(u * u, axis=1)  # per-row weight (deep inside points count less)
    assert np.all((w > 0) & (w <= 1))
    assert np.allclose(a, w[:, None] * u, atol=1e-9)
    assert np.allclose(b, w * np.sum(n * pts, axis=1))
    assert np.allclose(sqd, reg.sqdist[:, 0])


def _surface_candidates(local: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest point on every face of an axis-aligned box centred at 0.

    Parameters
    ----------
    local : (N, d) points in the box frame (metres).
    half : (d,) half sizes.

    Returns
    -------
    cand : (N, 2d, d) nearest point on each face (faces ordered -x, +x, -y, +y[, -z, +z]).
    sqdist : (N, 2d) squared distances.
    """
    local = np.asarray(local, dtype=float)
    half = np.asarray(half, dtype=float)
    n, d = local.shape
    clamped = np.clip(local, -half, half)
    cand = np.repeat(clamped[:, None, :], 2 * d, axis=1)
    for a in range(d):
        cand[:, 2 * a, a] = -half[a]
        cand[:, 2 * a + 1, a] = half[a]
    sqdist = np.sum((local[:, None, :] - cand) ** 2, axis=-1)
    return cand, sqdist


def _nearest_distinct(
    local: np.ndarray, half: np.ndarray, cand: np.ndarray, sqdist: np.ndarray, m: int
) -> tuple[np.ndarray, np.ndarray]:
    """Keep the m nearest *distinct* face candidates per point (reference for ``model._nearest_faces``).

    Two faces give the same candidate exactly when the point lies outside (or on) both of them:
    then both clamp to the same edge/corner point. Of the faces a point is outside of, only the
    first is kept.
    """
    n, f, d = cand.shape
    outside = np.empty((n, f), dtype=bool)
    tol = 1e-9 * float(np.max(half))  # points on an edge up to round-off count as on both faces
    outside[:, 0::2] = local <= -half + tol
    outside[:, 1::2] = local >= half - tol
    sqdist = np.where(outside & (np.cumsum(outside, axis=1) > 1), np.inf, sqdist)
    order = np.argsort(sqdist, axis=1, kind="stable")[:, :m]
    return np.take_along_axis(cand, order[:, :, None], axis=1), np.take_along_axis(sqdist, order, axis=1)


@pytest.mark.parametrize("d", [2, 3])
def test_fast_nearest_faces_match_the_reference(d):
    rng = np.random.default_rng(5)
    half = np.array([2.1, 0.85, 0.75])[:d]
    local = rng.uniform(-1.5, 1.5, (400, d)) * half
    local[:20] = np.sign(local[:20]) * half  # exactly on edges / corners
    for m in range(1, 2 * d + 1):
        cand, sqd = _surface_candidates(local, half)
        ref_c, ref_d = _nearest_distinct(local, half, cand, sqd, m)
        vstar, fast_d = M._nearest_faces(local, half, m)
        assert np.array_equal(np.isinf(fast_d), np.isinf(ref_d))
        fin = np.isfinite(ref_d)
        assert np.allclose(fast_d[fin], ref_d[fin], atol=1e-12)
        assert np.allclose((vstar * 2 * half)[fin], ref_c[fin], atol=1e-12)


def test_fit_sigma_hat_is_the_em_residual_at_the_suggested_box():
    pts = face_points(CAR, ["-x", "-y", "+z"], 60, 0.04, seed=2)
    fit = LF.fit_label(_shifted(CAR, cx=0.2), pts, "Car", ModelParams())
    assert fit.sigma_hat == pytest.approx(M.estimate_sigma(fit.box, pts, "3d"), rel=1e-12)
    assert np.isnan(LF.fit_label(CAR, pts[:1], "Car", ModelParams()).sigma_hat)


def test_hull_candidates_keep_every_hull_vertex():
    from scipy.spatial import ConvexHull

    rng = np.random.default_rng(4)
    clouds = [
        rng.normal(size=(500, 2)),
        g.unit_to_world(rng.uniform(-0.5, 0.5, (300, 2)), CAR, "bev"),
        np.stack(np.meshgrid(np.arange(10.0), np.arange(7.0)), -1).reshape(-1, 2),  # many points on hull edges
        face_points(CAR, ["-x", "-y"], 100, 0.02)[:, :2],  # an L-shape
    ]
    for pts in clouds:
        kept = IOU._hull_candidates(pts)
        assert len(kept) < len(pts)
        full = pts[ConvexHull(pts).vertices]
        assert {tuple(p) for p in full} <= {tuple(p) for p in kept}
        assert ConvexHull(kept).volume == pytest.approx(ConvexHull(pts).volume, rel=1e-12)


def test_sorted_hull_candidates_kernel_equals_numpy_form():
    """The compiled candidates pass (finite rows, Akl–Toussaint filter, order by x then y relative
    to the centre) gives the NumPy form's array bit for bit, float32 input, ties and ±0 included."""
    rng = np.random.default_rng(7)
    centre = (1.0, 2.0)
    for n in (0, 1, 3, 7, 8, 9, 40, 300):
        for variant in range(5):
            pts = rng.normal(size=(n, 4)) * 2.0 + [1.0, 2.0, 0.0, 0.0]
            if variant == 1:
                pts = np.round(pts, 1)  # many ties in x and in (x, y)
            elif variant == 2 and n > 2:
                pts[rng.integers(0, n, 2), rng.integers(0, 2, 2)] = np.nan
            elif variant == 3 and n:
                pts[:, 0] = 1.0  # on a line: local x = 0 for all
            elif variant == 4 and n:
                pts[::2, 0] = 1.0  # half the points share local x = 0 (runs of equal x)
            for arr in (pts, pts.astype(np.float32)):
                local = IOU._hull_candidates(g.clean_points(arr, 2)) - centre
                ref = local[np.lexsort((local[:, 1], local[:, 0]))]
                got = IOU._sorted_candidates_kernel(arr, *centre)
                assert got.shape == ref.shape and got.tobytes() == ref.tobytes()


def test_hull_iou_valid_equals_hull_iou():
    rng = np.random.default_rng(8)
    for n in (0, 2, 5, 60):
        pts = g.unit_to_world(rng.uniform(-0.6, 0.6, (n, 2)), CAR, "bev") if n else np.zeros((0, 2))
        for arr in (pts, pts.astype(np.float32), None, pts.tolist()):
            assert IOU.hull_iou_valid(g.validate_box(CAR), arr) == IOU.hull_iou(
                CAR, None if arr is None else np.asarray(arr, dtype=float).tolist()
            )  # a list takes the NumPy path


def test_closest_form_phi_equals_argmin_over_equivalent_boxes():
    """The written-out closest form is the np.argmin over :func:`_equivalent_boxes` of the φ
    distance, bit for bit (form and φ), ties and NaN costs included."""
    rng = np.random.default_rng(9)
    for model in ("bev", "3d"):
        p = g.phi_dim(model)
        for trial in range(200):
            y = CAR + np.r_[rng.normal(0, 0.3, 3), rng.uniform(-0.5, 0.5, 3), rng.uniform(-4, 4)]
            ref_box = CAR + np.r_[rng.normal(0, 0.3, 6), rng.uniform(-4, 4)]
            A = rng.normal(size=(p, p))
            W = np.eye(p) if trial % 5 == 0 else A @ A.T
            if trial % 17 == 0:
                W = np.full((p, p), np.nan)
            phi_ref = g.phi_of_valid_box(ref_box, model)
            forms = LF._equivalent_boxes(y)
            cost = [float((f := g.phi_of_valid_box(b, model) - phi_ref) @ W @ f) for b in forms]
            want = forms[int(np.argmin(cost))]
            form, phi = LF._closest_form_phi(y, phi_ref, W, model)
            assert form.tobytes() == want.tobytes()
            assert phi.tobytes() == g.phi_of_valid_box(want, model).tobytes()


def test_closed_form_chi2_cdf_equals_scipy():
    from scipy.stats import chi2

    for k in range(1, 10):
        for x in np.r_[0.0, np.logspace(-6, 2.5, 60)]:
            assert LF._chi2_cdf(float(x), k) == pytest.approx(chi2.cdf(x, k), abs=1e-13)
    assert LF._chi2_cdf(-1.0, 7) == 0.0


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_plane_rows_break_ties_like_the_nearest_face_registration(model):
    # points equally deep below two or three faces, on edges and at the centre: the compiled rows
    # must pick the same face as _nearest_faces (lower face index first)
    d = g.point_dim(model)
    half = CAR[3:6] / 2
    t = 0.3
    local = np.array(
        [
            [half[0] - t, half[1] - t, 0.0],  # +x and +y faces equally near
            [-half[0] + t, -half[1] + t, 0.0],
            [half[0] - t, 0.0, half[2] - t],
            [0.0, -half[1] + t, -half[2] + t],
            [half[0] - 0.2, half[1] - 0.2, half[2] - 0.2],
            [0.0, 0.0, 0.0],  # the centre
            [-half[0] - 0.1, half[1] + 0.1, 0.0],  # beyond a corner
        ]
    )[:, :d]
    pts = local.copy()
    pts[:, :2] = local[:, :2] @ g.rotation_z(CAR[6])[:2, :2].T + CAR[:2]
    if d == 3:
        pts[:, 2] += CAR[2]
    a, b, sqd = LF._plane_rows(CAR, pts, model)
    reg = M.register(CAR, pts, model, num_nearest=1)
    J = g.design_matrix(reg.vstar[:, 0, :], model)
    resid = pts - J @ g.box_to_phi(CAR, model)
    n = resid / np.linalg.norm(resid, axis=1, keepdims=True)
    u = np.einsum("kdp,kd->kp", J, n)
    w = np.sum(a * u, axis=1) / np.sum(u * u, axis=1)
    assert np.allclose(a, w[:, None] * u, atol=1e-9) and np.all(w > 0)
    assert np.allclose(sqd, reg.sqdist[:, 0])


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_unchecked_phi_equals_geometry(model):
    rng = np.random.default_rng(2)
    for _ in range(50):
        y = np.r_[rng.normal(0, 20, 3), rng.uniform(0.3, 8, 3), rng.uniform(-7, 7)]
        assert np.array_equal(g.phi_of_valid_box(y, model), g.box_to_phi(y, model))


def test_compiled_spd_solve_matches_numpy():
    # the fit's p × p solve (Cholesky) against LAPACK's LU, on badly scaled SPD systems like a
    # fit's precision (prior + σ⁻² Σ a aᵀ, entries from ~1 to ~1e6)
    rng = np.random.default_rng(4)
    for p in (6, 8):
        for _ in range(200):
            A = rng.normal(size=(p, 3 * p)) * rng.uniform(0.01, 100, size=(p, 1))
            P = A @ A.T + np.diag(rng.uniform(0.1, 10, p))
            rhs = rng.normal(size=p) * 100
            x = LF._solve_spd(P, rhs)
            ref = np.linalg.solve(P, rhs)
            assert np.allclose(x, ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())
    assert np.all(np.isnan(LF._solve_spd(-np.eye(6), np.ones(6))))  # not positive definite


def test_compiled_spd_inverse_against_known_inverses_and_lapack():
    # known answers: a diagonal matrix's inverse is its reciprocals; a 2 × 2 [[4, 2], [2, 3]] has
    # inverse [[3, −2], [−2, 4]] / 8
    out = np.empty((6, 6))
    D = np.diag([1.0, 4.0, 16.0, 0.25, 64.0, 0.0625])  # squares of powers of 2: every step exact
    assert linalg.spd_inverse_kernel(D, out)
    assert np.array_equal(out, np.diag(1.0 / np.diag(D)))
    out2 = np.empty((2, 2))
    assert linalg.spd_inverse_kernel(np.array([[4.0, 2.0], [2.0, 3.0]]), out2)
    assert np.allclose(out2, np.array([[3.0, -2.0], [-2.0, 4.0]]) / 8.0, rtol=0, atol=1e-15)
    # a fit's badly scaled precisions: M·M⁻¹ = I, exactly symmetric, LAPACK's spd_inverse to rounding
    rng = np.random.default_rng(5)
    for p in (6, 8):
        for _ in range(100):
            A = rng.normal(size=(p, 3 * p)) * rng.uniform(0.01, 100, size=(p, 1))
            P = A @ A.T + np.diag(rng.uniform(0.1, 10, p))
            P = 0.5 * (P + P.T)
            inv = np.empty((p, p))
            assert linalg.spd_inverse_kernel(P, inv)
            assert np.array_equal(inv, inv.T)
            ref = M.spd_inverse(P)
            assert np.allclose(inv, ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())
            assert np.allclose(P @ inv, np.eye(p), atol=1e-8)
    # not positive definite, or NaN: refused (the caller falls back to LAPACK, which says why)
    assert not linalg.spd_inverse_kernel(-np.eye(6), out)
    assert not linalg.spd_inverse_kernel(np.diag([1.0, 1.0, 0.0, 1.0, 1.0, 1.0]), out)
    assert not linalg.spd_inverse_kernel(np.full((6, 6), np.nan), out)


@pytest.mark.parametrize(("fit_model", "scored"), [("3d", "3d"), ("3d", "bev"), ("bev", "bev")])
def test_scored_metrics_equal_the_numpy_metric(fit_model, scored):
    # both label-error metrics in one compiled call = _scored_metric (LAPACK's inverse of the scored
    # block, zero elsewhere) of cov + S_tol and of cov, to rounding; entries outside the block exactly 0
    rng = np.random.default_rng(6)
    p = 8 if fit_model == "3d" else 6
    for _ in range(50):
        A = rng.normal(size=(p, 2 * p)) * rng.uniform(0.01, 1, size=(p, 1))
        cov = A @ A.T * 0.01 + np.diag(rng.uniform(1e-4, 1e-2, p))
        cov = 0.5 * (cov + cov.T)
        B = rng.normal(size=(p, p)) * 0.1
        S_tol = B @ B.T
        w_tol, w = LF._scored_metrics(cov, S_tol, fit_model, scored)
        for got, want in (
            (w_tol, LF._scored_metric(cov + S_tol, fit_model, scored)),
            (w, LF._scored_metric(cov, fit_model, scored)),
        ):
            assert np.allclose(got, want, rtol=1e-9, atol=1e-12 * np.abs(want).max())
            assert np.array_equal(got == 0, want == 0)
    if fit_model != scored:  # cz and height are not scored: their rows and columns are zero
        assert not w[2].any() and not w[:, 7].any()
    # a scored block that is not positive definite: NumPy's general inverse, as before
    bad = np.diag(np.r_[-1.0, np.ones(p - 1)])
    w_tol, w = LF._scored_metrics(bad, np.zeros((p, p)), fit_model, scored)
    assert np.array_equal(w, LF._scored_metric(bad, fit_model, scored))


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_fit_rectangle_of_phi_equals_geometry(model):
    rng = np.random.default_rng(5)
    label = np.array([1.0, 2.0, -0.5, 4.2, 1.8, 1.5, 0.3])
    for _ in range(200):
        y = np.r_[rng.normal(0, 20, 3), rng.uniform(0.3, 8, 3), rng.uniform(-np.pi, np.pi)]
        phi = g.box_to_phi(y, model)
        rect = LF._rect_from_phi(phi, model == "3d", label, 1e-3)
        ref = g.phi_to_box(phi, model, cz=label[2], height=label[5])
        assert np.allclose(rect, ref, rtol=1e-12, atol=1e-12)
    tiny = g.box_to_phi(np.r_[label[:3], 1e-9, 1e-9, 1e-9, 0.2], model)  # collapsed sizes are floored
    assert np.allclose(LF._rect_from_phi(tiny, model == "3d", label, 1e-3)[3:5], 1e-3 * label[3:5])


# ---------------------------------------------------------------------------------------------
# compiled kernels against the NumPy forms they replaced (bit for bit)
# ---------------------------------------------------------------------------------------------


def _registration_numpy(y, pts, d, m, sigma):
    """register_validated without outliers in its NumPy form (local frame, responsibilities)."""
    half = 0.5 * y[3 : 3 + d]
    c, s = np.cos(y[6]), np.sin(y[6])
    rel = pts[:, :2] - y[:2]
    local = np.empty_like(pts)
    local[:, 0] = c * rel[:, 0] + s * rel[:, 1]
    local[:, 1] = -s * rel[:, 0] + c * rel[:, 1]
    if d == 3:
        local[:, 2] = pts[:, 2] - y[2]
    vstar, sqd = M._nearest_faces(local, half, m)
    logw = -sqd / (2.0 * sigma**2)
    top = logw.max(axis=1, keepdims=True)
    top = np.where(np.isfinite(top), top, 0.0)
    e = np.exp(logw - top)
    return vstar, sqd, e / e.sum(axis=1, keepdims=True)


def _em_numpy(*sqds):
    """The σ̂ EM (pooled over registrations) in its NumPy/Python form: every candidate through
    ``math.exp`` (the kernel's vectorised exp is within 1 ulp of it), the points' sum in order."""
    sqd = np.concatenate(sqds)
    n = len(sqd)
    sqd0 = np.where(np.isfinite(sqd), sqd, 0.0)
    start = np.sqrt(sum(float(np.where(np.isfinite(s), s, 0.0)[:, 0].sum()) for s in sqds) / (1.0 * n))
    sigma, estimate = max(float(start), 0.01), float(start)
    diff, sq = (sqd - sqd.min(axis=1, keepdims=True)).T, sqd0.T
    for _ in range(50):
        scale = -0.5 / sigma**2
        num = 0.0
        for k in range(n):
            e = [math.exp(float(v) * scale) for v in diff[:, k]]
            se = s = 0.0
            for j in range(len(e)):
                se += e[j]
                s += e[j] * float(sq[j, k])
            num += s / se
        new = float(np.sqrt(num / n))
        converged = np.isfinite(estimate) and abs(new - estimate) <= 1e-3 * max(estimate, 0.01)
        estimate = new
        if converged or num == 0.0:
            break
        sigma = max(new, 0.01)
    return estimate


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_compiled_registration_em_and_information_equal_the_numpy_forms(model):
    """register_validated gives its NumPy form's arrays bit for bit, the per-object EM its σ̂ within
    1e-13 (its own exp and summation order: the last bits); registration_information (compiled, its own summation order) within 1e-13 of the BLAS form
    (points around, on and inside rotated boxes; 1 to 3 candidates)."""
    assert (C.SIGMA_FLOOR, C.EM_TOLERANCE, C.EM_MAX_ITERATIONS, C.EM_RESIDUAL_DOF) == (
        0.01,
        1e-3,
        50,
        1.0,
    )  # as _em_numpy
    rng = np.random.default_rng(21)
    d = g.point_dim(model)
    B, BB = M._BASIS[model]
    for trial in range(24):
        y = np.array([*rng.normal(0, 30, 3), *rng.uniform(0.5, 10, 3), rng.uniform(-4, 4)])
        pts = face_points(
            y, ["-x", "-y", "+x", "+z"], int(rng.integers(2, 300)), 10 ** rng.uniform(-3, -0.5), seed=trial
        )[:, :d].copy()
        m, sigma = int(rng.integers(1, 4)), float(rng.uniform(0.02, 0.5))
        reg = M.register_validated(y, pts, d, m, sigma, 0.0)
        vstar, sqd, resp = _registration_numpy(y, pts, d, m, sigma)
        assert (
            np.array_equal(reg.vstar, vstar) and np.array_equal(reg.sqdist, sqd) and np.array_equal(reg.resp, resp)
        ), trial
        if trial < 8:
            assert M.em_sigma([(sqd, 0.0)], d, sigma, 0.0) == pytest.approx(_em_numpy(sqd), rel=1e-13, abs=0), trial
            h = len(sqd) // 2  # pooled over two registrations
            pooled = M.em_sigma([(sqd[:h], 0.0), (sqd[h:], 0.0)], d, sigma, 0.0)
            assert pooled == pytest.approx(_em_numpy(sqd[:h], sqd[h:]), rel=1e-13, abs=0), trial
        n = len(pts)
        vt = np.empty((n, m, d + 1))
        vt[..., 0] = 1.0
        vt[..., 1:] = vstar
        rv = vt * resp[..., None]
        moments = rv.reshape(n * m, d + 1).T @ vt.reshape(n * m, d + 1)
        p = B.shape[-1]
        want = (
            (moments.reshape(-1) @ BB.reshape(-1, p * p)).reshape(p, p),
            (rv.sum(axis=1).T @ pts).reshape(-1) @ B.reshape(-1, p),
        )
        got = M.registration_information(reg, model)
        assert np.allclose(got[0], want[0], rtol=1e-13, atol=1e-13 * np.abs(want[0]).max()), trial
        assert np.allclose(got[1], want[1], rtol=1e-13, atol=1e-13 * np.abs(want[1]).max()), trial


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_compiled_quadratic_forms_equal_einsum(model):
    """The per-parameter variances and corner total variances are einsum's sums bit for bit."""
    rng = np.random.default_rng(17)
    p = g.phi_dim(model)
    J = M._CORNER_J[model]
    for _ in range(300):
        L = rng.normal(size=(p, p)) * 10.0 ** rng.uniform(-4, 1)
        cov = L @ L.T
        cov = 0.5 * (cov + cov.T)
        K, _ = g.box_param_jacobian(
            np.array([*rng.normal(0, 20, 3), *rng.uniform(0.3, 10, 3), rng.uniform(-4, 4)]), model
        )
        assert np.array_equal(M._quad_forms(K, cov), np.einsum("ip,pq,iq->i", K, cov, K))
        assert np.array_equal(M._corner_quad_forms(J, cov), np.einsum("cdp,pq,cdq->c", J, cov, J))


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_compiled_posterior_equals_the_lapack_form(model):
    """The compiled posterior (Cholesky inverse, mean, prior covariance) matches LAPACK's and BLAS's
    to 1e-12 of the largest entry (data columns scaled over six orders of magnitude); a precision
    that is not positive definite is refused with LAPACK's message."""
    rng = np.random.default_rng(29)
    p = g.phi_dim(model)
    for trial in range(200):
        G = rng.normal(size=(p, p))
        S_ext = G @ G.T + 1e-3 * np.eye(p)
        P0 = M.spd_inverse(S_ext)
        A = rng.normal(size=(3 * p, p)) * 10.0 ** rng.uniform(-3, 3, p)  # badly scaled data columns
        info = A.T @ A
        eta0, eta = rng.normal(size=p), rng.normal(size=p)
        sigma, weight = float(rng.uniform(0.01, 0.5)), float(rng.uniform(0.1, 10))
        ok, cov, mean, S0 = M._posterior_kernel(P0, eta0, info, eta, sigma, G, S_ext, weight)
        lam = P0 + info / sigma**2
        want = M.spd_inverse(0.5 * (lam + lam.T))
        assert ok and np.array_equal(cov, cov.T) and np.array_equal(S0, S0.T), trial
        assert np.abs(cov - want).max() <= 1e-12 * np.abs(want).max(), trial
        want_mean = want @ (eta0 + eta / sigma**2)
        assert np.abs(mean - want_mean).max() <= 1e-11 * np.abs(want_mean).max(), trial
        want_S0 = G @ (S_ext / weight) @ G.T
        assert np.abs(S0 - want_S0).max() <= 1e-13 * np.abs(want_S0).max(), trial
    ok, *_ = M._posterior_kernel(-np.eye(p), np.zeros(p), np.zeros((p, p)), np.zeros(p), 0.1, np.eye(p), np.eye(p), 1.0)
    assert not ok
    with pytest.raises(ValueError, match="not positive definite"):
        M.spd_inverse(-np.eye(p))


def _same_posterior(a, b) -> bool:
    """Every field of two LabelPosteriors equal bit for bit (NaN equal to NaN)."""
    for f in dataclasses.fields(a):
        u, v = getattr(a, f.name), getattr(b, f.name)
        if isinstance(u, dict):
            if list(u) != list(v) or not np.array_equal(list(u.values()), list(v.values()), equal_nan=True):
                return False
        elif isinstance(u, np.ndarray):
            if u.dtype != v.dtype or u.shape != v.shape or not np.array_equal(u, v, equal_nan=u.dtype.kind == "f"):
                return False
        elif not (u == v or (u != u and v != v)):
            return False
    return True


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_infer_label_valid_equals_infer_label(model):
    """The pipeline's entry (validated box, clean points, shared prior terms) gives the public
    function's posterior bit for bit, with or without the terms; terms of another kind are refused."""
    rng = np.random.default_rng(5)
    params = ModelParams(kind=model)
    d = g.point_dim(model)
    for trial in range(20):
        box = np.array([*rng.normal(0, 20, 3), *rng.uniform(0.5, 6, 3), rng.uniform(-4, 4)])
        pts = face_points(box, ["-x", "-y", "+z"], int(rng.integers(0, 60)), 0.05)
        pts = np.c_[pts, rng.uniform(0, 1, len(pts))].astype(np.float32 if trial % 2 else np.float64)  # (N, 4) crops
        origin = rng.normal(0, 2, 3)
        want = M.infer_label(box, pts, "Car", params, origin)
        y = g.validate_box(box)
        clean = g.clean_points(pts, d)
        terms = M.box_prior_terms(y, params.prior_for("Car"), params.prior_weight, model)
        assert _same_posterior(M.infer_label_valid(y, clean, "Car", params, origin), want), trial
        assert _same_posterior(M.infer_label_valid(y, clean, "Car", params, origin, prior_terms=terms), want), trial
    other = M.box_prior_terms(y, params.prior_for("Car"), params.prior_weight, "3d" if model == "bev" else "bev")
    with pytest.raises(ValueError, match="do not match"):
        M.infer_label_valid(y, clean, "Car", params, prior_terms=other)
    with pytest.raises(ValueError, match="do not match"):
        M.infer_label_valid(y, clean, "Pedestrian", params, prior_terms=terms)  # another class prior


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_box_prior_terms_are_the_numpy_set_up_within_the_last_bits(model):
    """The shared terms' φ and G are the geometry's bit for bit; their compiled G⁻¹, P0 = sym(G⁻ᵀ w
    Σ_ỹ⁻¹ G⁻¹) and P0 φ are LAPACK's inverse and the BLAS products within the last bits (relative
    to each array's largest entry), on boxes of every size and yaw; P0 is symmetric and G⁻¹ inverts G."""
    rng = np.random.default_rng(11)
    params = ModelParams(kind=model)
    prior = params.prior_for("Car")
    for _ in range(200):
        y = g.validate_box(np.array([*rng.normal(0, 30, 3), *rng.uniform(0.01, 12, 3), rng.uniform(-7, 7)]))
        t = M.box_prior_terms(y, prior, params.prior_weight, model)
        G = g.dphi_dext_valid(y, model)
        E = np.linalg.inv(G)
        P0 = M.prior_precision(y, prior, params.prior_weight, model)
        assert np.array_equal(t.phi, g.box_to_phi(y, model)) and np.array_equal(t.G, G)
        for got, want in ((t.Ginv, E), (t.P0, P0), (t.eta0, P0 @ t.phi)):
            assert np.max(np.abs(got - want)) <= 4e-15 * np.max(np.abs(want))
        assert np.array_equal(t.P0, t.P0.T)
        assert np.allclose(t.Ginv @ G, np.eye(len(G)), rtol=0, atol=1e-14)
        assert t.matches(model, prior, params.prior_weight) and not t.matches(model, prior, 2 * params.prior_weight)


def test_box_prior_terms_bev_3d_are_each_models_own_bit_for_bit():
    """The BEV and 3D terms made in one call are box_prior_terms' of each model bit for bit (every
    array, shape included), on boxes of every size and yaw, two weights and three class priors;
    a known answer: a yaw-0 box's φ is (cx, cy, l, 0, w, 0) in BEV and (cx, cy, cz, l, 0, w, 0, h) in 3D."""
    rng = np.random.default_rng(23)
    params = ModelParams(kind="bev")
    for k in range(300):
        cls = ("Car", "Pedestrian", "Cyclist")[k % 3]
        prior, weight = params.prior_for(cls), (params.prior_weight, 0.5)[k % 2]
        y = g.validate_box(np.array([*rng.normal(0, 30, 3), *rng.uniform(0.01, 12, 3), rng.uniform(-7, 7)]))
        pair = M.box_prior_terms_bev_3d(y, prior, weight)
        for got, model in zip(pair, ("bev", "3d")):
            want = M.box_prior_terms(y, prior, weight, model)
            assert got.matches(model, prior, weight) and got.model == model
            for f in ("phi", "G", "Ginv", "P0", "eta0"):
                a, b = getattr(got, f), getattr(want, f)
                assert a.shape == b.shape and np.array_equal(a, b) and a.tobytes() == b.tobytes(), (k, model, f)
    bev, three = M.box_prior_terms_bev_3d(g.validate_box([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 0.0]), prior, 1.0)
    assert bev.phi.tolist() == [1.0, 2.0, 4.0, 0.0, 5.0, 0.0]
    assert three.phi.tolist() == [1.0, 2.0, 3.0, 4.0, 0.0, 5.0, 0.0, 6.0]


def test_bev_label_scores_are_the_general_steps_bit_for_bit():
    """bev_label_scores (two compiled calls) gives box_prior_terms_bev_3d's 3D terms,
    infer_label_valid's σ, σ̂, Σ, corner variances and std, jiou_gt's and hull_iou_valid's values bit
    for bit: 0, 1, 2, few and many points, three classes, σ̂ on and off, boxes of every yaw and
    size; a box seen on two faces as a known answer (JIoU-GT in (0.5, 1), a hull inside the box)."""
    from labelaudit.config import SpatialParams
    from labelaudit.core.iou import hull_iou_valid
    from labelaudit.core.spatial import jiou_gt

    rng = np.random.default_rng(31)
    spatial = SpatialParams()
    checked = 0
    for k in range(60):
        cls = ("Car", "Pedestrian", "Cyclist")[k % 3]
        params = ModelParams(kind="bev", estimate_sigma=k % 2 == 0)
        box = np.array([*rng.normal(0, 25, 2), 0.8, *rng.uniform(0.3, 9, 3), rng.uniform(-7, 7)])
        y = g.validate_box(box)
        n = (0, 1, 2, 5, 40, 300)[k % 6]
        pts = np.ascontiguousarray(face_points(y, ["-x", "-y", "+y"][: 1 + k % 3], max(n, 1), 0.04, seed=k)[:n, :2])
        origin = (float(rng.normal(0, 3)), float(rng.normal(0, 3)), 1.7)
        prior = params.prior_for(cls)
        got = M.bev_label_scores(y, pts, prior, params, spatial, origin[0], origin[1])
        assert got is not None, k
        terms, fit_terms = M.box_prior_terms_bev_3d(y, prior, params.prior_weight)
        post = M.infer_label_valid(y, pts, cls, params, origin, prior_terms=terms)
        assert got.num_points == post.num_points == n and got.sigma == post.sigma
        assert got.sigma_hat == post.sigma_hat or (math.isnan(got.sigma_hat) and math.isnan(post.sigma_hat))
        for a, b in ((got.cov, post.cov), (got.corner_tv, post.corner_tv)):
            assert a.shape == b.shape and a.tobytes() == b.tobytes(), k
        assert got.std_box.keys() == post.std_box.keys()
        assert np.array_equal(list(got.std_box.values()), list(post.std_box.values()), equal_nan=True)
        assert got.jiou_gt == jiou_gt(post, spatial) and got.hull_iou == hull_iou_valid(y, pts), k
        assert got.fit_terms.matches("3d", prior, params.prior_weight)
        for f in ("phi", "G", "Ginv", "P0", "eta0"):
            assert getattr(got.fit_terms, f).tobytes() == getattr(fit_terms, f).tobytes(), (k, f)
        checked += 1
    assert checked == 60
    params = ModelParams(kind="bev")
    seen = face_points(CAR, ["-x", "-y"], 100, 0.03)[:, :2].copy()
    known = M.bev_label_scores(g.validate_box(CAR), seen, params.prior_for("Car"), params, spatial, 0.0, 0.0)
    assert 0.5 < known.jiou_gt < 1.0 and 0.0 < known.hull_iou < 1.0 and known.corner_tv[0] < known.corner_tv[3]


def test_audit_object_takes_the_general_steps_when_the_one_pass_cannot(monkeypatch):
    """When bev_label_scores cannot answer (None), audit_object's row is the same from the general steps."""
    from labelaudit.infer import rows as rows_mod

    cfg = load_config(None, "kitti")
    pts = face_points(CAR, ["-x", "-y"], 100, 0.03)
    model_pts, fit_cols = np.ascontiguousarray(pts[:, :2]), np.ascontiguousarray(pts[:, :3].T)
    calls = []
    real = rows_mod.bev_label_scores
    monkeypatch.setattr(rows_mod, "bev_label_scores", lambda *a: calls.append(1) or real(*a))
    fast = audit_object(CAR, model_pts, "Car", cfg, fit_points=fit_cols, clean=True)
    monkeypatch.setattr(rows_mod, "bev_label_scores", lambda *a: calls.append(0))
    general = audit_object(CAR, model_pts, "Car", cfg, fit_points=fit_cols, clean=True)
    assert calls == [1, 0] and list(fast) == list(general)
    for key, value in fast.items():
        other = general[key]
        assert value == other or (value != value and other != other), key


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_fit_label_with_shared_terms_equals_its_own(model):
    """fit_label_valid with a run's prior terms is the fit without them; a BEV run's terms (the fit
    is 3D) and terms of points without z are not used."""
    params = ModelParams(kind=model)
    y = g.validate_box(_shifted(CAR, cx=0.2, yaw=0.05))
    terms = M.box_prior_terms(y, params.prior_for("Car"), params.prior_weight, model)
    for pts in (face_points(CAR, ["-x", "-y"], 80, 0.03), face_points(CAR, ["-x", "-y"], 80, 0.03)[:, :2], None):
        want = LF.fit_label(y, pts, "Car", params)
        got = LF.fit_label_valid(y, pts, "Car", params, prior_terms=terms)
        for f in ("box", "phi", "cov"):
            assert np.array_equal(getattr(got, f), getattr(want, f)), f
        assert (got.model, got.label_error, got.mahalanobis, got.iterations) == (
            want.model,
            want.label_error,
            want.mahalanobis,
            want.iterations,
        )
        assert np.array_equal(list(got.offsets.values()), list(want.offsets.values()), equal_nan=True)


def _point_work(pts_t: np.ndarray) -> tuple[np.ndarray, ...]:
    """The fit's per-point work arrays (face, along, bs, rs) for points (d, N)."""
    n = pts_t.shape[1]
    return np.empty(n, dtype=np.int64), np.empty(n), np.empty(n), np.empty(n)


def _ray_work(p: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """The ray rows' work arrays (a (p, M), b (M,))."""
    return np.empty((p, m)), np.empty(m)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_fit_precision_kernel_equals_the_numpy_composition(model):
    """The one-call precision at the fitted box is, bit for bit, the NumPy composition of the point
    rows' and ray rows' normal equations: P0 + (AᵀA + A_rᵀA_r)/σ², symmetrised (and the residual sums)."""
    from labelaudit.core.freespace import FreeSpace

    rng = np.random.default_rng(21)
    three_d = model == "3d"
    d = 3 if three_d else 2
    y = CAR + np.r_[rng.normal(0, 0.2, 3), 0.0, 0.0, 0.0, 0.1]
    pts = face_points(CAR, ["-x", "-y", "+z"], 40, noise=0.03, seed=21)
    pts_t = np.ascontiguousarray(np.asarray(pts, dtype=float)[:, :d].T)
    ends = np.c_[
        rng.uniform(12, 22, 300), rng.uniform(2, 9, 300), rng.uniform(0.3, 0.5, 300)
    ]  # returns low behind and in the box
    fs = FreeSpace(np.array([0.0, 0.0, 1.7]), ends, np.array([0.0, 0.0, 0.0, 0.0]), CAR[:2].copy(), (0.25, 0.6), 0.1)
    terms = M.box_prior_terms(g.validate_box(CAR), ModelParams().prior_for("Car"), 1.0, model)
    phi, sigma = g.phi_of_valid_box(y, model), 0.05
    for rays in (LF._NO_RAYS, LF._ray_inputs(fs, sigma, g.validate_box(CAR))):
        m = rays[0].shape[1]
        got, rr, ss, sw = LF._fit_precision_work(
            y,
            pts_t,
            three_d,
            *LF._fit_point_constants(),
            sigma,
            phi,
            terms.P0,
            1.0 / sigma**2,
            *rays,
            CAR,
            *_point_work(pts_t),
            *_ray_work(len(phi), m),
        )
        ata, _, rr_want, ss_want, sw_want = LF._normal_eq_work(
            y, pts_t, d, *LF._fit_point_constants(), sigma, phi, *_point_work(pts_t)
        )
        if m:  # every ray evaluated: the bounds skip only rays without a row
            ata_r, _, rr_r, active = LF._ray_normal_eq_work(
                y, *rays[:9], three_d, phi, rays[9], np.full(m, math.inf), y, *_ray_work(len(phi), m)
            )
            assert active > 0  # the rays do add rows
            ata = ata + ata_r
            rr_want += rr_r
        precision = terms.P0 + ata * (1.0 / sigma**2)
        assert got.tobytes() == (0.5 * (precision + precision.T)).tobytes()
        assert (rr, ss, sw) == (rr_want, ss_want, sw_want)


def test_fit_descent_stop_hands_back_the_accepted_pass(tmp_path, monkeypatch):
    """A descent that stops on the last box it accepted hands back that box's own pass — its
    precision and RMS sums — instead of a further pass at it: with the log posterior not wanted
    (RMS not above ``post_above``) every output but the log posterior (NaN) is the full pass's bit
    for bit, and the log posterior is the full pass's whenever it is given. On the pipeline's fits
    of simulated frames, where descents do stop so."""
    from labelaudit.config import resolve_config
    from labelaudit.datasets import open_dataset
    from labelaudit.infer import rows as rows_mod
    from labelaudit.sim.dataset import simulate_dataset

    simulate_dataset(tmp_path / "sim", frames=8, seed=4, progress=False)
    calls, inner = [], LF._fit_em_kernel

    def spy(*a):
        calls.append(a)
        return inner(*a)

    monkeypatch.setattr(LF, "_fit_em_kernel", spy)
    reader = open_dataset(tmp_path / "sim", "kitti")
    cfg = resolve_config(None, "kitti", None, None)
    for ref in reader.list_units():
        for frame in reader.load_unit(ref):
            rows_mod.process_frame(frame, cfg)
    monkeypatch.undo()
    stops = 0
    for a in calls:
        cov_full, cov_kept = np.empty_like(a[29]), np.empty_like(a[29])
        full = inner(*a[:29], cov_full, -math.inf)
        kept = inner(*a[:29], cov_kept, math.inf)
        assert cov_full.tobytes() == cov_kept.tobytes()
        for i in (0, 1, 7):
            assert full[i].tobytes() == kept[i].tobytes()
        assert (full[2], full[3], full[5], full[6]) == (kept[2], kept[3], kept[5], kept[6])
        if math.isnan(kept[4]):
            stops += 1
        else:
            assert kept[4] == full[4]
        assert not math.isnan(full[4])
    assert len(calls) > 40 and stops > 0, (len(calls), stops)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_point_normal_equations_equal_the_rows_gram(model):
    """The point pass's one-pass sums (no rows written; deep points centred on the sums) equal the
    rows' Gram product (the rows of :func:`_rows_kernel`, deep points centred row by row) up to
    rounding: points on the faces, beyond edges and corners, deep inside (a loose box, every face's
    deep points centred), exactly on the surface, in world coordinates far from the origin."""
    rng = np.random.default_rng(8)
    three_d = model == "3d"
    d = 3 if three_d else 2
    box = np.array([41.3, -17.9, 0.8, 4.4, 1.8, 1.6, 2.3])
    loose = box + np.r_[0.3, -0.2, 0.05, 0.9, 0.6, 0.4, 0.08]  # most points deep inside it
    pts = np.vstack(
        [
            face_points(box, ["-x", "+x", "-y", "+y", "+z"], 60, noise=0.03, seed=8),
            box[:3] + rng.uniform(-3, 3, (80, 3)),  # beyond edges and corners, and inside
            face_points(box, ["-y"], 5, noise=0.0, seed=9),  # exactly on the surface
        ]
    )
    pts_t = np.ascontiguousarray(pts[:, :d].T)
    free_depth, deep_weight, _ = LF._fit_point_constants()
    for y in (box, loose):
        phi = g.phi_of_valid_box(y + np.r_[0.02, -0.01, 0.01, 0.0, 0.0, 0.0, 0.01], model)
        a = np.empty((2 * d + 2, pts_t.shape[1]))
        b, sqd = np.empty(pts_t.shape[1]), np.empty(pts_t.shape[1])
        LF._rows_kernel(y, pts_t, d, free_depth, deep_weight, 0.0, 0.05, a, b, sqd, True)
        assert (sqd < 0).sum() > (20 if y is loose else -1)  # deep points, centred
        keep = sqd >= 0
        w2 = (a[:3] ** 2).sum(0) if three_d else (a[:2] ** 2).sum(0)
        want = (a @ a.T, a @ b, ((a.T @ phi - b) ** 2).sum(), (w2 * sqd)[keep].sum(), w2[keep].sum())
        got = LF._normal_eq_work(y, pts_t, d, free_depth, deep_weight, 0.0, 0.05, phi, *_point_work(pts_t))
        scale = np.abs(want[0]).max()
        assert np.abs(got[0] - want[0]).max() <= 1e-12 * scale
        assert np.abs(got[1] - want[1]).max() <= 1e-12 * np.abs(want[1]).max()
        assert got[2:] == pytest.approx(want[2:], rel=1e-10, abs=0)


def test_corner_covariances_known_answer_and_one_formula():
    """Isotropic φ covariance s²·I (BEV): a corner v* = (±½, ±½) has J Jᵀ = (1 + v₁² + v₂²)·I₂ = 1.5·I₂,
    so each corner's covariance is 1.5 s²·I₂ and its total variance 3 s²; the per-box trace (compiled),
    the corner covariances and the stacked traces are one formula."""
    s2 = 0.04
    cov = s2 * np.eye(6)
    cc = M.corner_covariances(cov, "bev")
    np.testing.assert_allclose(cc, np.broadcast_to(1.5 * s2 * np.eye(2), (4, 2, 2)), rtol=1e-15)
    rng = np.random.default_rng(3)
    for model, p in (("bev", 6), ("3d", 8)):
        A = rng.normal(size=(3, p, p))
        covs = A @ A.transpose(0, 2, 1) * 0.01
        box = np.array([5.0, -2.0, 0.5, 4.0, 1.8, 1.5, 0.7])
        stacked = M.corner_variances(covs, model)
        for k in range(3):
            tv, order = M.corner_total_variance(box, covs[k], model)
            np.testing.assert_allclose(tv, stacked[k][order], rtol=1e-13)
            np.testing.assert_allclose(
                np.trace(M.corner_covariances(covs[k], model), axis1=1, axis2=2), stacked[k], rtol=1e-13
            )


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_one_pass_posterior_equals_the_general_steps(model, monkeypatch):
    """infer_label's one compiled pass (no outlier component) gives the general steps' posterior:
    the registration, σ, σ̂, corner order and sample count exactly, the covariance, corner variances,
    stds, Gaussian mean and prior covariance within the last bits (its exponentials are
    linalg.exp_kernel's, not NumPy's), for 0, 1, few and many points, with and without σ̂ replacing σ."""
    rng = np.random.default_rng(21)
    box = np.array([14.0, -3.0, 0.8, 4.3, 1.8, 1.5, 0.6])
    cases = []
    for n in (0, 1, 2, 5, 60, 400):
        for estimate in (True, False):
            pts = face_points(box, ["-x", "-y", "+y"][: 1 + n % 3], max(n, 1), 0.04, seed=n)[:n]
            cases.append((np.c_[pts, rng.uniform(0, 1, len(pts))], ModelParams(kind=model, estimate_sigma=estimate)))
    kernel = M._posterior_no_outliers_kernel
    taken = []
    monkeypatch.setattr(M, "_posterior_no_outliers_kernel", lambda *a: taken.append(kernel(*a)) or taken[-1])
    fast = [M.infer_label(box, pts, "Car", params, (0.0, 0.0, 0.0)) for pts, params in cases]
    assert len(taken) == len(cases) and all(t[0] for t in taken)  # the one pass answered every case
    monkeypatch.setattr(M, "_posterior_no_outliers_kernel", lambda *a: (False, *kernel(*a)[1:]))
    general = [M.infer_label(box, pts, "Car", params, (0.0, 0.0, 0.0)) for pts, params in cases]
    for a, b in zip(fast, general):
        assert a.num_points == b.num_points and a.sigma == b.sigma
        assert a.sigma_hat == b.sigma_hat or (math.isnan(a.sigma_hat) and math.isnan(b.sigma_hat))
        assert np.array_equal(a.corner_order, b.corner_order) and np.array_equal(a.phi, b.phi)
        for x, y in ((a.cov, b.cov), (a.corner_tv, b.corner_tv), (a.prior_cov, b.prior_cov)):
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-15 * np.abs(y).max())
        # the mean Σ(η0 + η/σ²) adds large terms that cancel: the responsibilities' last bits weigh more
        np.testing.assert_allclose(a.fit_mean, b.fit_mean, rtol=1e-10)
        np.testing.assert_allclose(list(a.std_box.values()), list(b.std_box.values()), rtol=1e-12)


def test_compiled_corner_order_equals_the_python_order():
    """The one pass's corner order (libm's cos, sin, hypot and an insertion sort) is
    :func:`_corner_order`'s: random boxes and sensors, and equal distances (a sensor on a box's
    axis, at its centre), where the stable order keeps the corners' own order."""
    rng = np.random.default_rng(3)
    cases = [
        (np.array([10.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]), (0.0, 0.0)),
        (np.array([0.0, 10.0, 0.0, 4.0, 2.0, 1.5, np.pi / 2]), (0.0, 0.0)),
        (np.array([3.0, -2.0, 0.0, 4.0, 2.0, 1.5, 0.3]), (3.0, -2.0)),
        (np.array([5.0, 5.0, 0.0, 2.0, 2.0, 1.5, np.pi / 4]), (0.0, 0.0)),
    ]
    for _ in range(3000):
        box = np.array([*rng.uniform(-60, 60, 2), 0.0, *rng.uniform(0.2, 12, 2), 1.5, rng.uniform(-7, 7)])
        cases.append((box, tuple(rng.uniform(-3, 3, 2))))
    for box, (ox, oy) in cases:
        expected = M._corner_order(box, (ox, oy, 0.0))
        assert np.array_equal(M._corner_order_kernel(box, ox, oy), expected), (box, ox, oy)


def test_compiled_box_jacobian_equals_numpys():
    """The one pass's K (E's box rows, the two angle rows averaged) is the general steps' NumPy K bit for bit."""
    rng = np.random.default_rng(6)
    for p in (6, 8):
        for _ in range(50):
            E = rng.normal(size=(p, p)) * 10.0 ** rng.integers(-8, 8)
            K = np.empty((p - 1, p))
            K[: p - 2] = E[: p - 2]
            K[p - 2] = 0.5 * (E[p - 2] + E[p - 1])
            assert M._box_jacobian_of(E).tobytes() == K.tobytes()


def test_branch_free_nearest_edges_equal_the_sorting_loop():
    """The BEV registration's branch-free pass (a sorting network on (distance, edge)) gives the
    stable insertion sort's arrays bit for bit: points inside, outside, exactly on edges and
    corners, on both sides within the tolerance, at equal distance from two edges; m = 1 … 4."""
    rng = np.random.default_rng(8)
    for trial in range(40):
        half = rng.uniform(0.2, 3.0, 2)
        if trial % 4 == 0:
            half[1] = half[0]  # a square: ties between the edges of both axes
        scale = rng.choice([0.0, 0.3, 1.0, 1.0 + 1e-12, 1.0 - 1e-12, 1.7, 4.0], (300, 2))
        local = rng.choice([-1.0, 1.0], (300, 2)) * half * scale
        local[:50] = rng.uniform(-2, 2, (50, 2)) * half
        tol = 1e-9 * float(half.max())
        for m in range(1, 5):
            fast = M._nearest_edges_kernel(local, half, m, tol)
            loop = M._nearest_faces_loop(local, half, m, tol)
            assert np.array_equal(fast[0], loop[0]) and np.array_equal(fast[1], loop[1]), (trial, m)
