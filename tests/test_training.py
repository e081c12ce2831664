"""labelaudit.training: encodings, error propagation (vs Monte-Carlo), σ_p sources and the KLD loss."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from _core_synth import face_points
from labelaudit import constants as C
from labelaudit import training as T
from labelaudit.config import ClassPrior, ModelParams
from labelaudit.core import geometry as g
from labelaudit.core.posterior import infer_label, prior_covariance

ENCODINGS = ("box", "log-size", "pixor", "residual")
ANCHOR = np.array([3.9, 1.6, 1.56])


# ----------------------------------------------------------------------------- helpers


def phi_to_boxes(phi: np.ndarray, model: str, cz: float, h: float) -> np.ndarray:
    """Vectorised φ → y (the map of geometry.phi_to_box: yaw = mean direction of the two axes)."""
    o = 1 if model == "3d" else 0
    lc, ls, wc, ws = (phi[:, 2 + o + k] for k in range(4))
    a, b = np.arctan2(ls, lc), np.arctan2(ws, wc)
    yaw = a + 0.5 * g.normalize_angle(b - a)
    z = phi[:, 2] if model == "3d" else np.full(len(phi), cz)
    hh = phi[:, 7] if model == "3d" else np.full(len(phi), h)
    return np.stack([phi[:, 0], phi[:, 1], z, np.hypot(lc, ls), np.hypot(wc, ws), hh, yaw], axis=1)


def test_vectorised_phi_to_box_helper_equals_geometry():
    rng = np.random.default_rng(3)
    for model in ("bev", "3d"):
        box = np.array([5.0, -2.0, 0.4, 4.1, 1.7, 1.5, 2.9])
        phis = g.box_to_phi(box, model) + rng.normal(0, 0.2, (20, g.phi_dim(model)))
        ours = phi_to_boxes(phis, model, box[2], box[5])
        ref = np.array([g.phi_to_box(p, model, cz=box[2], height=box[5]) for p in phis])
        ours[:, 6] = g.normalize_angle(ours[:, 6])
        assert np.allclose(ours, ref, atol=1e-12)


def mc_boxes(box, cov_phi, model, n=200_000, seed=0):
    """Boxes of φ ~ N(φ(label), Σ)."""
    rng = np.random.default_rng(seed)
    phis = rng.multivariate_normal(g.box_to_phi(box, model), cov_phi, size=n, method="cholesky")
    return phi_to_boxes(phis, model, box[2], box[5])


def mc_target_cov(box, boxes, encoding):
    """Covariance of the encoded targets of sampled boxes, angles compared modulo 2π."""
    enc = T.get_encoding(encoding)
    anchors = np.r_[box[:3] + [0.3, -0.2, 0.1], ANCHOR, 0.0]  # anchor position/yaw: constants
    dev = T.encode(boxes, enc, anchors=anchors) - T.encode(box[None], enc, anchors=anchors)[0]
    for i, name in enumerate(enc.targets):
        if name in enc.angular:
            dev[:, i] = g.normalize_angle(dev[:, i])
    return np.cov(dev, rowvar=False)


def scales(names: list[str], cov: np.ndarray) -> np.ndarray:
    """Per-target variance scale; a sin/cos pair shares the variance of the pair (rotation-invariant)."""
    s = np.diag(cov).copy()
    if "sin_yaw" in names:
        i, j = names.index("sin_yaw"), names.index("cos_yaw")
        s[i] = s[j] = s[i] + s[j]
    return s


def assert_matches_mc(box, cov_phi, model, encodings=ENCODINGS, rel=0.03):
    """Propagated covariance vs sampling: |ΔC_ij| ≤ 3 % √(s_i s_j), and non-degenerate variances within 3 %."""
    boxes = mc_boxes(box, cov_phi, model)
    cov_y = T.box_covariance_from_phi(box[None], cov_phi[None], model)
    for encoding in encodings:
        enc = T.get_encoding(encoding)
        prop = T.propagate(box[None], cov_y, enc, anchor_sizes=ANCHOR, available=T.available_params(model))[0]
        avail = ~np.isnan(np.diag(prop))
        # exactly the targets that need cz or h are missing for BEV, none for 3D
        assert np.array_equal(avail, ~enc.depends()[:, ~T.available_params(model)].any(axis=1))
        names = [t for t, a in zip(enc.targets, avail) if a]
        P = prop[np.ix_(avail, avail)]
        M = mc_target_cov(box, boxes, enc)[np.ix_(avail, avail)]
        s = scales(names, P)
        bad = np.abs(P - M) > rel * np.sqrt(np.outer(s, s))
        assert not bad.any(), (encoding, model, box[6], names, np.diag(P), np.diag(M))
        d_p, d_m = np.diag(P), np.diag(M)
        strong = d_p > 0.05 * s  # all but a sin or cos whose derivative vanishes at this yaw
        assert strong.sum() >= len(names) - 1
        assert np.all(np.abs(d_p[strong] - d_m[strong]) <= rel * d_m[strong])


def posterior(box, points, model, sigma=0.2):
    params = ModelParams(kind=model, sigma=sigma)
    return infer_label(box, points, "Car", params)


# ----------------------------------------------------------------------------- Jacobians


def test_box_jacobian_equals_geometry_jacobian():
    rng = np.random.default_rng(0)
    rows_bev = [0, 1, 3, 4, 6]
    for _ in range(20):
        box = np.r_[rng.normal(0, 20, 3), rng.uniform(0.5, 6, 3), rng.uniform(-np.pi, np.pi)]
        for model, rows in (("3d", list(range(7))), ("bev", rows_bev)):
            K_ref, _ = g.box_param_jacobian(box, model)
            K = T.box_jacobian(box[None], model)[0]
            assert np.allclose(K[rows], K_ref, atol=1e-12)
            if model == "bev":
                assert np.all(K[[2, 5]] == 0)


def test_box_covariance_gives_the_results_std_columns():
    box = np.array([12.0, 4.0, -0.8, 4.2, 1.7, 1.5, 0.4])
    pts = face_points(box, ["-x", "-y"], 80, noise=0.03, seed=1)
    for model in ("bev", "3d"):
        post = posterior(box, pts, model)
        std = np.sqrt(np.diag(T.box_covariance_from_phi(box[None], post.cov[None], model)[0]))
        for k, name in enumerate(g.BOX_FIELDS):
            if T.available_params(model)[k]:
                assert std[k] == pytest.approx(post.std_box[name], rel=1e-10)


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_encoding_jacobian_equals_finite_differences(encoding):
    rng = np.random.default_rng(1)
    boxes = np.c_[rng.normal(0, 10, (6, 3)), rng.uniform(0.5, 5, (6, 3)), rng.uniform(-np.pi, np.pi, 6)]
    anchors = np.c_[boxes[:, :3] + 0.1, np.tile(ANCHOR, (6, 1)), np.zeros(6)]
    J = T.encoding_jacobian(boxes, encoding, np.tile(ANCHOR, (6, 1)))
    h = 1e-6
    for k in range(7):
        e = np.zeros(7)
        e[k] = h
        fd = (T.encode(boxes + e, encoding, anchors=anchors) - T.encode(boxes - e, encoding, anchors=anchors)) / (2 * h)
        assert np.allclose(J[:, :, k], fd, atol=1e-7)


def test_encode_known_values():
    box = np.array([[10.0, 2.0, -1.0, 4.0, 1.6, 1.5, math.pi / 2]])
    t = T.encode(box, "log-size")[0]
    assert t == pytest.approx([10, 2, -1, math.log(4), math.log(1.6), math.log(1.5), 1.0, 0.0], abs=1e-12)
    anchor = np.array([9.0, 2.5, -0.9, 3.9, 1.6, 1.56, 0.0])
    r = T.encode(box, "residual", anchors=anchor)[0]
    d = math.hypot(3.9, 1.6)
    assert r == pytest.approx([1 / d, -0.5 / d, -0.1 / 1.56, math.log(4 / 3.9), 0.0, math.log(1.5 / 1.56), math.pi / 2])
    p = T.encode(box, "pixor", reference=[9.5, 2.5])[0]
    assert p == pytest.approx([0.5, -0.5, math.log(4), math.log(1.6), 1.0, 0.0], abs=1e-12)
    assert T.get_encoding("centerpoint") is T.ENCODINGS["log-size"]
    with pytest.raises(ValueError, match="unknown encoding 'yolo'"):
        T.get_encoding("yolo")


# ----------------------------------------------------------------------------- Monte-Carlo


YAWS = [0.3, math.pi - 0.01, -math.pi + 0.005, math.pi / 2, -math.pi / 2]


@pytest.mark.parametrize("yaw", YAWS)
@pytest.mark.parametrize("model", ["bev", "3d"])
def test_propagation_matches_monte_carlo_of_a_posterior(model, yaw):
    """Dense, two-face posterior (small Σ): every encoding's covariance within 3 % of sampling φ."""
    box = np.array([12.0, 4.0, -0.8, 4.2, 1.7, 1.5, yaw])
    pts = face_points(box, ["-x", "-y", "+z"], 60, noise=0.03, seed=2)
    assert_matches_mc(box, posterior(box, pts, model).cov, model)


