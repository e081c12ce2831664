"""The label_error score combination: which box parameters a run scores (docs/label-error.md)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from _core_synth import face_points
from labelaudit.config import ModelParams
from labelaudit.core import fit as LF

CAR = np.array([15.0, 5.0, 0.75, 4.2, 1.7, 1.5, 0.0])


def _moved(**delta: float) -> np.ndarray:
    out = CAR.copy()
    for name, value in delta.items():
        out[("cx", "cy", "cz", "length", "width", "height", "yaw").index(name)] += value
    return out


def test_bev_run_scores_the_bev_marginal_3d_run_scores_height():
    # Points on the seen faces and the roof: the 3D fit recovers a label 0.5 m too high.
    pts = face_points(CAR, ["-x", "-y", "+z", "-z"], 150, 0.03)
    too_high = _moved(cz=0.5)
    bev = LF.fit_label(too_high, pts, "Car", ModelParams(kind="bev"))
    full = LF.fit_label(too_high, pts, "Car", ModelParams(kind="3d"))
    assert bev.offsets["cz"] == pytest.approx(-0.5, abs=0.05)  # the fit sees it either way …
    assert full.label_error > 0.99  # … a 3D audit flags it,
    assert bev.label_error < 0.1  # a BEV audit does not judge cz
    # a BEV error is flagged by both, and the BEV score is chi2 with 5 degrees of freedom
    shifted = _moved(cy=-0.4)
    for params in (ModelParams(kind="bev"), ModelParams(kind="3d")):
        assert LF.fit_label(shifted, pts, "Car", params).label_error > 0.9
    assert bev.label_error == pytest.approx(chi2.cdf(bev.tolerance_distance**2, 5))
    assert full.label_error == pytest.approx(chi2.cdf(full.tolerance_distance**2, 7))


def test_a_centre_shift_outweighs_the_same_size_change():
    # Same 15 cm offset of one face: as a centre shift of the whole box it weighs more than as a
    # size change (sizes have the wider tolerance: the fit sees them least well).
    pts = face_points(CAR, ["-x", "+x", "-y", "+y", "+z"], 150, 0.02)
    centre = LF.fit_label(_moved(cx=0.15), pts, "Car", ModelParams())
    size = LF.fit_label(_moved(length=0.15), pts, "Car", ModelParams())
    exact = LF.fit_label(CAR, pts, "Car", ModelParams())
    assert exact.label_error < size.label_error < centre.label_error


def test_label_error_is_written_only_for_classes_it_is_validated_for():
    """Vehicles get a score; a pedestrian, a cyclist or a Misc box gets null (on real KITTI the
    score ranks perturbed pedestrians no better than chance), while its suggested box is still written."""
    from labelaudit import constants as C
    from labelaudit.config import load_config
    from labelaudit.infer.rows import audit_object

    cfg = load_config(None, "kitti")
    pts = face_points(CAR, ["-x", "-y"], 80, 0.03)
    car = audit_object(CAR, pts, "Car", cfg)
    assert isinstance(car["label_error"], float)
    for name in ("Pedestrian", "Cyclist", "Misc"):
        assert name not in C.LABEL_ERROR_CLASSES
        row = audit_object(CAR, pts, name, cfg)
        assert row["label_error"] is None and np.isfinite(row["fit_cx"]) and row["status"] == "ok"


# --- the seen faces' gaps (docs/label-error.md, "Sizes: the seen faces' gaps") ------------------------

BEHIND = np.array([0.0, 5.0, 1.7])  # the sensor straight behind CAR: only its −x face is seen
BESIDE = np.array([15.0, 0.0, 1.7])  # the sensor beside CAR: only its −y face is seen


def _lower_body(faces, n=400, noise=0.01, seed=0):
    """Points of CAR's given faces (its lower body among them: face_points spreads them over the height)."""
    return face_points(CAR, faces, n, noise, seed=seed)


