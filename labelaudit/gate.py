"""Threshold evaluation for ``labelaudit check`` — a CI gate on label quality (docs/ci-gate.md).
It parses gate files and evaluates rules over a results folder; it prints nothing (the CLI shows the report).

A gate file is TOML with a ``[default]`` table (rules for every class) and optional
``[class.<Name>]`` tables that override single keys for one class::

    [default]
    min_median_jiou_gt = 0.6
    jiou_gt_threshold = 0.3            # with the next key: at most 5 % of objects below 0.3
    max_fraction_jiou_gt_below = 0.05
    [class.Pedestrian]
    min_median_jiou_gt = 0.4

Every rule is evaluated per class present in the results, except ``max_failed_frames`` and
``max_missing_per_frame``, which are dataset-wide; ``[class.X]`` tables of classes without objects
are listed as absent. Outcome per rule: ``pass``, ``fail``, ``skip`` (inactive: no ``label_error`` /
``track_error`` values, or no missing-label table because the run skipped the search) or ``error``
(could not be evaluated).
Exit code: 2 when any rule errs or nothing was evaluated, else 1 when any rule fails, else 0.
"""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import pyarrow as pa

from labelaudit import constants as C
from labelaudit.config import CONFIG_DIR, ConfigError, check_keys, read_toml
from labelaudit.results import Results, ResultsError

DEFAULT_GATE_PATH = CONFIG_DIR / C.DEFAULT_GATE_CONFIG

EVALUATED_STATUSES = ("ok", "few_points", "no_points")
"""Objects that count for quality rules; ``skipped`` ones are out of scope, ``error`` ones are
counted by ``max_failed_objects``."""

# key → (kind, description). kind: "min"/"max" rule on a fraction, mean or count; "param" = a
# threshold used by another rule.
KEYS: dict[str, tuple[str, str]] = {
    "min_median_jiou_gt": ("min", "median JIoU-GT of the class's objects"),
    "jiou_gt_threshold": ("param", "JIoU-GT below this counts as uncertain (for max_fraction_jiou_gt_below)"),
    "max_fraction_jiou_gt_below": ("max", "fraction of objects with JIoU-GT below jiou_gt_threshold"),
    "max_fraction_no_points": ("max", "fraction of objects without any LiDAR point"),
    "max_count_no_points": ("max", "number of objects without any LiDAR point"),
    "label_error_threshold": ("param", "label_error above this counts as a likely wrong label"),
    "max_fraction_label_error_above": ("max", "fraction of objects with label_error above label_error_threshold"),
    "track_error_threshold": ("param", "track_error at or above this counts as a label that contradicts its track"),
    "max_fraction_track_error_above": (
        "max",
        "fraction of tracked objects with track_error at or above track_error_threshold",
    ),
    "max_failed_objects": ("max", "objects whose inference failed (status error)"),
    "min_objects": ("min", "objects evaluated (status ok, few_points or no_points)"),
    "max_failed_frames": ("max", "frames that could not be read or audited (dataset-wide)"),
    "missing_score_threshold": (
        "param",
        "a missing-label candidate with a score at or above this counts (for max_missing_per_frame)",
    ),
    "max_missing_per_frame": (
        "max",
        "missing-label candidates with score ≥ missing_score_threshold per frame, on average over the frames (dataset-wide)",
    ),
}
GLOBAL_KEYS = frozenset({"max_failed_frames", "max_missing_per_frame", "missing_score_threshold"})
COUNT_KEYS = frozenset({"max_count_no_points", "max_failed_objects", "min_objects", "max_failed_frames"})
FRACTION_KEYS = frozenset(
    {
        "max_fraction_jiou_gt_below",
        "max_fraction_no_points",
        "max_fraction_label_error_above",
        "max_fraction_track_error_above",
    }
)
NEEDS = {
    "max_fraction_jiou_gt_below": "jiou_gt_threshold",
    "max_fraction_label_error_above": "label_error_threshold",
    "max_fraction_track_error_above": "track_error_threshold",
    "max_missing_per_frame": "missing_score_threshold",
}
_SCORE_RULES = {  # rule → (score column, its threshold key, counts values at the threshold, why inactive without values)
    "max_fraction_label_error_above": ("label_error", "label_error_threshold", False, "no label_error yet"),
    "max_fraction_track_error_above": (
        "track_error",
        "track_error_threshold",
        True,
        "no track_error (no tracks: KITTI, or tracks of < 3 frames)",
    ),
}
# Order of rules in reports.
RULE_ORDER = tuple(k for k, (kind, _) in KEYS.items() if kind != "param")


