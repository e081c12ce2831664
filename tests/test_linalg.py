"""labelaudit.core.linalg: the np.linalg kernels without their wrappers — bit-identical, same errors."""

from __future__ import annotations

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
