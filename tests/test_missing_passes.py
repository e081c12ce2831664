"""The compiled passes of the missing-label search against what they stand for: the opening's
square minimum against a brute-force one, the 3 × 3 sorting network against a sort, the exact
reciprocal against a division, and the ground grid's floors against known heights."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from labelaudit.infer import missing as M


def _square_min_brute(a: np.ndarray, reach: int) -> np.ndarray:
    n0, n1 = a.shape
    out = np.empty_like(a)
    for i in range(n0):
        for j in range(n1):
            out[i, j] = a[max(0, i - reach) : i + reach + 1, max(0, j - reach) : j + reach + 1].min()
    return out


@pytest.mark.parametrize("reach", [0, 1, 2, 4, 7])
def test_square_min_is_the_lowest_value_of_each_square_inf_where_all_are_inf(reach):
    rng = np.random.default_rng(reach)
    for shape in [(1, 1), (1, 9), (9, 1), (5, 13), (24, 17)]:
        a = rng.normal(size=shape)
        a[rng.random(shape) < 0.4] = np.inf  # cells without returns
        assert np.array_equal(M._square_min(a, reach), _square_min_brute(a, reach)), (shape, reach)
    assert np.all(M._square_min(np.full((6, 4), np.inf), reach) == np.inf)


def test_the_sorting_network_sorts_every_input_of_nine():
    net = M._SORT9
    assert net.shape == (25, 2) and np.all(net[:, 0] < net[:, 1])
    # the 0-1 principle: a network that sorts all 2⁹ inputs of 0s and 1s sorts every input
    for bits in itertools.product((0.0, 1.0), repeat=9):
        v = list(bits)
        for a, b in net:
            v[a], v[b] = min(v[a], v[b]), max(v[a], v[b])
        assert v == sorted(bits), bits
    broken = net[1:]  # one comparator fewer: some input stays unsorted
    assert any(_network(broken, list(bits)) != sorted(bits) for bits in itertools.product((0.0, 1.0), repeat=9))


def _network(net: np.ndarray, v: list) -> list:
    for a, b in net:
        v[a], v[b] = min(v[a], v[b]), max(v[a], v[b])
    return v


def test_the_exact_reciprocal_multiplies_as_the_division_divides_bit_for_bit():
    rng = np.random.default_rng(0)
    d = np.concatenate([rng.normal(0.0, 50.0, 10_000), rng.uniform(-1e-310, 1e-310, 100), [0.0, -0.0, 1e300]])
    for cell in (1.0, 0.5, 0.25, 2.0, 4.0, 0.125):
        inv = M._exact_inverse(cell)
        assert inv == 1.0 / cell
        assert np.array_equal((d * inv).view(np.int64), (d / cell).view(np.int64)), cell
    for cell in (0.2, 0.3, 3.0, 1.5):  # not a power of two: the kernels divide
        assert M._exact_inverse(cell) == 0.0
    assert not np.array_equal(d * (1.0 / 0.2), d / 0.2)  # why: 1 / 0.2 is rounded


def _ground(xyz: np.ndarray, rank: int = 3) -> np.ndarray:
    ground, _ = M._ground_grid(
        np.ascontiguousarray(xyz, dtype=np.float32),
        0.0,
        0.0,
        0.0,
        -10.0,
        -10.0,
        1.0,
        M._exact_inverse(1.0),
        20,
        20,
        30.0**2,
        rank,
        360,
        1.5,
        math.tan(math.radians(-2.0)),
        2,
        math.radians(1.5),
    )
    return ground


def test_a_cells_floor_is_its_rank_th_lowest_return_whatever_their_order():
    # every cell of a flat patch holds the same five heights: its floor, and so the ground
    # everywhere on the patch, is the third lowest (two returns below the road are ignored)
    heights = np.array([-1.0, -3.0, -1.5, -1.2, -2.0])
    cx, cy = np.meshgrid(np.arange(-10, 10) + 0.5, np.arange(-10, 10) + 0.5, indexing="ij")
    xyz = np.array([(x, y, z) for x, y in zip(cx.ravel(), cy.ravel()) for z in heights])
    xyz = xyz[np.hypot(xyz[:, 0], xyz[:, 1]) > 3.0]  # not under the sensor
    ground = _ground(xyz)
    seen = np.isfinite(ground)
    assert seen.sum() > 300 and np.all(ground[seen] == np.float32(-1.5))
    rng = np.random.default_rng(1)
    for _ in range(3):  # the order the returns come in changes nothing, bit for bit
        assert np.array_equal(_ground(xyz[rng.permutation(len(xyz))]), ground)
    # cells with fewer returns than the rank: the floor is their highest
    assert np.all(_ground(xyz[xyz[:, 2] >= -1.2])[seen] == np.float32(-1.0))
