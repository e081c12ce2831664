"""Built-in configs (configs/kitti.toml, configs/waymo.toml) and the loader's error messages."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from labelaudit.config import CONFIG_DIR, ConfigError, RunConfig, load_config

KITTI = CONFIG_DIR / "kitti.toml"
WAYMO = CONFIG_DIR / "waymo.toml"


def test_kitti_config():
    cfg = load_config(None, "kitti")
    assert cfg.classes == ("Car", "Van", "Truck")
    assert cfg.model.sigma == 0.2
    assert cfg.model.num_nearest == 3
    assert cfg.model.outlier_prob == 0.0
    assert cfg.min_length == 0.0 and cfg.max_length == float("inf")
    car = cfg.model.prior_for("Car")
    assert (car.center, car.length, car.width, car.yaw) == (0.25, 0.44, 0.10, 0.1745)
    for name in cfg.classes:
        assert name in cfg.model.priors


@pytest.mark.parametrize("fmt", ["waymo-v1", "waymo-v2"])
def test_waymo_config(fmt):
    cfg = load_config(None, fmt)
    assert cfg.dataset_format == fmt
    assert cfg.classes == ("Vehicle",)
    assert cfg.model.sigma == 0.3
    assert (cfg.min_length, cfg.max_length) == (3.0, 6.5)
    assert "Vehicle" in cfg.model.priors


@pytest.mark.parametrize("path", [KITTI, WAYMO])
def test_every_setting_is_documented(path):
    lines = path.read_text().splitlines()
    for i, line in enumerate(lines):
        if re.match(r"^\s*[A-Za-z_]+\s*=", line):
            documented = "#" in line or (i > 0 and lines[i - 1].lstrip().startswith("#")) or (
                i > 0 and lines[i - 1].lstrip().startswith("[") and "#" in lines[i - 1]
            )
            assert documented, f"{path.name}:{i + 1} has no comment: {line!r}"


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "cfg.toml"
    p.write_text(text)
    return p


def test_unknown_key_is_an_error_naming_file_and_key(tmp_path):
    p = _write(tmp_path, "[model]\nsigmma = 0.2\n")
    with pytest.raises(ConfigError, match=r"cfg\.toml.*sigmma"):
        load_config(p)


def test_wrong_type_and_range_are_errors(tmp_path):
    with pytest.raises(ConfigError, match="sigma"):
        load_config(_write(tmp_path, '[model]\nsigma = "big"\n'))
    with pytest.raises(ConfigError, match="sigma must be > 0"):
        load_config(_write(tmp_path, "[model]\nsigma = 0.0\n"))
    with pytest.raises(ConfigError, match="kind must be"):
        load_config(_write(tmp_path, '[model]\nkind = "2d"\n'))
    with pytest.raises(ConfigError, match="unknown key.*model.*expected one of.*kind"):  # the key's old name
        load_config(_write(tmp_path, '[model]\nmodel = "3d"\n'))
    with pytest.raises(ConfigError, match="missing"):
        load_config(_write(tmp_path, "[prior.Car]\ncenter = 0.2\n"))


def test_syntax_error_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(_write(tmp_path, "[model\n"))
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.toml")


def test_param_hash_tracks_parameters(tmp_path):
    a = load_config(None, "kitti")
    assert a.param_hash() == load_config(KITTI, "kitti").param_hash()
    b = load_config(_write(tmp_path, KITTI.read_text().replace("sigma = 0.2", "sigma = 0.25")), "kitti")
    assert b.model.sigma == 0.25
    assert a.param_hash() != b.param_hash()
    assert isinstance(RunConfig().param_hash(), str)
