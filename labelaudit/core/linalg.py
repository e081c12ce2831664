"""Small dense linear algebra (matrices up to 8×8) for the per-box model, at a fraction of the call cost.

``np.linalg`` wraps each LAPACK call in type checks, an ``errstate`` context and result
wrapping, which on a 6×6 matrix cost several times the arithmetic (a box runs about ten such
calls). These functions call the same NumPy gufuncs (``numpy.linalg._umath_linalg``, float64
signature) directly, so their results are bit-identical to ``np.linalg`` (a test checks); they
fall back to ``np.linalg`` when that module is not there. Errors stay errors: a matrix that is not
positive definite or is singular raises, as in ``np.linalg``. It also holds :func:`pairwise_sum`,
NumPy's summation order, and :func:`nan_max` / :func:`nan_min` (``np.maximum`` / ``np.minimum`` of two
floats), for compiled kernels that must reproduce NumPy's results, and :func:`exp_kernel`, an
``exp`` of a whole array that the compiler vectorises (numba's cache does not see a
change here from the kernels of other modules that inline them: clear their ``__pycache__/*.nb*``
after editing these). No I/O.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from labelaudit.kernels import kernel

try:  # the gufuncs behind np.linalg (present in NumPy 1.x and 2.x)
    from numpy.linalg import _umath_linalg as _UL
except ImportError:  # pragma: no cover - another NumPy layout: use the public API
    _UL = None

FloatArray = NDArray[np.float64]

__all__ = [
    "cholesky",
    "cholesky_kernel",
    "eigh",
    "exp_kernel",
    "inv",
    "nan_max",
    "nan_min",
    "pairwise_sum",
    "solve",
    "spd_inverse_kernel",
    "sqrt_psd_kernel",
]


def inv(a: FloatArray) -> FloatArray:
    """``np.linalg.inv`` of a float64 square matrix; raises ``np.linalg.LinAlgError`` when singular."""
    if _UL is None:
        return np.linalg.inv(a)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        out = _UL.inv(a, signature="d->d")
    if out[0, 0] != out[0, 0]:  # LAPACK failed: the gufunc filled the result with NaN
        return np.linalg.inv(a)  # raises the LinAlgError np.linalg gives (or returns what it returns)
    return out


def cholesky(a: FloatArray) -> FloatArray:
    """Lower Cholesky factor, as ``np.linalg.cholesky``; raises ``np.linalg.LinAlgError`` when ``a``
    is not positive definite."""
    if _UL is None:
        return np.linalg.cholesky(a)
    with np.errstate(invalid="ignore"):
        out = _UL.cholesky_lo(a, signature="d->d")
    if out[0, 0] != out[0, 0]:  # not positive definite: NaN-filled
        return np.linalg.cholesky(a)  # raises LinAlgError
    return out


def solve(a: FloatArray, b: FloatArray) -> FloatArray:
    """``np.linalg.solve(a, b)`` for a float64 square ``a`` and a float64 matrix ``b`` (2-D);
    raises ``np.linalg.LinAlgError`` when ``a`` is singular."""
    if _UL is None:
        return np.linalg.solve(a, b)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        out = _UL.solve(a, b, signature="dd->d")
    if out.size and out[0, 0] != out[0, 0]:
        return np.linalg.solve(a, b)
    return out


def eigh(a: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``np.linalg.eigh(a)`` (lower triangle) of a float64 symmetric matrix: eigenvalues ascending,
    eigenvectors as columns; raises ``np.linalg.LinAlgError`` when LAPACK does not converge."""
    if _UL is None:
        return np.linalg.eigh(a)
    with np.errstate(invalid="ignore"):
        w, v = _UL.eigh_lo(a, signature="d->dd")
    if w.size and w[0] != w[0]:
        return np.linalg.eigh(a)
    return w, v