@pytest.mark.parametrize("yaw", YAWS)
def test_propagation_matches_monte_carlo_of_a_scaled_prior(yaw):
    """No points: the class prior, scaled to a small covariance (std ≈ 0.2× the prior's)."""
    box = np.array([30.0, -5.0, -0.7, 3.9, 1.6, 1.5, yaw])
    prior = ClassPrior(0.25, 0.44, 0.10, 0.10, 0.1745)
    for model in ("bev", "3d"):
        assert_matches_mc(box, prior_covariance(box, prior, 1.0, model) * 0.05, model)


def test_propagation_matches_monte_carlo_of_a_correlated_covariance():
    rng = np.random.default_rng(7)
    for model, p in (("bev", 6), ("3d", 8)):
        A = rng.normal(0, 0.03, (p, p))
        cov = A @ A.T + 1e-5 * np.eye(p)
        for yaw in (1.2, math.pi / 2, -math.pi + 0.02):
            assert_matches_mc(np.array([8.0, 1.0, -0.5, 4.5, 1.9, 1.6, yaw]), cov, model)


def test_sin_cos_first_order_at_ninety_degrees():
    """At yaw = π/2 sin has no first-order variance (MC: ~s⁴/2); cos carries the whole s²."""
    box = np.array([10.0, 0.0, 0.0, 4.0, 1.7, 1.5, math.pi / 2])
    s = 0.02
    cov_y = np.diag([0.01, 0.01, 0.01, 0.01, 0.01, 0.01, s * s])[None]
    P = T.propagate(box[None], cov_y, "log-size")[0]
    assert P[6, 6] == pytest.approx(0.0, abs=1e-18)
    assert P[7, 7] == pytest.approx(s * s, rel=1e-12)
    exact_sin = (1 - math.exp(-s * s)) ** 2 / 2  # Gaussian yaw: var sin(π/2 + e)
    assert exact_sin < 1e-3 * s * s


