"""The typed run configuration: every bad value is refused before any data is loaded, with a message that
names the key, the value and what is expected; config -> dict -> config is the identity; configurations
and checkpoints written before the typed configuration still load."""

from __future__ import annotations

import copy
import dataclasses

import pytest
import yaml
from tiny_configs import tiny_config

from zernet.training import DEFAULT_CONFIG, ConfigError, RunConfig, parse_config, read_config, resolve_config
from zernet.training.config import TrainSection

# A resolved configuration exactly as resolve_config wrote it into config.yaml and checkpoints before the
# redesign (the demo's): keys in this order, pass-through keys after the data and model defaults.
TODAYS_FORMAT = {
    "data": {
        "kind": "synthetic",
        "seed": 0,
        "val_fraction": None,
        "val_count": 3,
        "on_error": "raise",
        "residency": "auto",
        "task": "segmentation",
        "n_shapes": 30,
        "n_vertices": 1000,
        "test_fraction": 0.2,
        "features": "xyz+normals",
    },
    "patch": {
        "area": None,
        "scale": None,
        "scales": [{"r0": 2.5, "n_samples": 4000, "patch_size": 50, "n_max": 5, "subtract_center": True}],
    },
    "model": {"name": "zernet", "widths": [16, 32, 64, 64], "angular_resolution": 4, "pooling": "max", "dropout": 0.1},
    "train": {
        "epochs": 12,
        "lr": 0.005,
        "lr_schedule": "constant",
        "lr_schedule_epochs": None,
        "weight_decay": 0.0,
        "loss": "auto",
        "label_radius": 0.0,
        "standardize_targets": True,
        "target_transform": "none",
        "standardize_features": False,
        "patience": 6,
        "seed": 0,
        "shapes_per_step": 1,
        "device": "auto",
        "threads": None,
        "grad_clip": None,
        "precision": "float32",
        "augment_rotation": "none",
        "augment_scale": 0.0,
        "augment_anisotropy": 0.0,
        "augment_warp": 0.0,
        "keep_epochs": False,
        "init_from": None,
    },
    "eval": {"renders": 3, "plots": True, "refine_rings": [0], "refine_passes": [1], "refine_spectral": [0.0]},
    "cache_dir": ".zernet-cache",
}


def test_a_dict_in_todays_format_round_trips_with_its_key_order():
    config = parse_config(TODAYS_FORMAT)
    assert config.to_dict() == TODAYS_FORMAT
    assert yaml.safe_dump(config.to_dict(), sort_keys=False) == yaml.safe_dump(TODAYS_FORMAT, sort_keys=False)
    assert parse_config(config.to_dict()) == config
    assert config.train.epochs == 12 and config.model.options["widths"] == [16, 32, 64, 64]
    assert config.data.options["features"] == "xyz+normals" and config.patch.patch_configs()[0].r0 == 2.5


def test_a_config_written_before_augmentation_loads_with_it_off():
    older = copy.deepcopy(TODAYS_FORMAT)
    del older["train"]["augment_rotation"], older["train"]["augment_scale"]
    config = parse_config(older)
    assert config.train.augment_rotation == "none" and config.train.augment_scale == 0.0
    assert config == parse_config(TODAYS_FORMAT)


def test_a_config_written_before_residency_loads_with_auto():
    older = copy.deepcopy(TODAYS_FORMAT)
    del older["data"]["residency"]
    assert parse_config(older).data.residency == "auto" and parse_config(older) == parse_config(TODAYS_FORMAT)


def test_defaults_fill_in_and_the_input_is_not_aliased(tmp_path):
    given = tiny_config(tmp_path)
    config = parse_config(given)
    assert config.train.precision == "float32" and config.eval.plots is False
    assert resolve_config(given)["train"]["patience"] == DEFAULT_CONFIG["train"]["patience"] == 20
    given["model"]["widths"].append(99)
    assert config.model.options["widths"] == [8, 8, 16]
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.train.epochs = 3
    assert parse_config({}) == RunConfig()
    assert parse_config({"cache_dir": None, "train": None}) == RunConfig()


def test_read_config_applies_overrides(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(tiny_config(tmp_path)))
    config = read_config(path, ["train.epochs=7", "model.widths=[4, 4]", "patch.scales.0.r0=3.5"])
    assert config.train.epochs == 7 and config.model.options["widths"] == [4, 4]
    assert config.patch.scales[0]["r0"] == 3.5