@dataclass(frozen=True)
class GateConfig:
    """Parsed gate file: default rules and per-class overrides (key → number)."""

    default: Mapping[str, float]
    classes: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    source: str = "<gate>"

    def rules_for(self, class_name: str) -> dict[str, float]:
        """Effective rules of a class: the defaults with its overrides applied."""
        return {**self.default, **self.classes.get(class_name, {})}


def _check_section(section: Any, where: str, source: str) -> dict[str, float]:
    if not isinstance(section, dict):
        raise ConfigError(f"{source}: [{where}] must be a table of thresholds")
    check_keys(section, KEYS, where, source)
    out: dict[str, float] = {}
    for key, value in section.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"{source}: [{where}] {key} must be a number, got {value!r}")
        if key in COUNT_KEYS and (not float(value).is_integer() or value < 0):
            raise ConfigError(f"{source}: [{where}] {key} must be a whole number ≥ 0, got {value!r}")
        if key == "max_missing_per_frame" and value < 0:
            raise ConfigError(f"{source}: [{where}] {key} must be ≥ 0 (candidates per frame), got {value!r}")
        if key in FRACTION_KEYS and not 0 <= value <= 1:
            raise ConfigError(f"{source}: [{where}] {key} must be a fraction in [0, 1], got {value!r}")
        if key in ("min_median_jiou_gt", "missing_score_threshold") and not 0 <= value <= 1:
            raise ConfigError(f"{source}: [{where}] {key} must be in [0, 1], got {value!r}")
        out[key] = float(value)
    return out


def gate_from_dict(data: Mapping[str, Any], source: str = "<gate>") -> GateConfig:
    """Validate a parsed gate file (see module docstring); raises :class:`ConfigError`."""
    unknown = sorted(set(data) - {"default", "class"})
    if unknown:
        raise ConfigError(f"{source}: unknown table(s) {', '.join(unknown)}; expected [default] and [class.<Name>]")
    default = _check_section(data.get("default", {}), "default", source)
    classes_raw = data.get("class", {})
    if not isinstance(classes_raw, dict):
        raise ConfigError(f"{source}: 'class' must hold tables like [class.Car]")
    classes = {}
    for name, section in classes_raw.items():
        rules = _check_section(section, f"class.{name}", source)
        bad = sorted(set(rules) & GLOBAL_KEYS)
        if bad:
            raise ConfigError(f"{source}: [class.{name}] {', '.join(bad)} is dataset-wide; put it in [default]")
        classes[name] = rules
    gate = GateConfig(default, classes, source)
    for where, rules in [("default", default), *((f"class.{n}", gate.rules_for(n)) for n in classes)]:
        for key, needed in NEEDS.items():
            if key in rules and needed not in rules:
                raise ConfigError(f"{source}: [{where}] {key} needs {needed} (in the same table or in [default])")
    if not any(k in RULE_ORDER for k in default) and not any(any(k in RULE_ORDER for k in r) for r in classes.values()):
        raise ConfigError(f"{source}: no rules; set at least one of {', '.join(RULE_ORDER)} in [default]")
    return gate


def load_gate(path: str | Path | None = None) -> GateConfig:
    """Load a gate file (default: the built-in ``configs/gate.toml``); raises :class:`ConfigError`."""
    path = Path(path) if path is not None else DEFAULT_GATE_PATH
    return gate_from_dict(read_toml(path, "gate file"), source=str(path))


# --------------------------------------------------------------------------- evaluation


@dataclass
class RuleResult:
    """One evaluated rule."""

    scope: str  # a class name, or "dataset" for dataset-wide rules
    rule: str
    value: float | None
    threshold: float
    status: str  # pass | fail | skip | error
    objects: int  # objects the value was computed over
    note: str = ""

    @property
    def comparison(self) -> str:
        return ">=" if KEYS[self.rule][0] == "min" else "<="