def test_face_gaps_known_answer():
    pts = face_points(CAR, ["-x", "-y"], 400, 0.0)
    gaps, counts = LF.face_gaps(CAR, pts, np.zeros(3))
    # seen from the origin: −x and −y are seen (the sensor is beyond their planes), +x and +y are not
    assert gaps[0] == pytest.approx(0.0, abs=1e-9) and gaps[2] == pytest.approx(0.0, abs=1e-9)
    assert np.isnan(gaps[1]) and np.isnan(gaps[3])
    # only the lower body counts: FREE_SPACE_SLAB above the bottom (0.25 m to 0.4 × 1.5 m), ~23 % of a face
    assert 0.15 * 400 < counts[0] < 0.32 * 400
    # a label 0.3 m longer and 0.2 m wider about the centre: each seen face lies half of that beyond its points
    gaps, _ = LF.face_gaps(_moved(length=0.3, width=0.2), pts, np.zeros(3))
    assert gaps[0] == pytest.approx(0.15, abs=1e-9) and gaps[2] == pytest.approx(0.10, abs=1e-9)
    # 0.2 m shorter: the points lie outside the −x face (negative depth)
    gaps, _ = LF.face_gaps(_moved(length=-0.2), pts, np.zeros(3))
    assert gaps[0] == pytest.approx(-0.1, abs=1e-9)
    # the FACE_GAP_QUANTILE of the depths: a few points outside the surface (mirrors, noise) do not move it
    stray = CAR[:3] + np.array([[-2.2, 0.0, -0.3]] * 3)  # 0.1 m behind the −x face, in the lower body
    gaps_stray, _ = LF.face_gaps(CAR, np.vstack([pts, stray]), np.zeros(3))
    assert gaps_stray[0] == pytest.approx(0.0, abs=1e-9)
    # fewer than FACE_GAP_MIN_POINTS points on a face: no gap
    gaps, counts = LF.face_gaps(CAR, pts[:1], np.zeros(3))
    assert np.all(np.isnan(gaps))


@pytest.mark.parametrize(
    "sensor, faces, field",
    [(BEHIND, ["-x"], "length"), (BESIDE, ["-y"], "width")],
    ids=["length-seen-from-behind", "width-seen-from-the-side"],
)
def test_a_size_error_on_the_seen_face_orders_perfect_slight_bad(sensor, faces, field):
    pts = _lower_body(faces)
    params = ModelParams()

    def score(delta):
        return LF.fit_label(_moved(**{field: delta}), pts, "Car", params, sensor_origin=sensor).label_error

    # too long / too wide about the centre: the seen face lies beyond its points by half the error
    assert score(0.0) < score(0.25) < score(0.5)
    # too short / too narrow: the points fall outside the seen face
    assert score(0.0) < score(-0.25) < score(-0.5)
    # a face 0.25 m beyond its points is (0.25 − FACE_GAP) / FACE_GAP_STD ≈ 2.9 standard deviations
    # of a right label's looseness: flagged at about 0.7; 0.25 m inside them adds the fit's own pull
    assert score(0.0) < 0.01 and score(0.5) > 0.5 and score(-0.5) > 0.9
    # without the sensor's position the faces' gaps are not known, and the fit alone does not see a
    # loose (too long) label at all — the score before the face term
    alone = LF.fit_label(_moved(**{field: 0.5}), pts, "Car", params).label_error
    assert alone < 0.01