@pytest.mark.parametrize(
    "dotted, value, expected",
    [
        ("train.epochs", -1, "an integer >= 0"),
        ("train.epochs", 2.5, "an integer"),
        ("train.epochs", True, "an integer"),
        ("train.patience", 0, "an integer >= 1 or null"),
        ("train.seed", "zero", "an integer"),
        ("train.shapes_per_step", 0, "an integer >= 1"),
        ("train.threads", 0, "an integer >= 1 or null"),
        ("train.lr", 0, "a number > 0"),
        ("train.lr", "fast", "a number > 0"),
        ("train.lr", float("nan"), "a number"),
        ("train.weight_decay", None, "a number"),
        ("train.grad_clip", -1.0, "a number > 0 or null"),
        ("train.loss", "hinge", "one of auto, cross_entropy, mse, l1, relative_l1"),
        ("train.lr_schedule", "step", "one of constant, cosine"),
        ("train.target_transform", "sqrt", "one of none, log"),
        ("train.precision", "float16", "one of float32, bfloat16"),
        ("train.augment_rotation", "z", "one of none, vertical, any"),
        ("train.augment_scale", 1.0, "a number >= 0 and < 1"),
        ("train.augment_scale", -0.1, "a number >= 0 and < 1"),
        ("train.device", 0, "a string"),
        ("train.standardize_targets", "yes", "true or false"),
        ("eval.renders", -2, "an integer >= 0"),
        ("eval.plots", 1, "true or false"),
        ("data.kind", "mnist", "one of synthetic"),
        ("data.seed", -1, "an integer >= 0"),
        ("data.val_fraction", 1.0, "a number >= 0 and < 1 or null"),
        ("data.val_count", -1, "an integer >= 0 or null"),
        ("data.features", 3, "a string"),
        ("data.n_shapes", "many", "an integer >= 1"),
        ("data.strict", "no", "true or false"),
        ("data.on_error", "ignore", "one of raise, skip"),
        ("model.name", "zernett", "one of "),
        ("model.widths", [8, "x"], "a list of integers"),
        ("model.dropout", 1.5, "a number >= 0 and < 1"),
        ("model.angular_resolution", 0, "an integer >= 1"),
        ("patch.area", -3, "a number > 0 or null"),
        ("cache_dir", 5, "a folder path or null"),
    ],
)
def test_each_bad_value_names_the_key_the_value_and_what_is_expected(tmp_path, dotted, value, expected):
    config = tiny_config(tmp_path)
    if "." in dotted:
        section, key = dotted.split(".")
        config[section][key] = value
    else:
        config[dotted] = value
    with pytest.raises(ConfigError) as caught:
        parse_config(config)
    message = str(caught.value)
    assert message.startswith(f"{dotted} must be {expected}"), message
    assert f"got {value!r}" in message


def test_structure_errors_name_the_key(tmp_path):
    base = tiny_config(tmp_path)
    cases = [
        (dict(base, optimiser={}), "unknown config section 'optimiser'"),
        ({**base, "train": {"epoch": 3}}, "unknown key train.epoch (known: "),
        ({**base, "eval": {"render": 3}}, "unknown key eval.render"),
        ({**base, "train": [1, 2]}, "config section 'train' must be a mapping, got list"),
        ({**base, "patch": {"scales": {"r0": 5.0}}}, "patch.scales must be a list"),
        ({**base, "patch": {"scales": [3.0]}}, "patch.scales.0 must be a mapping"),
        ({**base, "patch": {"scales": [{"r0": 1.0, "radius": 2}]}}, "unknown key patch.scales.0.radius"),
        ({**base, "patch": {"scales": [{"n_max": 3}]}}, "patch.scales.0.r0 (the patch radius) is required"),
        ({**base, "patch": {"scales": [{"r0": -1.0}]}}, "patch.scales.0: "),
    ]
    for config, expected in cases:
        with pytest.raises(ConfigError) as caught:
            parse_config(config)
        assert expected in str(caught.value), (expected, str(caught.value))
    with pytest.raises(ConfigError, match="config must be a mapping"):
        parse_config([1])


def test_loader_keys_pass_through_and_keys_unknown_to_the_data_kind_are_named(tmp_path):
    config = tiny_config(tmp_path)
    config["data"] = {"kind": "segmentation", "meshes": "/somewhere", "num_classes": 3}
    config["model"]["nonlinearity"] = "regular"
    parsed = parse_config(config)
    assert parsed.data.options["meshes"] == "/somewhere" and parsed.model.options["nonlinearity"] == "regular"
    assert list(parsed.to_dict()["data"])[:5] == ["kind", "seed", "val_fraction", "val_count", "on_error"]
    config["data"]["root"] = "/elsewhere"
    with pytest.raises(ConfigError, match=r"unknown key data.root for data kind 'segmentation' \(known: .*meshes"):
        parse_config(config)
    config["data"] = {"kind": "synthetic", "area": 3.0}
    with pytest.raises(ConfigError, match="data.area is not a data option: the target area is patch.area"):
        parse_config(config)


def test_sections_check_their_values_when_made_directly():
    with pytest.raises(ConfigError, match="train.epochs must be an integer >= 0, got -5"):
        TrainSection(epochs=-5)
    with pytest.raises(ConfigError, match="train.lr"):
        dataclasses.replace(TrainSection(), lr=-1.0)


def test_a_stored_config_of_an_older_release_missing_newer_keys_gets_their_defaults():
    older = copy.deepcopy(TODAYS_FORMAT)
    del older["train"]["precision"], older["eval"]["plots"], older["data"]["on_error"]
    config = parse_config(older)
    assert config.train.precision == "float32" and config.eval.plots is True and config.data.on_error == "raise"


def test_the_former_data_strict_maps_to_on_error_with_a_deprecation_warning(tmp_path):
    for strict, on_error in ((True, "raise"), (False, "skip")):
        config = tiny_config(tmp_path)
        config["data"]["strict"] = strict
        with pytest.warns(FutureWarning, match=f"data.strict is deprecated: use data.on_error: {on_error}"):
            parsed = parse_config(config)
        assert parsed.data.on_error == on_error and "strict" not in parsed.to_dict()["data"]


def test_faust_splits_take_lists_or_quoted_ranges(tmp_path):
    config = {"data": {"kind": "faust", "root": str(tmp_path), "train_indices": "0:180", "test_indices": [180, 181]}}
    parsed = parse_config(config)
    assert parsed.data.options["train_indices"] == "0:180" and parsed.data.options["test_indices"] == [180, 181]
    for bad in (620, "0-180", "9:3"):  # 620: YAML's reading of an unquoted 10:20
        config["data"]["train_indices"] = bad
        with pytest.raises(ConfigError, match=r"data.train_indices must be a list of integers or a quoted range"):
            parse_config(config)


def test_a_config_written_before_refinement_passes_loads_with_one_pass():
    older = copy.deepcopy(TODAYS_FORMAT)
    del older["eval"]["refine_passes"]
    assert parse_config(older).eval.refine_passes == [1] and parse_config(older) == parse_config(TODAYS_FORMAT)
