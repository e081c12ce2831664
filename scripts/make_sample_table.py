"""Write labelaudit/data/normal_samples.npz: the default quasi-random normal samples of p_G.

They are what ``labelaudit.core.spatial.generate_normal_samples`` (scipy.stats.qmc) returns for the
dimensions used (φ: 6 BEV, 8 3D; box parameters: 5 BEV, 7 3D) with the default sample count and
seed; stored so worker processes do not import scipy.stats. tests/test_spatial.py checks equality.

    .venv/bin/python scripts/make_sample_table.py
"""

from __future__ import annotations

import numpy as np

from labelaudit import constants as C
from labelaudit.core.params import SAMPLE_TABLE
from labelaudit.core.spatial import generate_normal_samples


def main() -> None:
    n, seed = C.DEFAULT_NUM_SAMPLES, C.DEFAULT_QMC_SEED
    arrays = {f"d{d}_n{n}_s{seed}": generate_normal_samples(d, n, seed) for d in (5, 6, 7, 8)}
    SAMPLE_TABLE.parent.mkdir(exist_ok=True)
    np.savez_compressed(SAMPLE_TABLE, **arrays)
    print(f"wrote {SAMPLE_TABLE} ({', '.join(arrays)})")


if __name__ == "__main__":
    main()