def test_bev_model_targets_without_z_and_h_are_nan():
    box = np.array([10.0, 0.0, 0.0, 4.0, 1.7, 1.5, 0.2])
    cov = T.box_covariance_from_phi(box[None], np.eye(6)[None] * 1e-3, "bev")
    P = T.propagate(box[None], cov, "residual", anchor_sizes=ANCHOR, available=T.available_params("bev"))[0]
    names = T.ENCODINGS["residual"].targets
    nan_rows = {names[i] for i in range(7) if np.isnan(P[i, i])}
    assert nan_rows == {"zt", "dzt"}
    assert np.isnan(P[2]).all() and np.isnan(P[:, 5]).all()
    assert np.all(np.isfinite(P[np.ix_([0, 1, 3, 4, 6], [0, 1, 3, 4, 6])]))


# ----------------------------------------------------------------------------- directions


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_dense_near_object_has_smaller_sigma_p_than_far_sparse_in_every_encoding(model):
    near = np.array([12.0, 3.0, -0.8, 4.2, 1.7, 1.5, 0.5])
    far = np.array([55.0, 14.0, -0.8, 4.2, 1.7, 1.5, 0.5])
    dense = posterior(near, face_points(near, ["-x", "-y"], 150, noise=0.03, seed=4), model)
    sparse = posterior(far, face_points(far, ["-x"], 5, noise=0.03, seed=5), model)
    for enc in ENCODINGS:
        stds = []
        for post in (dense, sparse):
            cov_y = T.box_covariance_from_phi(post.box[None], post.cov[None], model)
            P = T.propagate(post.box[None], cov_y, enc, anchor_sizes=ANCHOR, available=T.available_params(model))
            stds.append(T.target_std(P)[0])
        ok = ~np.isnan(stds[0])
        assert ok.sum() >= 5
        assert np.all(stds[0][ok] < stds[1][ok]), (enc, stds)


