"""Detector evaluation with IoU, JIoU and JIoU-ratio (``labelaudit eval``, docs/eval.md).

The KITTI object devkit's matching and AP (:mod:`~labelaudit.evaluate.matching`,
:mod:`~labelaudit.evaluate.ap`), run with three overlap measures: the IoU of the boxes
(:mod:`~labelaudit.evaluate.overlap`), the JIoU of the detection and the uncertain label
(:mod:`~labelaudit.evaluate.jiou`), and JIoU / JIoU-GT. Labels come from
:mod:`~labelaudit.datasets.gt`, detections from :mod:`~labelaudit.datasets.detections`, label
covariances from an ``infer`` results folder (:mod:`~labelaudit.evaluate.labels`);
:mod:`~labelaudit.evaluate.run` ties them together and :mod:`~labelaudit.evaluate.output` writes
EVAL_DIR. Nothing here prints; the CLI is :mod:`labelaudit.cli_eval`.

Examples
--------
>>> from pathlib import Path
>>> from labelaudit.evaluate import EvalRequest, run_eval, write_eval_dir
>>> result = run_eval(EvalRequest(Path("kitti"), Path("pointgnn/data"), results=Path("kitti-results")))  # doctest: +SKIP
>>> [r["ap"] for r in result.summary["ap"] if r["metric"] == "jiou_ratio" and r["threshold"] == 0.7][:3]  # doctest: +SKIP
"""

from typing import Any

__all__ = ["EvalRequest", "EvalResult", "evaluate", "run_eval", "write_eval_dir"]


def __getattr__(name: str) -> Any:
    # Lazy: worker processes import labelaudit.evaluate.jiou without the orchestration (Arrow, readers).
    if name in ("EvalRequest", "EvalResult", "evaluate", "run_eval"):
        from labelaudit.evaluate import run

        return getattr(run, name)
    if name == "write_eval_dir":
        from labelaudit.evaluate.output import write_eval_dir

        return write_eval_dir
    raise AttributeError(f"module 'labelaudit.evaluate' has no attribute {name!r}")
