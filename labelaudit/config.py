"""Typed run configuration: model, prior, spatial grid, crop and class selection, loaded from TOML.
It owns the run configuration (:class:`RunConfig`), its TOML files, their validation and the hash;
it computes nothing and reads no dataset. The parameter types it is made of are the core's
(:mod:`labelaudit.core.params`).

Every tunable has a default in :mod:`labelaudit.constants`; a TOML file overrides them per dataset
(``configs/kitti.toml``, ``configs/waymo.toml``, ``configs/av2.toml``). Unknown keys are an error, so a typo never
silently falls back to a default.
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

from labelaudit import constants as C
from labelaudit.core.params import SAMPLE_TABLE, ClassPrior, CropParams, ModelParams, SpatialParams, default_priors
from labelaudit.errors import ConfigError

CONFIG_DIR = Path(__file__).parent / "configs"
"""Where the built-in per-dataset configs live (``configs/`` at the repository root links here)."""

ALL_CLASSES = "all"
"""Put this alone in ``classes`` to audit every class (``--classes all``)."""

PRESETS: dict[str, str] = {"paper": "kitti-paper.toml"}
"""Built-in presets by name (``--config paper``): the authors' published KITTI setting."""


def preset_path(path: str | Path) -> Path:
    """``path``, or the built-in file of a preset name (:data:`PRESETS`) when no such file exists."""
    p = Path(path)
    if not p.exists() and str(path) in PRESETS:
        return CONFIG_DIR / PRESETS[str(path)]
    return p


@dataclass(frozen=True)
class MissingParams:
    """The search for objects without a label (``missing/``, docs/missing.md)."""

    enabled: bool = True  # --no-missing: False
    max_range: float = (
        C.MISSING_MAX_RANGE
    )  # m; candidates farther than this (BEV) from the sensor are not looked for (the dataset's labelled range)
    min_points: int = C.MISSING_MIN_POINTS  # a cluster with fewer points above the ground is no candidate
    detections: str | None = None  # --detections: absolute path of a detector's output (the formats `eval` reads)
    detections_format: str = "auto"  # auto, kitti, waymo or parquet
    detection_min_score: float = C.MISSING_DETECTION_MIN_SCORE  # detections below this confidence are not candidates


