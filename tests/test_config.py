"""Built-in configs (configs/kitti.toml, configs/waymo.toml, configs/av2.toml) and the loader's error messages."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from labelaudit.config import CONFIG_DIR, ConfigError, RunConfig, load_config

KITTI = CONFIG_DIR / "kitti.toml"
WAYMO = CONFIG_DIR / "waymo.toml"
AV2 = CONFIG_DIR / "av2.toml"


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


def test_av2_config():
    cfg = load_config(None, "av2")
    assert cfg.dataset_format == "av2"
    assert cfg.classes == ("REGULAR_VEHICLE", "LARGE_VEHICLE", "BUS", "SCHOOL_BUS", "BOX_TRUCK", "TRUCK", "TRUCK_CAB")
    assert cfg.model.sigma == 0.3
    assert (cfg.min_length, cfg.max_length) == (0.0, float("inf"))
    car = cfg.model.prior_for("REGULAR_VEHICLE")
    assert (car.center, car.length, car.width, car.height, car.yaw) == (0.25, 0.44, 0.10, 0.10, 0.1745)
    for name in cfg.classes:
        assert name in cfg.model.priors
        assert cfg.model.prior_for(name).length >= car.length  # no audited class is surer than a car
    from labelaudit import constants as C

    assert set(cfg.classes) <= set(C.FREE_SPACE_CLASSES)  # every audited AV2 class has a solid lower body


@pytest.mark.parametrize("path", [KITTI, WAYMO, AV2])
def test_every_setting_is_documented(path):
    lines = path.read_text().splitlines()
    for i, line in enumerate(lines):
        if re.match(r"^\s*[A-Za-z_]+\s*=", line):
            documented = (
                "#" in line
                or (i > 0 and lines[i - 1].lstrip().startswith("#"))
                or (i > 0 and lines[i - 1].lstrip().startswith("[") and "#" in lines[i - 1])
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
    with pytest.raises(ConfigError, match=r"sigma must be in \[0.0001, 10\], got 0.0"):
        load_config(_write(tmp_path, "[model]\nsigma = 0.0\n"))
    with pytest.raises(ConfigError, match="kind must be"):
        load_config(_write(tmp_path, '[model]\nkind = "2d"\n'))
    with pytest.raises(ConfigError, match="unknown key.*model.*expected one of.*kind"):  # the key's old name
        load_config(_write(tmp_path, '[model]\nmodel = "3d"\n'))
    with pytest.raises(ConfigError, match="missing"):
        load_config(_write(tmp_path, "[prior.Car]\ncenter = 0.2\n"))


@pytest.mark.parametrize(
    "text",
    [
        "[model]\nsigma = inf\n",  # else accepted: every std would be the prior's
        "[model]\nsigma = 1e308\n",  # else every object would be status=error with exit 0
        "[model]\nsigma = nan\n",
        "[model]\nsigma = 1e-300\n",
        "[model]\nprior_weight = inf\n",
        "[model]\nnum_nearest = 100\n",
        "[model]\noutlier_prob = 1.0\n",
        "[spatial]\ncells_per_side = 1000000000\n",
        "[spatial]\nnum_samples = 100000000\n",
        "[spatial]\nsupport_std = inf\n",
        "[spatial]\nseed = -1\n",
        "[crop]\nmargin = 1e300\n",
        "[crop]\nground_cut = nan\n",
        "[prior.Car]\ncenter = inf\nlength = 0.4\nwidth = 0.1\nheight = 0.1\nyaw = 0.1\n",
        "[dataset]\nmin_length = 5.0\nmax_length = 3.0\n",
        "[dataset]\nmin_length = nan\n",
        '[dataset]\nmax_length = "long"\n',
    ],
)
def test_values_outside_their_sane_range_are_refused(tmp_path, text):
    key = text.split("\n")[1].split(" =")[0]
    with pytest.raises(ConfigError, match=rf"cfg\.toml: .*{key}"):
        load_config(_write(tmp_path, text))


def test_the_built_in_configs_are_within_the_ranges():
    for fmt in ("kitti", "waymo-v2"):
        load_config(None, fmt)  # validates
    assert load_config(None, "waymo-v2").max_length < float("inf")


def test_non_utf8_and_folder_configs_name_the_file(tmp_path):
    # a non-UTF-8 --config or a folder is a config error naming it, not a UnicodeDecodeError (exit 3) or an IsADirectoryError
    p = tmp_path / "cfg.toml"
    p.write_bytes(b"[model]\nsigma = 0.2 # \xff\n")
    with pytest.raises(ConfigError, match=r"cfg\.toml: config file is not UTF-8 text \(byte 22\)"):
        load_config(p)
    with pytest.raises(ConfigError, match="cannot read config file .Is a directory"):
        load_config(tmp_path)


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


def test_the_ground_fits_scored_candidates_enter_the_hash(monkeypatch):
    """GROUND_SCORED caps the candidates each RANSAC hypothesis is scored on: it can change a
    row, so the parameter hash covers it."""
    from labelaudit import constants as C
    from labelaudit.config import constants_digest, is_unhashed

    assert not is_unhashed("GROUND_SCORED")
    before = constants_digest()
    monkeypatch.setattr(C, "GROUND_SCORED", C.GROUND_SCORED + 1)
    assert constants_digest() != before