@kernel
def _pairwise_block(a, lo, n):  # pragma: no cover - compiled
    """NumPy's sum of a block of n ≤ 128 elements: 8 accumulators (sequential below 8 elements)."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - n % 8:
        j = lo + i
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@kernel
def pairwise_sum(a):  # pragma: no cover - compiled
    """``a.sum()`` of a 1-D float64 array with NumPy's order of operations (0 + pairwise sum:
    halves rounded to multiples of 8 until a block has ≤ 128 elements), so compiled code can
    reproduce a NumPy total bit for bit (tests/test_linalg.py checks it). The split tree is
    walked with an explicit stack: numba's cache does not load recursive functions reliably."""
    if a.size <= 128:
        return 0.0 + _pairwise_block(a, 0, a.size)
    seg_lo = np.empty(64, dtype=np.int64)
    seg_n = np.empty(64, dtype=np.int64)
    left = np.empty(64)
    right_pending = np.zeros(64, dtype=np.bool_)  # the left half of this segment is summed
    top = 0
    seg_lo[0], seg_n[0] = 0, a.size
    while True:
        n = seg_n[top]
        if n > 128:  # split: visit the left half first
            n2 = n // 2
            n2 -= n2 % 8
            right_pending[top] = False
            top += 1
            seg_lo[top], seg_n[top] = seg_lo[top - 1], n2
            continue
        v = _pairwise_block(a, seg_lo[top], n)
        while top > 0:  # hand the sum up the tree
            top -= 1
            if not right_pending[top]:
                left[top] = v
                right_pending[top] = True
                n2 = seg_n[top] // 2
                n2 -= n2 % 8
                top += 1
                seg_lo[top], seg_n[top] = seg_lo[top - 1] + n2, seg_n[top - 1] - n2
                break
            v = left[top] + v
        else:
            return 0.0 + v


@kernel
def nan_max(a: float, b: float) -> float:  # pragma: no cover - compiled
    """np.maximum of two floats (NaN propagates)."""
    if a != a or b != b:
        return a + b
    return a if a >= b else b


@kernel
def nan_min(a: float, b: float) -> float:  # pragma: no cover - compiled
    """np.minimum of two floats (NaN propagates)."""
    if a != a or b != b:
        return a + b
    return a if a <= b else b


@kernel(error_model="numpy")
def sqrt_psd_kernel(a):  # pragma: no cover - compiled
    """The symmetric square root V √max(Λ, 0) Vᵀ of a symmetric PSD matrix (its lower triangle, as
    LAPACK's ``eigh`` reads it; small n), by cyclic Jacobi rotations.

    Compiled code cannot call NumPy's LAPACK, and a per-object LAPACK call costs more than the
    arithmetic of a 6×6 or 8×8 matrix. Jacobi's eigenvalues are accurate to a few units in the
    last place (relative to the largest), so the root differs from the LAPACK form only in its
    last bits (tests/test_linalg.py compares them); the square root itself is unique, so repeated
    eigenvalues, whose eigenvectors the two methods pick differently, do not change it. Non-finite
    input gives a non-finite result (the caller decides what that means).
    """
    n = a.shape[0]
    A = np.empty((n, n))
    for i in range(n):
        for j in range(i + 1):
            A[i, j] = a[i, j]
            A[j, i] = a[i, j]
    V = np.zeros((n, n))
    for i in range(n):
        V[i, i] = 1.0
    for sweep in range(64):
        off = 0.0
        for p in range(n):
            for q in range(p + 1, n):
                off += A[p, q] * A[p, q]
        if not off > 0.0:  # diagonal (or NaN: no rotation would help)
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = A[p, q]
                if apq == 0.0:
                    continue
                app, aqq = A[p, p], A[q, q]
                small = 100.0 * abs(apq)
                if sweep > 3 and abs(app) + small == abs(app) and abs(aqq) + small == abs(aqq):
                    A[p, q] = A[q, p] = 0.0  # below the diagonal's last bit
                    continue
                theta = (aqq - app) / (2.0 * apq)
                if abs(theta) < 1e150:
                    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                    if theta < 0.0:
                        t = -t
                else:  # θ² would overflow: t ≈ 1 / (2θ)
                    t = 0.5 / theta
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):  # A ← A J (columns p, q)
                    akp, akq = A[k, p], A[k, q]
                    A[k, p] = c * akp - s * akq
                    A[k, q] = s * akp + c * akq
                for k in range(n):  # A ← Jᵀ A (rows p, q)
                    apk, aqk = A[p, k], A[q, k]
                    A[p, k] = c * apk - s * aqk
                    A[q, k] = s * apk + c * aqk
                A[p, q] = A[q, p] = 0.0  # zero by construction of t
                for k in range(n):  # V ← V J
                    vkp, vkq = V[k, p], V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
    root = np.empty(n)
    for k in range(n):
        lam = A[k, k]
        root[k] = math.sqrt(lam) if lam > 0.0 else (lam if lam != lam else 0.0)  # NaN stays NaN
    out = np.empty((n, n))
    for i in range(n):
        for j in range(i, n):
            acc = 0.0
            for k in range(n):
                acc += V[i, k] * root[k] * V[j, k]
            out[i, j] = acc
            out[j, i] = acc
    return out