def test_heuristics_rank_objects_as_defined():
    n = np.array([0, 1, 5, 10, 50, 500])
    f = T.num_points_scale(n)
    assert f[0] == 1.0 and np.all(np.diff(f) < 0)  # no points = the prior; more points, smaller
    half = C.HEURISTIC_NUM_POINTS_HALF
    assert T.num_points_scale([half])[0] == pytest.approx(0.5)
    assert f[-1] == pytest.approx(half / 500, rel=0.03)  # ∝ 1/n for many points
    iou = np.array([0.0, 0.2, 0.5, 0.9, 1.0])
    h = T.hull_iou_scale(iou)
    assert h[0] == 1.0 and np.all(np.diff(h) < 0) and h[-1] == C.HEURISTIC_HULL_IOU_FLOOR
    prior = np.tile([0.25, 0.25, 0.25, 0.44, 0.10, 0.10, 0.1745], (len(n), 1))
    box = np.tile([20.0, 1.0, -0.8, 4.0, 1.7, 1.5, 0.7], (len(n), 1))
    cov_y = T.heuristic_box_covariance(T.prior_box_variance(prior, 2.0), f)
    assert np.allclose(np.diagonal(cov_y, axis1=1, axis2=2)[0], np.square(prior[0]) / 2.0)
    for enc in ENCODINGS:
        std = T.target_std(T.propagate(box, cov_y, enc, anchor_sizes=ANCHOR))
        assert np.all(np.diff(std, axis=0) < 0)  # more points → smaller σ_p, every target
    with pytest.raises(ValueError):
        T.hull_iou_scale([1.2])
    with pytest.raises(ValueError):
        T.num_points_scale([-1])


def test_parse_source():
    assert T.parse_source("model").kind == "model"
    assert T.parse_source("num-points").kind == "num_points"
    s = T.parse_source("fixed:0.01")
    assert s.kind == "fixed" and s.value == 0.01 and str(s) == "fixed:0.01"
    for bad in ("fixed:-1", "fixed:abc", "fixed:0", "nll"):
        with pytest.raises(ValueError):
            T.parse_source(bad)
    cov = T.fixed_target_covariance(3, "pixor", 0.04)
    assert cov.shape == (3, 6, 6) and np.allclose(T.target_std(cov), 0.2)


# ----------------------------------------------------------------------------- KLD loss


def _kl_numeric(mu_p, var_p, mu_q, var_q):
    sp = math.sqrt(var_p)

    def f(x):
        lp = -0.5 * (x - mu_p) ** 2 / var_p - 0.5 * math.log(2 * math.pi * var_p)
        lq = -0.5 * (x - mu_q) ** 2 / var_q - 0.5 * math.log(2 * math.pi * var_q)
        return math.exp(lp) * (lp - lq)

    val, err = integrate.quad(
        f, mu_p - 40 * sp, mu_p + 40 * sp, points=[mu_p, mu_q], limit=400, epsabs=1e-13, epsrel=1e-12
    )
    assert err < 1e-9
    return val


CASES = [
    (0.0, 0.04, 0.1, 0.09),
    (1.5, 0.5, -0.5, 0.01),
    (-2.0, 1e-4, -2.001, 2e-4),
    (0.3, 2.0, 0.3, 2.0),
    (10.0, 0.25, 9.0, 4.0),
]


