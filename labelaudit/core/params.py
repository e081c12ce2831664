"""The model's parameter types: which model (:data:`ModelKind`), the box fields, and the parameters
of the label model, the spatial distribution and the crop.

They live in the core, beside the code that reads them, so the core never imports the layer
above it (:mod:`labelaudit.config` builds them from TOML, validates and hashes them). Defaults come
from :mod:`labelaudit.constants`; nothing here reads a file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Mapping

from labelaudit import constants as C

ModelKind = Literal["bev", "3d"]
"""``"bev"``: the box seen from above (φ of 6 entries); ``"3d"``: the full box (φ of 8 entries)."""

BOX_FIELDS: tuple[str, ...] = ("cx", "cy", "cz", "length", "width", "height", "yaw")
"""Names of the 7 box parameters, in the order of ``y``."""

SAMPLE_TABLE = Path(__file__).resolve().parent.parent / "data" / "normal_samples.npz"
"""The stored Sobol normal samples of p_G (dims 5–8, DEFAULT_NUM_SAMPLES, DEFAULT_QMC_SEED), as
:func:`labelaudit.core.spatial.generate_normal_samples` makes them: a worker process then need not
import scipy.stats (about a second each); a test checks they are identical. They change rows, so
:func:`labelaudit.config.constants_digest` hashes the file. Rebuild: ``python scripts/make_sample_table.py``."""


@dataclass(frozen=True)
class ClassPrior:
    """Prior std of one class's box parameters (metres, radians), before the weight w."""

    center: float  # std of cx, cy and cz
    length: float
    width: float
    height: float
    yaw: float


def default_priors() -> dict[str, ClassPrior]:
    """The built-in per-class priors of :data:`labelaudit.constants.DEFAULT_PRIORS`."""
    return {name: ClassPrior(**values) for name, values in C.DEFAULT_PRIORS.items()}


@dataclass(frozen=True)
class ModelParams:
    """Parameters of the generative label model (docs/method.md)."""

    kind: ModelKind = C.DEFAULT_MODEL  # "bev" or "3d": which φ (and which rows of the fit) the model uses
    sigma: float = C.DEFAULT_SIGMA
    estimate_sigma: bool = False
    num_nearest: int = C.DEFAULT_NUM_NEAREST
    outlier_prob: float = 0.0
    prior_weight: float = C.DEFAULT_PRIOR_WEIGHT
    priors: Mapping[str, ClassPrior] = field(default_factory=lambda: default_priors())
    min_points: int = C.DEFAULT_MIN_POINTS

    def prior_for(self, class_name: str) -> ClassPrior:
        """Prior of a class; unknown classes fall back to the ``default`` entry."""
        if class_name in self.priors:
            return self.priors[class_name]
        return self.priors["default"]


@dataclass(frozen=True)
class SpatialParams:
    """Grid and sampling of the spatial distribution p_G (docs/method.md §6–7)."""

    cells_per_side: int = C.DEFAULT_CELLS_PER_SIDE
    num_samples: int = C.DEFAULT_NUM_SAMPLES
    support_std: float = C.DEFAULT_SUPPORT_STD
    seed: int = C.DEFAULT_QMC_SEED


@dataclass(frozen=True)
class CropParams:
    """Point selection per box (docs/datasets.md)."""

    margin: float = C.DEFAULT_CROP_MARGIN
    ground_cut: float = C.DEFAULT_GROUND_CUT
    fit_margin: float = C.DEFAULT_FIT_CROP_MARGIN  # crop of the label-error fit (≥ margin)
