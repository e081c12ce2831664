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