def test_a_face_never_seen_gives_no_evidence():
    # Seen from behind, the car's far end (+x face) is hidden by the car itself: a label 0.4 m too
    # long *at that end* has the same seen-face gaps as the right label, and is not flagged.
    pts = _lower_body(["-x"])
    far_end = _moved(cx=0.2, length=0.4)
    right = LF.fit_label(CAR, pts, "Car", ModelParams(), sensor_origin=BEHIND)
    wrong = LF.fit_label(far_end, pts, "Car", ModelParams(), sensor_origin=BEHIND)
    assert np.allclose(wrong.face_gaps, right.face_gaps, equal_nan=True)
    assert np.isfinite(right.face_gaps[0]) and np.all(np.isnan(np.asarray(right.face_gaps)[1:]))
    assert wrong.label_error < 0.1
    # the same 0.4 m at the seen end is found
    near_end = _moved(cx=-0.2, length=0.4)
    assert LF.fit_label(near_end, pts, "Car", ModelParams(), sensor_origin=BEHIND).label_error > 0.9


def test_the_score_adds_the_seen_faces_as_degrees_of_freedom():
    pts = _lower_body(["-x", "-y"])
    for label in (CAR, _moved(length=0.3), _moved(width=-0.3, cy=0.1)):
        for kind, k in (("bev", 5), ("3d", 7)):
            fit = LF.fit_label(label, pts, "Car", ModelParams(kind=kind), sensor_origin=np.zeros(3))
            m = int(np.isfinite(fit.face_gaps).sum())
            assert m == 2
            want = chi2.cdf(fit.tolerance_distance**2 + fit.face_gap_distance**2, k + m)
            assert fit.label_error == pytest.approx(want, abs=1e-12)
    # non-vehicles (no solid lower body) get no face term
    ped = LF.fit_label(CAR, pts, "Pedestrian", ModelParams(), sensor_origin=np.zeros(3))
    assert np.all(np.isnan(ped.face_gaps)) and ped.face_gap_distance == 0.0


def test_face_gaps_count_the_lower_body_above_the_local_ground():
    # The kernel's slab selection equals the NumPy form (ground_heights of the free space's plane):
    # the gaps of the points within FREE_SPACE_SLAB above a sloped ground are those of that subset.
    from labelaudit.core.freespace import FreeSpace, ground_heights

    rng = np.random.default_rng(3)
    pts = face_points(CAR, ["-x", "-y"], 300, 0.01, seed=3)
    pts = np.vstack([pts, CAR[:3] + rng.uniform(-2.5, 2.5, (200, 3))])  # clutter at every height
    ground = np.array([0.05, 0.03, -0.02, 0.0])  # 3 % and 2 % slopes, 5 cm up at the label's centre
    fs = FreeSpace(np.zeros(3), np.zeros((0, 3)), ground, CAR[:2].copy(), (0.25, 0.6), 0.1)
    h = ground_heights(pts, fs.ground, fs.ref)
    lower = pts[(h >= 0.25) & (h <= 0.6)]
    got, counts = LF.face_gaps(CAR, pts, np.zeros(3), fs)
    # the same points with a flat ground far below: every one of them is in the slab
    flat = FreeSpace(
        np.zeros(3), np.zeros((0, 3)), np.array([-100.0, 0.0, 0.0, 0.0]), CAR[:2].copy(), (0.0, 200.0), 0.1
    )
    want, want_counts = LF.face_gaps(CAR, lower, np.zeros(3), flat)
    assert np.array_equal(got, want, equal_nan=True) and np.array_equal(counts, want_counts)
    assert 0 < counts.sum() < len(pts)


def test_the_row_names_the_seen_face_furthest_from_a_right_labels():
    # A label 0.4 m too long seen from behind: its rear face lies 0.2 m beyond the points, and the
    # row says so (the suggested box keeps the label's length: deep points do not pull a face in).
    from labelaudit.config import resolve_config
    from labelaudit.infer.rows import audit_object

    pts = _lower_body(["-x"])
    too_long = _moved(length=0.4)
    fit = LF.fit_label(too_long, pts, "Car", ModelParams(), sensor_origin=BEHIND)
    assert fit.face_gap == pytest.approx(0.2, abs=0.03) and fit.label_error > 0.3
    row = audit_object(too_long, pts, "Car", resolve_config(None, "kitti"), BEHIND)
    assert row["face_gap"] == pytest.approx(fit.face_gap)
    # the most-off face is chosen by its distance from FACE_GAP, and its sign is kept
    two = LF.fit_label(
        _moved(length=-0.3, width=0.1), _lower_body(["-x", "-y"]), "Car", ModelParams(), sensor_origin=np.zeros(3)
    )
    assert two.face_gap == pytest.approx(-0.15, abs=0.03)
    # no side face seen (the sensor's position unknown): null
    assert np.isnan(LF.fit_label(too_long, pts, "Car", ModelParams()).face_gap)