@dataclass(frozen=True)
class RunConfig:
    """Everything that determines the rows of a run; its hash guards ``--resume``."""

    dataset_format: str = "kitti"
    classes: tuple[str, ...] = C.DEFAULT_CLASSES
    min_length: float = 0.0  # Waymo: the paper audits small vehicles only (3–6.5 m)
    max_length: float = float("inf")
    model: ModelParams = field(default_factory=ModelParams)
    spatial: SpatialParams = field(default_factory=SpatialParams)
    crop: CropParams = field(default_factory=CropParams)
    missing: MissingParams = field(default_factory=MissingParams)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dictionary of every parameter."""
        d = asdict(self)
        d["classes"] = list(self.classes)
        d["max_length"] = None if self.max_length == float("inf") else self.max_length
        return d

    def param_hash(self) -> str:
        """Stable hash of everything that can change a row (sha256 of canonical JSON, 16 hex digits).

        It covers the resolved parameters (:meth:`to_dict`), the digest of the fixed numbers
        (:func:`constants_digest`), the results schema version and the package version, so a
        results folder is never resumed by a run that would compute other rows.
        """
        return _digest(hash_inputs(self))

    def with_overrides(self, **kw: Any) -> "RunConfig":
        """Copy with top-level fields replaced (``model=``, ``classes=`` …)."""
        return replace(self, **kw)


def constants_digest() -> str:
    """Digest of every fixed number of :mod:`labelaudit.constants` and of the stored Sobol samples.

    Every upper-case name of the constants module enters it except those listed as never changing
    a row (:data:`~labelaudit.constants.UNHASHED_PREFIXES`, :data:`~labelaudit.constants.UNHASHED_NAMES`):
    a new constant is hashed by default, so forgetting to list one costs a needless re-run, never a
    folder that mixes two models.
    """
    values = {name: getattr(C, name) for name in dir(C) if name.isupper() and not is_unhashed(name)}
    blob = json.dumps(values, sort_keys=True, default=repr, separators=(",", ":"))
    h = hashlib.sha256(blob.encode())
    h.update(SAMPLE_TABLE.read_bytes())
    return h.hexdigest()[:16]


def is_unhashed(name: str) -> bool:
    """Whether a constant is left out of the parameter hash (it cannot change a result row)."""
    return name.startswith(C.UNHASHED_PREFIXES) or name in C.UNHASHED_NAMES


def hash_inputs(cfg: RunConfig) -> dict[str, Any]:
    """What :meth:`RunConfig.param_hash` hashes; the manifest records each part, so a refused
    resume can say which one differs."""
    from labelaudit import SCHEMA_VERSION, __version__

    return {
        "params": cfg.to_dict(),
        "constants_digest": constants_digest(),
        "schema_version": SCHEMA_VERSION,
        "tool_version": __version__,
    }


def _digest(data: Mapping[str, Any]) -> str:
    blob = json.dumps(data, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def check_keys(section: Mapping[str, Any], allowed: set[str] | Mapping[str, Any], where: str, source: str) -> None:
    """Refuse keys of a TOML table outside ``allowed``, naming them and the accepted ones (model and gate files)."""
    unknown = sorted(set(section) - set(allowed))
    if unknown:
        raise ConfigError(
            f"{source}: unknown key(s) {', '.join(unknown)} in [{where}]; expected one of {', '.join(sorted(allowed))}"
        )


def _typed(value: Any, kind: type, key: str, source: str) -> Any:
    if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if kind is int and isinstance(value, int) and not isinstance(value, bool):
        return value
    if kind is bool and isinstance(value, bool):
        return value
    if kind is str and isinstance(value, str):
        return value
    raise ConfigError(f"{source}: {key} must be {kind.__name__}, got {value!r}")


def _build(cls: type, section: Mapping[str, Any], where: str, source: str, skip: frozenset[str] = frozenset()) -> Any:
    names = {f.name: f for f in fields(cls) if f.name not in skip}
    check_keys(section, set(names), where, source)
    kw = {}
    for key, value in section.items():
        f = names[key]
        kind = {"float": float, "int": int, "bool": bool, "str": str}.get(str(f.type), None)
        if kind is None:  # Literal / complex types are handled by the caller
            kw[key] = value
        else:
            kw[key] = _typed(value, kind, f"[{where}] {key}", source)
    return kw


BUILTIN_CONFIGS: dict[str, str] = {
    "kitti": "kitti.toml",
    "waymo-v2": "waymo.toml",
    "waymo-v1": "waymo.toml",
    "av2": "av2.toml",
}
"""The built-in config file (in :data:`CONFIG_DIR`) of each dataset format."""


def builtin_config_name(dataset_format: str) -> str:
    """File name of the built-in config of a dataset format (KITTI's for an unknown format)."""
    return BUILTIN_CONFIGS.get(dataset_format, "kitti.toml")


def load_config(path: str | Path | None = None, dataset_format: str = "kitti") -> RunConfig:
    """Load a run configuration.

    Parameters
    ----------
    path : TOML file, a preset name (``"paper"``, :data:`PRESETS`), or None for the built-in
        config of ``dataset_format``.
    dataset_format : "kitti", "waymo-v2", "waymo-v1" or "av2"; chooses the built-in config
        (:func:`builtin_config_name`).

    Raises
    ------
    ConfigError
        Unreadable file, TOML syntax error (with line), unknown key or wrong type.
    """
    if path is None:
        path = CONFIG_DIR / builtin_config_name(dataset_format)
    path = preset_path(path)
    return config_from_dict(read_toml(path, "config file"), source=str(path), dataset_format=dataset_format)


def read_toml(path: Path, what: str) -> dict[str, Any]:
    """Parse a TOML file (model config or gate file); every failure is a :class:`ConfigError` naming it."""
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: {what} not found") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: {what} is not UTF-8 text (byte {exc.start}); save it as UTF-8") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None


