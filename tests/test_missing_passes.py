"""The compiled passes of the missing-label search against what they stand for: the opening's
square minimum against a brute-force one, the 3 × 3 sorting network against a sort, the exact
reciprocal against a division, and the ground grid's floors against known heights."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from labelaudit import constants as C
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


def test_the_ground_grid_runs_the_sorting_network_in_its_order():
    # the ground pass spells the network out (in registers); it must be _SORT9's pairs, in order
    import inspect
    import re

    src = inspect.getsource(M._ground_grid.py_func if hasattr(M._ground_grid, "py_func") else M._ground_grid)
    pairs = [
        (int(a), int(b))
        for a, b, a2, b2, a3, b3 in re.findall(r"v(\d), v(\d) = min\(v(\d), v(\d)\), max\(v(\d), v(\d)\)", src)
        if a == a2 == a3 and b == b2 == b3
    ]
    assert pairs == [tuple(p) for p in M._SORT9.tolist()]


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


def _ground(
    xyz: np.ndarray,
    rank: int = 3,
    reach: int = 2,
    wide: int = 2,
    min_cells: float = 0.0,
    half: int = 10,
    share: float = 0.0,
) -> np.ndarray:
    ground, _, _ = M._ground_grid(
        M._four_columns(np.ascontiguousarray(xyz, dtype=np.float32)),
        0.0,
        0.0,
        0.0,
        -float(half),
        -float(half),
        1.0,
        M._exact_inverse(1.0),
        2 * half,
        2 * half,
        30.0**2,
        rank,
        share,
        360,
        1.5,
        math.tan(math.radians(-2.0)),
        reach,
        math.radians(1.5),
        wide,
        min_cells,
        0.3,
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


@pytest.mark.parametrize("rank", [1, 2, 3])
def test_a_cells_floor_is_its_rank_th_lowest_for_every_rank_the_grid_keeps(rank):
    heights = np.array([-1.0, -3.0, -1.5, -1.2, -2.0])
    cx, cy = np.meshgrid(np.arange(-10, 10) + 0.5, np.arange(-10, 10) + 0.5, indexing="ij")
    xyz = np.array([(x, y, z) for x, y in zip(cx.ravel(), cy.ravel()) for z in heights])
    xyz = xyz[np.hypot(xyz[:, 0], xyz[:, 1]) > 3.0]
    ground = _ground(xyz, rank=rank)
    seen = np.isfinite(ground)
    assert seen.sum() > 300 and np.all(ground[seen] == np.float32(np.sort(heights)[rank - 1]))


def test_a_rank_beyond_the_three_lowest_kept_is_refused():
    with pytest.raises(ValueError, match="rank"):
        _ground(np.array([[5.0, 5.0, -1.0]]), rank=4)


def _frame_points(seed: int) -> np.ndarray:
    from labelaudit.sim.dataset import simulate_frame

    return simulate_frame(0, seed=seed, drop_fraction=0.3).points


@pytest.mark.parametrize("seed", [3, 8])
def test_the_occupancy_passing_over_whole_runs_keeps_every_band_return(seed):
    # a simulated frame's returns come in runs of one ground cell (along a beam): the occupancy pass
    # skips a run whose highest return lies under the band or whose lowest lies above it. Against
    # every return looked at one by one (runs of one return, each taking its cell from x, y): the
    # same band returns, in the same order, the same counts
    pts = _frame_points(seed)
    xyz = pts[:, :3]
    half = 40
    out = M._ground_grid(
        M._four_columns(pts),
        0.0,
        0.0,
        1.73,
        -float(half),
        -float(half),
        1.0,
        1.0,
        2 * half,
        2 * half,
        38.0**2,
        3,
        0.05,
        360,
        1.5,
        math.tan(math.radians(-2.0)),
        4,
        math.radians(1.5),
        12,
        0.25 * 81,
        0.3,
    )
    ground, runs = out[0], out[2]
    start, code, _ = runs
    assert len(code) < len(xyz) / 5  # long runs: most returns follow one of their own cell
    inside = np.zeros(len(xyz), dtype=np.int64) - 1
    for r, c in enumerate(code):
        inside[start[r] : start[r + 1]] = -1 if c == -1 else -2
    single = (np.arange(len(xyz) + 1, dtype=np.int64), inside, np.zeros((len(xyz), 2)))
    cell = C.MISSING_CELL
    args = (0.0, 0.0, 9.0, 36.0**2, ground, -float(half), -float(half), 1.0, 1.0)
    mask = np.zeros((int(2 * half / cell), int(2 * half / cell)), dtype=np.uint8)
    rest = (mask, -float(half), -float(half), cell, 0.3, 4.4, 6.0)
    grids = [(np.zeros(mask.shape, dtype=np.int32), np.zeros(mask.shape, dtype=np.int32)) for _ in range(2)]
    fast = M._occupancy(xyz, runs, *args, *rest, *grids[0])
    slow = M._occupancy(xyz, single, *args, *rest, *grids[1])
    assert len(fast[0]) > 200  # the frame's vehicles and clutter are in the band
    for a, b in zip(fast + grids[0], slow + grids[1], strict=True):
        assert np.array_equal(a, b)


def test_the_ground_pass_reads_the_frames_own_rows_of_four_and_a_copy_of_any_other_layout():
    pts = _frame_points(3)  # x, y, z, intensity, float32 (a KITTI scan)
    assert M._four_columns(pts) is pts  # no copy of the frame
    xyz = pts[:, :3].astype(np.float64)
    rows = M._four_columns(xyz)
    assert rows.shape == (len(xyz), 4) and rows.dtype == np.float64 and rows.flags.c_contiguous
    assert np.array_equal(rows[:, :3], xyz)
    args = (0.0, 0.0, 1.73, -40.0, -40.0, 1.0, 1.0, 80, 80, 38.0**2, 3, 0.05, 360, 1.5)
    args += (math.tan(math.radians(-2.0)), 4, math.radians(1.5), 12, 0.25 * 81, 0.3)
    ground, top, _ = M._ground_grid(pts, *args)
    other = pts.copy()
    other[:, 3] = -7.0  # the fourth column is not read
    for same in (other, rows, M._four_columns(np.asfortranarray(pts[:, :3]))):
        g, t, _ = M._ground_grid(same, *args)
        assert np.array_equal(g, ground) and np.array_equal(t, top)
    with pytest.raises(ValueError, match="rows of 4"):
        M._ground_grid(np.ascontiguousarray(pts[:, :3]), *args)


def test_a_dozen_returns_under_the_road_in_a_cell_of_hundreds_are_not_its_floor():
    # the road at −1.7 m, 300 returns in every cell; one cell 6 m from the sensor also holds 12
    # returns 0.8 m below the road (its mirror image of a number plate): with the rank alone they are
    # that cell's floor and the ground of the 3 × 3 cells around it; with the share they are ignored
    cx, cy = np.meshgrid(np.arange(-10, 10) + 0.5, np.arange(-10, 10) + 0.5, indexing="ij")
    road = np.repeat(np.c_[cx.ravel(), cy.ravel(), np.full(cx.size, -1.7)], 300, axis=0)
    road = road[np.hypot(road[:, 0], road[:, 1]) > 3.0]
    ghosts = np.c_[np.full(12, 6.5), np.full(12, 1.5), np.linspace(-2.55, -2.45, 12)]
    xyz = np.vstack([road, ghosts])
    pit = (slice(15, 18), slice(10, 13))  # the 3 × 3 cells around the one at (6.5, 1.5)
    assert np.all(_ground(xyz)[pit] == np.float32(-2.55 + 0.1 * 2 / 11))  # the third lowest ghost
    shared = _ground(xyz, share=0.05)
    seen = np.isfinite(shared)
    assert np.all(shared[seen] == np.float32(-1.7))
    assert np.array_equal(shared, _ground(road, share=0.05))  # as if they were not there
    assert np.array_equal(_ground(road, share=0.05), _ground(road))  # a cell whose floor is the road keeps it
    # the returns in long runs of one cell (as above) or shuffled (runs of one return): the same floors
    rng = np.random.default_rng(2)
    assert np.array_equal(_ground(xyz[rng.permutation(len(xyz))], share=0.05), shared)
    # a cell of few returns keeps the rank rule (the share of 5 returns is less than 3 of them)
    few = np.vstack([road[np.hypot(road[:, 0] - 6.5, road[:, 1] - 1.5) > 1.0], [[6.5, 1.5, -1.7]] * 2, ghosts[:3]])
    assert _ground(few, share=0.05)[16, 11] == np.float32(ghosts[2, 2])


def _cells(rows: range, cols: range, heights, half: int = 20) -> list:
    """Returns at the given heights at the centre of every 1 m cell of the grid anchored at (−half, −half)."""
    return [(i - half + 0.5, j - half + 0.5, z) for i in rows for j in cols for z in heights]


def _without(points: list, rows: range, cols: range, half: int = 20) -> list:
    return [p for p in points if not (int(p[0] + half) in rows and int(p[1] + half) in cols)]


# the search's squares: a 9 m opening, a 17 m one where fewer than a quarter of the 9 m square's cells hold returns
OPEN, WIDE, FEW = 4, 8, 0.25 * 81


def test_an_object_in_a_shadow_wider_than_the_opening_stands_on_the_road_past_the_shadow():
    # the road at 0 all around, a 13 × 13 m shadow (nothing seen) holding a car 4 × 2 m whose
    # lowest returns are 0.7 m up: the 9 m opening's squares around it see only the car's cells
    shadow_i, shadow_j = range(24, 37), range(14, 27)
    car_i, car_j = range(28, 32), range(19, 21)
    road = _without(_cells(range(40), range(40), [0.0] * 3), shadow_i, shadow_j)
    xyz = np.array(road + _cells(car_i, car_j, [0.7, 1.0, 1.3, 1.5]))
    xyz = xyz[np.hypot(xyz[:, 0], xyz[:, 1]) > 2.0]
    car = (slice(28, 32), slice(19, 21))
    # the opening alone: the car's own floor (1.3, its third lowest) is taken for the road under it
    before = _ground(xyz, reach=OPEN, half=20)
    assert np.all(before[car] > 0.5)
    # the wider opening where the square holds few cells with returns: the road's height
    after = _ground(xyz, reach=OPEN, wide=WIDE, min_cells=FEW, half=20)
    assert np.all(after[car] == 0.0)
    # and nowhere else does the ground change: the road's cells are the road
    seen = np.isfinite(after)
    assert np.array_equal(seen, np.isfinite(before))
    assert np.all(after[seen] == 0.0)


def test_a_raised_stretch_of_ground_seen_whole_keeps_its_height_with_the_wider_opening():
    # a 12 × 12 m platform 1 m high, wider than the 9 m opening and narrower than the 17 m one, its
    # every cell seen: its squares are full of returns, so the wider opening does not apply
    plat_i, plat_j = range(24, 36), range(4, 16)
    road = _without(_cells(range(40), range(40), [0.0] * 3), plat_i, plat_j)
    xyz = np.array(road + _cells(plat_i, plat_j, [1.0] * 3))
    xyz = xyz[np.hypot(xyz[:, 0], xyz[:, 1]) > 2.0]
    inner = (slice(25, 35), slice(5, 15))  # its edge cells stand on the road beside them (the 3 × 3 rule)
    ground = _ground(xyz, reach=OPEN, wide=WIDE, min_cells=FEW, half=20)
    assert np.all(ground[inner] == 1.0)
    # applied everywhere, the wider opening would take the platform away (why the rule asks for a shadow)
    everywhere = _ground(xyz, reach=OPEN, wide=WIDE, min_cells=82.0, half=20)
    assert np.all(everywhere[inner] == 0.0)


def _beams(ranges: np.ndarray, azimuths_deg: np.ndarray, elevations_deg: np.ndarray) -> np.ndarray:
    """Returns at ``ranges`` (E, A) (m, bird's-eye) along the rays of a sensor at the origin:
    one beam per elevation, one column per azimuth."""
    el, az = np.radians(elevations_deg)[:, None], np.radians(azimuths_deg)[None, :]
    return np.stack([ranges * np.cos(az), ranges * np.sin(az), ranges * np.tan(el)], axis=-1).reshape(-1, 3)


def test_roughness_is_the_depth_scatter_along_each_beam_and_zero_on_a_plane():
    """A flat face square to the sensor at 20 m (four beams, 0.17° apart in azimuth) lies on its
    beams' lines: 0. Every other column 0.3 m deeper (foliage's scatter): a return is 0.3 m off the
    line of its two nearest neighbours and, from the line of the two on one side of it (through the
    0.3 m step, h = 20 m · 0.17° apart), 2·0.3·h / √(h² + 0.3²) — the least of the three; farther
    away the returns are farther apart and the scatter shows more. A face that steps back 1 m
    halfway along (a body and a cabin behind glass) keeps 0: every return continues the line of its
    own side. Too few returns with beam neighbours: −1 (nothing to tell)."""
    az = np.arange(-2.0, 2.0, 0.17)
    el = np.array([-3.0, -2.6, -2.2, -1.8])
    gap, step = math.radians(0.1), math.radians(1.0)

    def rough(ranges, azimuths=az, elevations=el):
        return M._roughness(_beams(ranges, azimuths, elevations), 0.0, 0.0, 0.0, gap, step, 8)

    def face(x):  # the ranges of the plane at x along each beam
        return x / np.cos(np.radians(az))[None, :].repeat(len(el), axis=0)

    assert rough(face(20.0)) == pytest.approx(0.0, abs=1e-9)
    zigzag = 0.3 * (np.arange(len(az)) % 2)[None, :]
    h = 20.0 * math.radians(0.17)
    assert rough(face(20.0) + zigzag) == pytest.approx(0.6 * h / math.hypot(h, 0.3), rel=0.02)
    assert rough(face(20.0) + zigzag) < rough(face(60.0) + zigzag) < 0.3 + 1e-9
    assert rough(np.where(az >= 0.0, face(21.0), face(20.0))) == pytest.approx(0.0, abs=1e-9)
    # the beams are told apart by elevation: one beam of scatter among three flat ones is a quarter
    mixed = face(20.0)
    mixed[0] += zigzag[0]
    assert rough(mixed) == pytest.approx(0.0, abs=1e-9)
    assert rough((face(20.0) + zigzag)[:1, :7], az[:7], el[:1]) == -1.0  # 7 returns


def _quantile_cases():
    rng = np.random.default_rng(7)
    for n in (1, 2, 3, 5, 101, 4096, 4118, 8191):
        yield rng.normal(size=n)
        yield rng.integers(-3, 3, n) * 0.1  # ties
        yield rng.choice([0.0, -0.0, 1e-300], n)  # zeros of either sign
    with_nan = rng.normal(size=500)
    with_nan[17] = np.nan
    yield with_nan


def test_the_search_quantiles_are_numpys_bit_for_bit():
    for v in _quantile_cases():
        for qs in ((0.01, 0.99), (0.0, 1.0), (0.5, 0.25)):
            want, got = np.quantile(v, list(qs)), M._quantiles(v, qs)
            assert len(got) == len(qs)
            for w, g in zip(want.tolist(), got):
                assert (math.isnan(w) and math.isnan(g)) or (w == g and math.copysign(1, w) == math.copysign(1, g))


def test_group_statistics_are_numpys_sums_maxima_and_rectangles_per_root():
    rng = np.random.default_rng(3)
    for k in (1, 2, 7, 40):
        group = rng.integers(0, k, k)
        stats = rng.integers(0, 400, (k, 7))
        extras = rng.normal(1.0, 1.0, (k, 7))
        sums, rect, present = M._group_stats(group, stats, extras)
        assert np.array_equal(present, np.isin(np.arange(k), group))
        for row, col in ((0, 0), (1, 1), (3, 2)):
            assert np.array_equal(sums[row], np.bincount(group, weights=stats[:, col], minlength=k))
        top = np.zeros(k)
        np.maximum.at(top, group, extras[:, 0])
        assert np.array_equal(sums[2], top)
        lo, hi = np.full(k, np.iinfo(np.int64).max), np.zeros(k, dtype=np.int64)
        for r, col, f, init in (
            (0, 3, np.minimum, lo),
            (1, 4, np.maximum, hi),
            (2, 5, np.minimum, lo),
            (3, 6, np.maximum, hi),
        ):
            want = init.copy()
            f.at(want, group, stats[:, col])
            assert np.array_equal(rect[r], want)


def test_row_chains_link_fragments_within_the_gap_and_name_each_chain_by_its_first_member():
    # rectangles of cells (i0, i1, j0, j1): 0–1–2 a chain along i, 3 alone far off, 4 linked to 2 only
    rect = np.array([[0, 0, 0, 0], [3, 3, 0, 0], [6, 7, 0, 1], [40, 40, 40, 40], [9, 9, 3, 3]])
    stats = np.zeros((6, 7), dtype=np.int64)
    stats[1:, 3:] = rect  # component 0 is not among the small ones
    small = np.arange(1, 6)
    assert M._row_chains(stats, small, 3).tolist() == [0, 0, 0, 3, 0]
    assert M._row_chains(stats, small, 2).tolist() == [0, 1, 2, 3, 2]
    # against every pair looked at (the union of linked pairs, each chain named by its least position)
    rng = np.random.default_rng(5)
    lo = rng.integers(0, 30, (25, 2))
    stats = np.zeros((25, 7), dtype=np.int64)
    stats[:, 3], stats[:, 4] = lo[:, 0], lo[:, 0] + rng.integers(0, 2, 25)
    stats[:, 5], stats[:, 6] = lo[:, 1], lo[:, 1] + rng.integers(0, 2, 25)
    small = np.arange(25)
    got = M._row_chains(stats, small, 3)
    s = stats
    gap = np.maximum.reduce(
        [
            s[:, None, 3] - s[None, :, 4],
            s[None, :, 3] - s[:, None, 4],
            s[:, None, 5] - s[None, :, 6],
            s[None, :, 5] - s[:, None, 6],
        ]
    )
    reach = gap <= 3
    for _ in range(25):  # the transitive closure
        reach = reach | ((reach.astype(int) @ reach.astype(int)) > 0)
    assert np.array_equal(got, np.argmax(reach, axis=1))


def test_the_search_median_is_numpys_bit_for_bit():
    for v in _quantile_cases():
        want, got = float(np.median(v)), M._median(v)
        assert (math.isnan(want) and math.isnan(got)) or (
            want == got and math.copysign(1, want) == math.copysign(1, got)
        )