def test_face_gap_is_the_order_statistic_of_the_registered_depths():
    """Each seen face's gap is the FACE_GAP_QUANTILE order statistic (rank ⌊q (n − 1)⌋, ascending) of
    the depths of the points registered to it, here computed by a full sort in NumPy."""
    from labelaudit import constants as C

    rng = np.random.default_rng(11)
    for trial in range(20):
        box = _moved(yaw=rng.uniform(-0.2, 0.2))
        pts = face_points(box, ["-x", "-y"], int(rng.integers(5, 200)), 0.05, seed=trial)
        pts = pts[(pts[:, 2] > box[2] - 0.5 * box[5] + C.FREE_SPACE_SLAB[0] + 0.01)]
        pts = pts[pts[:, 2] < box[2] - 0.5 * box[5] + C.FREE_SPACE_SLAB[1] * box[5] - 0.01]  # all in the lower body
        gaps, counts = LF.face_gaps(box, pts, np.zeros(3))
        c, s = np.cos(box[6]), np.sin(box[6])
        q = pts[:, :2] - box[:2]
        lx, ly = c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1]
        ex, ey = np.abs(lx) - box[3] / 2, np.abs(ly) - box[4] / 2
        face = np.where(ex >= ey, np.where(lx > 0, 1, 0), np.where(ly > 0, 3, 2))
        depth = -np.where(ex >= ey, ex, ey)
        bx, by = -c * box[0] - s * box[1], s * box[0] - c * box[1]  # the sensor (the origin) in the box frame
        seen = (-bx > box[3] / 2, bx > box[3] / 2, -by > box[4] / 2, by > box[4] / 2)
        assert seen[0] and seen[2]
        for f in (0, 2):  # the faces the sensor sees
            dep = np.sort(depth[face == f])
            assert counts[f] == len(dep)
            if len(dep) >= C.FACE_GAP_MIN_POINTS:
                assert gaps[f] == dep[int(C.FACE_GAP_QUANTILE * (len(dep) - 1))]
            else:
                assert np.isnan(gaps[f])


def test_face_gap_is_the_first_seen_gap_furthest_from_a_right_labels():
    """face_gap: of the non-NaN gaps, the first one furthest from FACE_GAP (ties: the earlier face);
    NaN when none is seen."""
    import dataclasses
    import math

    from labelaudit import constants as C

    fit = LF.fit_label(CAR, _lower_body(["-x"]), "Car", ModelParams())
    g0 = C.FACE_GAP
    cases = [
        ((g0 + 0.25, g0 - 0.25, math.nan, math.nan), g0 + 0.25),  # equally far: the first
        ((math.nan, g0 - 0.1, g0 + 0.3, g0 - 0.3), g0 + 0.3),
        ((math.nan,) * 4, math.nan),
        ((g0, math.nan, g0, math.nan), g0),
    ]
    rng = np.random.default_rng(1)
    for _ in range(200):
        gaps = tuple(float(v) if rng.random() < 0.7 else math.nan for v in rng.normal(g0, 0.2, 4))
        seen = [v for v in gaps if v == v]
        cases.append((gaps, max(seen, key=lambda v: abs(v - g0)) if seen else math.nan))
    for gaps, want in cases:
        got = dataclasses.replace(fit, face_gaps=gaps).face_gap
        assert (got == want) or (math.isnan(got) and math.isnan(want)), gaps