@kernel
def matmul_kernel(a, b, out):  # pragma: no cover - compiled
    """``out`` (n, m) = a (n, q) · b (q, m) of small matrices, each entry summed over q in order
    (no BLAS: the same sums wherever it is called, so the kernels that share it stay bit for bit
    reproducible). Pass a transpose as ``a.T`` or ``b.T``."""
    for i in range(a.shape[0]):
        for j in range(b.shape[1]):
            acc = 0.0
            for k in range(a.shape[1]):
                acc += a[i, k] * b[k, j]
            out[i, j] = acc


@kernel
def cholesky_kernel(M, L):  # pragma: no cover - compiled
    """The lower Cholesky factor of a small symmetric positive definite M (p, p), read from its
    lower triangle, written into L (p, p; zeros above the diagonal as given). Returns False at the
    first pivot that is not positive (M not positive definite, or NaN): L is then incomplete."""
    p = M.shape[0]
    for j in range(p):
        acc = M[j, j]
        for k in range(j):
            acc -= L[j, k] * L[j, k]
        if not acc > 0.0:
            return False
        L[j, j] = math.sqrt(acc)
        for i in range(j + 1, p):
            acc = M[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = acc / L[j, j]
    return True


@kernel
def spd_inverse_kernel(M, out):  # pragma: no cover - compiled
    """``out`` (p, p) = M⁻¹ of a small symmetric positive definite M (p, p), read from its lower
    triangle: the Cholesky factor L, L⁻¹ by forward substitution, L⁻ᵀL⁻¹ (symmetric by
    construction) — what ``posterior.spd_inverse`` does with LAPACK, in scalars, agreeing to
    rounding. Returns False (``out`` then undefined) when M is not positive definite."""
    p = M.shape[0]
    L = np.zeros((p, p))
    if not cholesky_kernel(M, L):
        return False
    Li = np.zeros((p, p))  # L⁻¹, lower triangular
    for j in range(p):
        Li[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, p):
            acc = 0.0
            for k in range(j, i):
                acc -= L[i, k] * Li[k, j]
            Li[i, j] = acc / L[i, i]
    for i in range(p):  # (L⁻ᵀL⁻¹)_ij = Σ_(k ≥ max(i, j)) Li[k, i] Li[k, j]
        for j in range(i + 1):
            acc = 0.0
            for k in range(i, p):
                acc += Li[k, i] * Li[k, j]
            out[i, j] = acc
            out[j, i] = acc
    return True


# exp(x) = 2^k exp(r), x = k ln 2 + r: ln 2 split as fdlibm's (k · _LN2_HI is exact for |k| < 2^11)
_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
_LOG_MAX = 709.782712893384  # ln of the largest float64
_EXP_TAYLOR = tuple(1.0 / math.factorial(j) for j in range(13, -1, -1))  # 1/13!, …, 1/1!, 1/0!


@kernel(error_model="numpy", fastmath={"contract"})
def exp_kernel(x, out, bits):  # pragma: no cover - compiled
    """``out[i] = exp(x[i])`` over 1-D float64 arrays of n values, x ≤ 709, in loops the compiler
    vectorises — ``math.exp`` is a call into libm per value, several times dearer — when ``out`` is
    not ``x`` (in place they run value by value). Within 1 ulp of libm's exp (~10 % of the values
    differ in the last bit), except that a result below e^−708 (≈ 3.3e-308, x < −708) is 0:
    subnormal numbers would cost a microcode assist per operation, here and in the sums that read
    them. exp(0) = 1 exactly, NaN gives NaN, x > ln(max float) gives inf. ``bits``: int64 scratch
    of n values.

    x = k ln 2 + r with |r| ≤ ½ ln 2 (Cody–Waite), exp(r) by its Taylor polynomial to degree 13
    (remainder < 5e-18 of the value), times 2^k written into ``bits`` as an exponent field. Its
    fused multiply-adds (``contract``) are the same on every run, ahead of time and JIT."""
    n = x.size
    for i in range(n):
        v = x[i]
        v = -708.0 if v < -708.0 else (709.0 if v > 709.0 else v)  # NaN stays NaN
        kf = math.floor(v * _LOG2E + 0.5)
        kf = 0.0 if kf != kf else kf
        r = (v - kf * _LN2_HI) - kf * _LN2_LO
        poly = 0.0
        for c in _EXP_TAYLOR:
            poly = poly * r + c
        bits[i] = (np.int64(kf) + 1023) << 52
        out[i] = poly if x[i] >= -708.0 else (0.0 if x[i] < -708.0 else poly)  # NaN: poly is NaN
    scale = bits.view(np.float64)
    for i in range(n):
        e = out[i] * scale[i]
        out[i] = math.inf if x[i] > _LOG_MAX else e