def config_from_dict(data: Mapping[str, Any], *, source: str = "<config>", dataset_format: str = "kitti") -> RunConfig:
    """Build a :class:`RunConfig` from a parsed TOML mapping (see :func:`load_config`)."""
    check_keys(data, {"dataset", "model", "prior", "spatial", "crop", "missing"}, "top level", source)
    ds = dict(data.get("dataset", {}))
    check_keys(ds, {"classes", "min_length", "max_length"}, "dataset", source)
    classes = ds.get("classes", list(C.DEFAULT_CLASSES))
    if not (isinstance(classes, list) and all(isinstance(c, str) for c in classes) and classes):
        raise ConfigError(f"{source}: [dataset] classes must be a non-empty list of class names, got {classes!r}")

    model_kw = _build(ModelParams, data.get("model", {}), "model", source, skip=frozenset({"priors"}))
    if "kind" in model_kw and model_kw["kind"] not in ("bev", "3d"):
        raise ConfigError(f"{source}: [model] kind must be 'bev' or '3d', got {model_kw['kind']!r}")
    priors = default_priors()
    for cls_name, section in data.get("prior", {}).items():
        kw = _build(ClassPrior, section, f"prior.{cls_name}", source)
        missing = {f.name for f in fields(ClassPrior)} - set(kw)
        if missing:
            raise ConfigError(f"{source}: [prior.{cls_name}] is missing {', '.join(sorted(missing))}")
        priors[cls_name] = ClassPrior(**kw)
    model = ModelParams(priors=priors, **model_kw)
    spatial = SpatialParams(**_build(SpatialParams, data.get("spatial", {}), "spatial", source))
    crop = CropParams(**_build(CropParams, data.get("crop", {}), "crop", source))
    # the detections are a run option (--detections), not a model setting
    missing = MissingParams(
        **_build(MissingParams, data.get("missing", {}), "missing", source, skip={"detections", "detections_format"})
    )
    lengths = {k: _typed(ds[k], float, f"[dataset] {k}", source) for k in ("min_length", "max_length") if k in ds}
    cfg = RunConfig(
        dataset_format=dataset_format,
        classes=tuple(classes),
        min_length=lengths.get("min_length", 0.0),
        max_length=lengths.get("max_length", float("inf")),
        model=model,
        spatial=spatial,
        crop=crop,
        missing=missing,
    )
    validate_config(cfg, source)
    return cfg


def validate_config(cfg: RunConfig, source: str = "<config>") -> None:
    """Check every value of a run configuration against :data:`~labelaudit.constants.PARAM_RANGES`
    (and the length range), raising :class:`ConfigError` with the value and the accepted range."""
    lo, hi = cfg.min_length, cfg.max_length
    if not (math.isfinite(lo) and lo >= 0 and hi > lo):  # max_length = inf is the default: no upper cut
        raise ConfigError(
            f"{source}: [dataset] min_length must be finite and ≥ 0 and max_length > min_length, got {lo} and {hi}"
        )
    if not cfg.classes or not all(isinstance(c, str) and c for c in cfg.classes):
        raise ConfigError(
            f"{source}: [dataset] classes must be a non-empty list of class names, got {list(cfg.classes)!r}"
        )
    validate_params(cfg.model, cfg.spatial, cfg.crop, source, cfg.missing)