@dataclass
class GateReport:
    """All rule outcomes and the exit code they imply."""

    results: list[RuleResult]
    source: str
    total_objects: int
    absent_classes: list[str] = field(default_factory=list)  # [class.X] tables with no objects: not evaluated

    @property
    def exit_code(self) -> int:
        statuses = {r.status for r in self.results}
        if "error" in statuses or not statuses & {"pass", "fail"}:
            return 2
        return 1 if "fail" in statuses else 0

    @property
    def verdict(self) -> str:
        return {0: "PASS", 1: "FAIL", 2: "ERROR"}[self.exit_code]

    def to_dict(self) -> dict[str, Any]:
        return {
            "verdict": self.verdict,
            "exit_code": self.exit_code,
            "gate": self.source,
            "objects": self.total_objects,
            "absent_classes": self.absent_classes,
            "rules": [{**asdict(r), "comparison": r.comparison} for r in self.results],
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    def to_junit(self) -> str:
        """JUnit XML: one test case per rule (fail → <failure>, error → <error>, skip → <skipped>)."""
        counts = {s: sum(r.status == s for r in self.results) for s in ("fail", "error", "skip")}
        suites = ET.Element("testsuites", name="labelaudit check")
        suite = ET.SubElement(
            suites,
            "testsuite",
            name="labelaudit.check",
            tests=str(len(self.results)),
            failures=str(counts["fail"]),
            errors=str(counts["error"]),
            skipped=str(counts["skip"]),
        )
        for r in self.results:
            case = ET.SubElement(suite, "testcase", classname=f"labelaudit.check.{r.scope}", name=r.rule)
            text = f"{r.rule} = {format_number(r.value)} (must be {r.comparison} {format_number(r.threshold)}; {r.objects} objects){' — ' + r.note if r.note else ''}"
            if r.status == "fail":
                ET.SubElement(case, "failure", message=text, type="threshold")
            elif r.status == "error":
                ET.SubElement(case, "error", message=text, type="not_evaluated")
            elif r.status == "skip":
                ET.SubElement(case, "skipped", message=r.note or "inactive")
            ET.SubElement(case, "system-out").text = text
        ET.indent(suites)
        return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(suites, encoding="unicode") + "\n"


def format_number(v: float | None) -> str:
    """A rule value or threshold as shown in reports: whole numbers without decimals, else 4 digits."""
    if v is None:
        return "n/a"
    return f"{int(v)}" if float(v).is_integer() and abs(v) >= 1 else f"{v:.4g}"


def _compare(rule: str, value: float, threshold: float) -> str:
    return "pass" if (value >= threshold if KEYS[rule][0] == "min" else value <= threshold) else "fail"


def _finite(values: np.ndarray) -> np.ndarray:
    v = values.astype(float)
    return v[np.isfinite(v)]


def _evaluate_class(
    name: str, rules: Mapping[str, float], status: np.ndarray, jiou: np.ndarray, lerr: np.ndarray, terr: np.ndarray
) -> list[RuleResult]:
    """Rules of one class over its rows (arrays of equal length; NaN = null)."""
    evaluated = np.isin(status, EVALUATED_STATUSES)
    n = int(evaluated.sum())
    out: list[RuleResult] = []
    for rule in RULE_ORDER:
        if rule not in rules or rule in GLOBAL_KEYS:
            continue
        thr = rules[rule]
        note = ""
        value: float | None = None
        count = n
        if rule == "min_objects":
            value = float(n)
        elif rule == "max_failed_objects":
            value = float(np.sum(status == "error"))
            count = len(status)
        elif rule in ("max_fraction_no_points", "max_count_no_points"):
            if n == 0:
                note = "no evaluated objects (all skipped or failed)"
            else:
                k = float(np.sum(status == "no_points"))
                value = k / n if rule == "max_fraction_no_points" else k
        elif rule in ("min_median_jiou_gt", "max_fraction_jiou_gt_below"):
            values = _finite(jiou[evaluated])
            count = len(values)
            if count == 0:
                note = "no JIoU-GT values"
            elif rule == "min_median_jiou_gt":
                value = float(np.median(values))
            else:
                value = float(np.mean(values < rules["jiou_gt_threshold"]))
                note = f"below {format_number(rules['jiou_gt_threshold'])}"
        elif rule in _SCORE_RULES:
            score, param, at_or_above, inactive = _SCORE_RULES[rule]
            values = _finite((lerr if score == "label_error" else terr)[evaluated])
            count = len(values)
            if count == 0:  # the score is not computed for these objects (yet): the rule is inactive
                out.append(RuleResult(name, rule, None, thr, "skip", 0, f"inactive: {inactive}"))
                continue
            value = float(np.mean(values >= rules[param] if at_or_above else values > rules[param]))
            note = f"{'at or above' if at_or_above else 'above'} {format_number(rules[param])}"
        if value is None:
            out.append(RuleResult(name, rule, None, thr, "error", count, note or "could not be evaluated"))
        else:
            out.append(RuleResult(name, rule, value, thr, _compare(rule, value, thr), count, note))
    return out


def _missing_rule(results: Results, objects: pa.Table, rules: Mapping[str, float]) -> RuleResult:
    """``max_missing_per_frame``: candidates with score ≥ the threshold, per frame of the run.

    The frames are those with a label row or a candidate row (a frame with neither has nothing to
    count and is not known from the tables), so the rate is never understated by empty frames. The
    note names the frame with the most candidates, the first to look at.
    """
    from labelaudit.rank import read_candidates

    thr, floor = rules["max_missing_per_frame"], rules["missing_score_threshold"]
    candidates = read_candidates(results)
    if candidates is None:
        return RuleResult(
            "dataset",
            "max_missing_per_frame",
            None,
            thr,
            "skip",
            0,
            "inactive: the run did not search for missing labels (infer --no-missing)",
        )
    frames = set(objects.column("frame_id").to_pylist()) | set(candidates.column("frame_id").to_pylist())
    scores = np.asarray(candidates.column("score").to_numpy(zero_copy_only=False), dtype=float)
    counted = [f for f, s in zip(candidates.column("frame_id").to_pylist(), scores) if s >= floor]
    value = len(counted) / len(frames)
    note = f"{len(counted)} candidates with score ≥ {format_number(floor)} in {len(frames)} frames"
    if counted:
        per_frame = Counter(counted)
        worst = min(per_frame, key=lambda f: (-per_frame[f], f))
        note += f"; most in frame {worst} ({per_frame[worst]})"
    return RuleResult(
        "dataset",
        "max_missing_per_frame",
        value,
        thr,
        _compare("max_missing_per_frame", value, thr),
        objects.num_rows,
        note,
    )


def evaluate_gate(results: Results, gate: GateConfig) -> GateReport:
    """Evaluate every rule of ``gate`` on opened results.

    Raises
    ------
    ResultsError
        Empty results, or results of a run that did not finish (the gate would judge a part).
    """
    if not results.complete:
        raise ResultsError(
            f"{results.root}: the run that wrote these results did not finish; rerun `labelaudit infer` "
            "with the same options to resume, then check again"
        )
    table = results.read(["frame_id", "class_name", "status", "jiou_gt", "label_error", "track_error"])
    if table.num_rows == 0:
        raise ResultsError(
            f"{results.root}: results hold no objects; nothing to check (wrong --classes, or an empty dataset?)"
        )
    classes = np.asarray(table.column("class_name").to_pylist(), dtype=object)
    status = np.asarray(table.column("status").to_pylist(), dtype=object)
    jiou = table.column("jiou_gt").to_numpy(zero_copy_only=False).astype(float)
    lerr = np.asarray([np.nan if v is None else v for v in table.column("label_error").to_pylist()], dtype=float)
    terr = np.asarray([np.nan if v is None else v for v in table.column("track_error").to_pylist()], dtype=float)

    out: list[RuleResult] = []
    names = sorted(set(classes.tolist()))
    for name in names:
        m = classes == name
        out.extend(_evaluate_class(name, gate.rules_for(name), status[m], jiou[m], lerr[m], terr[m]))
    if "max_failed_frames" in gate.default:
        failed = results.failed_frames()
        thr = gate.default["max_failed_frames"]
        out.append(
            RuleResult(
                "dataset",
                "max_failed_frames",
                float(failed),
                thr,
                _compare("max_failed_frames", failed, thr),
                table.num_rows,
            )
        )
    if "max_missing_per_frame" in gate.default:
        out.append(_missing_rule(results, table, gate.default))
    return GateReport(out, gate.source, table.num_rows, sorted(set(gate.classes) - set(names)))
