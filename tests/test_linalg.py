"""labelaudit.core.linalg: the np.linalg kernels without their wrappers — bit-identical, same errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from labelaudit.core import linalg


@pytest.mark.parametrize("p", [2, 6, 8])
def test_small_linear_algebra_is_bit_identical_to_numpy(p: int) -> None:
    rng = np.random.default_rng(p)
    for _ in range(200):
        A = rng.normal(size=(p, p)) * 10.0 ** rng.uniform(-3, 3)
        P = A @ A.T + 1e-6 * np.eye(p)
        B = rng.normal(size=(p, p))
        assert np.array_equal(linalg.inv(A), np.linalg.inv(A))
        assert np.array_equal(linalg.cholesky(P), np.linalg.cholesky(P))
        assert np.array_equal(linalg.solve(A, B), np.linalg.solve(A, B))
        w, V = linalg.eigh(P)
        w0, V0 = np.linalg.eigh(P)
        assert np.array_equal(w, w0) and np.array_equal(V, V0)


def test_errors_stay_errors() -> None:
    singular = np.ones((3, 3))
    with pytest.raises(np.linalg.LinAlgError):
        linalg.inv(singular)
    with pytest.raises(np.linalg.LinAlgError):
        linalg.solve(singular, np.eye(3))
    with pytest.raises(np.linalg.LinAlgError):
        linalg.cholesky(-np.eye(4))


def test_compiled_pairwise_sum_is_numpys_sum():
    """pairwise_sum reproduces ndarray.sum bit for bit (pairwise blocks), contiguous or strided."""
    rng = np.random.default_rng(5)
    for n in [*range(0, 300), 1000, 1023, 1024, 1700, 8191, 8192, 8193, 50001]:
        x = rng.normal(size=(n, 2)) * 10.0 ** rng.uniform(-6, 6, size=(n, 2))
        assert linalg.pairwise_sum(x[:, 0]) == x[:, 0].sum() and linalg.pairwise_sum(x.ravel()) == x.sum(), n


@pytest.mark.parametrize("p", [2, 6, 8])
def test_compiled_symmetric_root_equals_the_lapack_form(p: int) -> None:
    """sqrt_psd_kernel (Jacobi rotations) gives LAPACK's V √max(Λ, 0) Vᵀ within what the root's
    conditioning allows (an eigenvalue λ off by ε·λ_max moves √λ by ε·λ_max / 2√λ), exactly
    symmetric, squaring back to the matrix; singular and repeated-eigenvalue matrices included,
    and its lower triangle is what it reads (as eigh_lo)."""
    rng = np.random.default_rng(10 + p)
    for trial in range(300):
        A = rng.normal(size=(p, p)) * 10.0 ** rng.uniform(-3, 1, size=p)
        P = A @ A.T
        if trial % 4 == 0:  # singular
            P[:, 0] = P[0, :] = 0.0
        if trial % 5 == 0:  # repeated eigenvalues
            Q, _ = np.linalg.qr(rng.normal(size=(p, p)))
            lam = np.repeat(rng.uniform(0.1, 2.0, (p + 1) // 2), 2)[:p]
            P = (Q * lam) @ Q.T
        lam, V = np.linalg.eigh(P)
        want = (V * np.sqrt(np.maximum(lam, 0.0))) @ V.T
        upper_garbage = P + np.triu(rng.normal(size=(p, p)), 1)
        got = linalg.sqrt_psd_kernel(upper_garbage)
        scale = np.sqrt(max(lam.max(), 1e-300))
        small = np.sqrt(np.clip(lam, 0.0, None)[np.clip(lam, 0.0, None) > 1e-14 * lam.max()].min())
        assert np.array_equal(got, got.T)
        assert np.abs(got - want).max() <= 1e-13 * scale * max(1.0, scale / small), trial
        np.testing.assert_allclose(got @ got, P, atol=1e-12 * lam.max())
    assert np.isnan(linalg.sqrt_psd_kernel(np.full((p, p), np.nan))).all()


def test_matmul_kernel_sums_each_entry_in_order_and_takes_transposes() -> None:
    """The small product the compiled kernels share: each entry is the in-order sum of its
    products (as a Python loop writes it), so it equals a @ b to rounding and a loop exactly."""
    rng = np.random.default_rng(7)
    a, b = rng.normal(size=(6, 4)), rng.normal(size=(4, 5))
    out = np.empty((6, 5))
    linalg.matmul_kernel(a, b, out)
    loop = np.array([[sum((a[i, k] * b[k, j] for k in range(4)), 0.0) for j in range(5)] for i in range(6)])
    assert np.array_equal(out, loop)
    np.testing.assert_allclose(out, a @ b, rtol=1e-14, atol=1e-14)
    square = rng.normal(size=(5, 5))
    t = np.empty((5, 5))
    linalg.matmul_kernel(square.T, square, t)  # EᵀW as the prior terms form it: a transposed view
    tloop = [[sum((square[k, i] * square[k, j] for k in range(5)), 0.0) for j in range(5)] for i in range(5)]
    assert np.array_equal(t, np.array(tloop))
    np.testing.assert_allclose(t, square.T @ square, rtol=1e-14, atol=1e-14)


def test_exp_kernel_is_within_one_ulp_of_libm() -> None:
    """exp_kernel against math.exp: ≤ 1 ulp over the whole range it serves (the responsibilities'
    exponents are ≤ 0), exact at 0, 0 below e^−708 (no subnormal results), NaN and ±inf as exp;
    a wrong coefficient or reduction constant fails by many ulps."""
    rng = np.random.default_rng(5)
    x = np.concatenate(
        [
            -np.abs(rng.standard_normal(5000)) * rng.choice([1e-6, 0.1, 1.0, 10.0, 100.0], 5000),
            rng.uniform(-708.0, 709.0, 20000),
            [0.0, -0.0, -0.5 * math.log(2.0), 0.5 * math.log(2.0), -708.0, 709.0, 1e-300, -1e-300],
        ]
    )
    out = np.empty_like(x)
    linalg.exp_kernel(x, out, np.empty(x.size, dtype=np.int64))
    want = np.array([math.exp(v) for v in x])
    assert np.all(np.abs(out - want) <= np.spacing(want))
    assert out[x == 0.0].tolist() == [1.0, 1.0]
    special = np.array([-708.5, -745.0, -800.0, -np.inf, np.nan, 710.0, np.inf])
    got = np.empty_like(special)
    linalg.exp_kernel(special, got, np.empty(special.size, dtype=np.int64))
    assert got[:4].tolist() == [0.0, 0.0, 0.0, 0.0] and math.isnan(got[4]) and got[5:].tolist() == [math.inf] * 2