def validate_params(
    model: ModelParams,
    spatial: SpatialParams,
    crop: CropParams,
    source: str = "<config>",
    missing: MissingParams | None = None,
) -> None:
    """Check every number against its sane range (:data:`~labelaudit.constants.PARAM_RANGES`).

    NaN, ±inf and values like ``sigma = 1e308`` (every object would fail, or every std would be
    the prior's) are refused; the message shows the key, the value and the accepted range.
    """
    values: list[tuple[str, str, Any]] = [
        *(
            (f"model.{f.name}", f"[model] {f.name}", getattr(model, f.name))
            for f in fields(ModelParams)
            if f.name not in ("kind", "estimate_sigma", "priors")
        ),
        *((f"spatial.{f.name}", f"[spatial] {f.name}", getattr(spatial, f.name)) for f in fields(SpatialParams)),
        *((f"crop.{f.name}", f"[crop] {f.name}", getattr(crop, f.name)) for f in fields(CropParams)),
        *(
            (f"prior.{f.name}", f"[prior.{name}] {f.name}", getattr(prior, f.name))
            for name, prior in model.priors.items()
            for f in fields(ClassPrior)
        ),
        *(
            (f"missing.{name}", f"[missing] {name}", getattr(missing, name))
            for name in ("max_range", "min_points", "detection_min_score")
            if missing is not None
        ),
    ]
    for key, label, value in values:
        lo, hi, lo_open, hi_open = C.PARAM_RANGES[key]
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        ok = ok and (value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)
        if not ok:
            accepted = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
            raise ConfigError(f"{source}: {label} must be in {accepted}, got {value!r}")
    if missing is not None and missing.detections_format not in ("auto", "kitti", "waymo", "parquet"):
        raise ConfigError(
            f"{source}: detections format must be auto, kitti, waymo or parquet, got {missing.detections_format!r}"
        )
    if crop.fit_margin < crop.margin:
        raise ConfigError(f"{source}: [crop] fit_margin must be ≥ margin ({crop.margin}), got {crop.fit_margin}")


def resolve_config(
    config_path: Path | None, dataset_format: str, classes: Sequence[str] | None = None, model: str | None = None
) -> RunConfig:
    """Load the TOML config (or the built-in one of the format) and apply CLI overrides.

    Raises
    ------
    ConfigError
        Unreadable file, unknown key, bad value.
    """
    if config_path is None:
        name = builtin_config_name(dataset_format)
        cfg = (
            load_config(None, dataset_format)
            if (CONFIG_DIR / name).is_file()
            else RunConfig(dataset_format=dataset_format)
        )
    else:
        cfg = load_config(config_path, dataset_format)
    if classes is not None:
        classes = tuple(c.strip() for c in classes if c.strip())
        if not classes:
            raise ConfigError("--classes: expected a comma-separated list of class names or 'all'")
        cfg = cfg.with_overrides(classes=(ALL_CLASSES,) if ALL_CLASSES in classes else classes)
    if model is not None:
        if model not in ("bev", "3d"):
            raise ConfigError(f"--model: expected bev or 3d, got {model!r}")
        cfg = cfg.with_overrides(model=replace(cfg.model, kind=model))
    return cfg


def config_from_params(params: Mapping[str, Any], *, source: str = "<params>") -> RunConfig:
    """Rebuild the :class:`RunConfig` that :meth:`RunConfig.to_dict` wrote (a results manifest's ``params``).

    The inverse of ``to_dict``: ``config_from_params(cfg.to_dict()) == cfg``, so a results folder's
    pictures can be recomputed with the very configuration of its run.

    Raises
    ------
    ConfigError
        A key is missing, unknown or of the wrong type.
    """
    try:
        top = dict(params)
        check_keys(top, {f.name for f in fields(RunConfig)}, "params", source)
        model = dict(top.get("model", {}))
        priors = {name: ClassPrior(**dict(p)) for name, p in dict(model.pop("priors", {})).items()} or default_priors()
        check_keys(model, {f.name for f in fields(ModelParams)}, "params.model", source)
        spatial, crop, missing = dict(top.get("spatial", {})), dict(top.get("crop", {})), dict(top.get("missing", {}))
        check_keys(spatial, {f.name for f in fields(SpatialParams)}, "params.spatial", source)
        check_keys(crop, {f.name for f in fields(CropParams)}, "params.crop", source)
        check_keys(missing, {f.name for f in fields(MissingParams)}, "params.missing", source)
        max_length = top.get("max_length")
        return RunConfig(
            dataset_format=str(top.get("dataset_format", "kitti")),
            classes=tuple(top.get("classes", C.DEFAULT_CLASSES)),
            min_length=float(top.get("min_length", 0.0)),
            max_length=float("inf") if max_length is None else float(max_length),
            model=ModelParams(priors=priors, **model),
            spatial=SpatialParams(**spatial),
            crop=CropParams(**crop),
            missing=MissingParams(**missing),
        )
    except ConfigError:
        raise
    except (TypeError, ValueError, AttributeError) as exc:
        raise ConfigError(f"{source}: malformed run parameters ({exc})") from None