@pytest.mark.parametrize("mu_p,var_p,mu_q,var_q", CASES)
def test_kld_equals_numerical_integration(mu_p, var_p, mu_q, var_q):
    closed = float(T.kld_loss(mu_q, math.log(var_q), mu_p, var_p))
    assert closed == pytest.approx(_kl_numeric(mu_p, var_p, mu_q, var_q), abs=1e-6)
    assert closed >= 0.0


def test_kld_is_zero_only_at_the_target():
    assert float(T.kld_loss(0.3, math.log(0.2), 0.3, 0.2)) == pytest.approx(0.0, abs=1e-15)
    assert float(T.kld_loss(0.31, math.log(0.2), 0.3, 0.2)) > 0
    assert float(T.kld_loss(0.3, math.log(0.21), 0.3, 0.2)) > 0


@pytest.mark.parametrize("mu_p,var_p,mu_q,var_q", CASES)
def test_kld_gradient_matches_finite_differences(mu_p, var_p, mu_q, var_q):
    s = math.log(var_q)
    g_mu, g_s = T.kld_loss_grad(mu_q, s, mu_p, var_p)
    h = 1e-6
    fd_mu = (T.kld_loss(mu_q + h, s, mu_p, var_p) - T.kld_loss(mu_q - h, s, mu_p, var_p)) / (2 * h)
    fd_s = (T.kld_loss(mu_q, s + h, mu_p, var_p) - T.kld_loss(mu_q, s - h, mu_p, var_p)) / (2 * h)
    assert float(g_mu) == pytest.approx(float(fd_mu), rel=1e-6, abs=1e-6)
    assert float(g_s) == pytest.approx(float(fd_s), rel=1e-6, abs=1e-6)
    # the constant dropped by include_constant=False does not change the gradient
    fd_mu0 = (
        T.kld_loss(mu_q + h, s, mu_p, var_p, include_constant=False)
        - T.kld_loss(mu_q - h, s, mu_p, var_p, include_constant=False)
    ) / (2 * h)
    assert float(fd_mu0) == pytest.approx(float(g_mu), rel=1e-6, abs=1e-6)


def test_kld_tends_to_the_nll_up_to_a_constant():
    rng = np.random.default_rng(0)
    mu_q, s = rng.normal(0, 1, 50), rng.normal(-1, 1, 50)
    target = 0.7
    nll = T.gaussian_nll(mu_q, s, target)
    for eps in (1e-4, 1e-8, 1e-12):
        diff = T.kld_loss(mu_q, s, target, eps) - nll
        const = -0.5 * (math.log(eps) + 1 + math.log(2 * math.pi))
        assert np.allclose(diff, const, atol=0.5 * eps * np.exp(-s).max() + 1e-9)
    # at σ_p = 0 exactly: the prediction-dependent part is the NLL minus ½ log 2π
    assert np.allclose(T.kld_loss(mu_q, s, target, 0.0, include_constant=False), nll - 0.5 * math.log(2 * math.pi))
    with pytest.raises(ValueError, match="infinite"):
        T.kld_loss(mu_q, s, target, 0.0)
    with pytest.raises(ValueError):
        T.kld_loss(mu_q, s, target, -1.0)


def test_kld_variance_optimum_is_the_label_variance_plus_the_error():
    """Minimising over the predicted variance: KLD → σ_q² = σ_p² + Δ², the NLL → Δ² (zero at the target)."""
    from scipy.optimize import minimize_scalar

    for delta, var_p in ((0.0, 0.01), (0.2, 0.05), (1.0, 0.3)):
        best = minimize_scalar(
            lambda s, d=delta, v=var_p: float(T.kld_loss(d, s, 0.0, v)),
            bounds=(-20, 5),
            method="bounded",
            options={"xatol": 1e-10},
        )
        assert math.exp(best.x) == pytest.approx(var_p + delta**2, rel=1e-5)
        assert float(T.kld_loss_grad(delta, math.log(var_p + delta**2), 0.0, var_p)[1]) == pytest.approx(0.0, abs=1e-12)
    # NLL at the target: the log-variance gradient stays +½, pushing σ_q² to zero without bound
    assert float(T.kld_loss_grad(0.0, -30.0, 0.0, 0.0)[1]) == pytest.approx(0.5)
