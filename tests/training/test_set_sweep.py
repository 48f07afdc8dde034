"""A sweep over ``zernet train CONFIG --set KEY=VALUE``: whatever the key and the value (wrong types, out of
range, unknown keys, keys into values or lists), the command answers with exit code 0 or 2 and a message,
never "internal error" (exit 1).

The configuration points at a mesh folder that does not exist and the swept keys leave every path alone,
so a valid override fails fast on the missing data and nothing is ever trained or preprocessed.
"""

from __future__ import annotations

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from zernet.cli import main
from zernet.training import DEFAULT_CONFIG

# Every key of the sections, the segmentation loader's own options, patch settings of the first scale, and
# some that do not exist anywhere. Paths (data.meshes, data.labels, cache_dir) and data.kind are left alone.
_PATHS = {"meshes", "labels", "root"}
KNOWN = (
    [
        f"{section}.{key}"
        for section, keys in DEFAULT_CONFIG.items()
        if isinstance(keys, dict)
        for key in keys
        if key not in _PATHS | {"kind", "scales"}
    ]
    + [
        f"data.{key}"
        for key in (
            "num_classes",
            "class_names",
            "label_base",
            "label_kind",
            "test",
            "test_fraction",
            "features",
            "repair",
            "workers",
            "strict",
        )
    ]
    + [
        f"patch.scales.0.{key}"
        for key in ("r0", "n_samples", "patch_size", "n_max", "subtract_center", "backend", "seed", "ridge")
    ]
    + [f"model.{key}" for key in ("widths", "dropout", "angular_resolution", "pooling", "n_max", "k")]
    + [
        "patch.scales",
        "patch.scales.3.r0",
        "train.epochs.deep",
        "data",
        "model",
        "eval",
        "area",
        "data.area",
        "model.bogus_option",
        "train.bogus",
        "nosection.key",
        "patch.scales.x.r0",
    ]
)

VALUES = st.one_of(
    st.integers(min_value=-(10**12), max_value=10**12).map(str),
    st.sampled_from(
        [
            "0",
            "-1",
            "1",
            "2",
            "0.5",
            "1.0e-3",
            "-3.5",
            ".nan",
            ".inf",
            "-.inf",
            "1e400",
            "null",
            "true",
            "false",
            "two",
            "abc",
            "''",
            "[]",
            "{}",
            "[1, 2]",
            "[8, -1]",
            "[a, b]",
            "[0]",
            "[[1]]",
            "{r0: 1}",
            "[{r0: 1.0}]",
            "[{r0: -1}]",
            "[{n_max: 3}]",
            "xyz+normals",
            "shape+curvature",
            "xyz+colour",
            "cuda:7",
            "cpu",
            "meta",
            "auto",
            "skip",
            "raise",
            "face",
            "vertex",
            "1.5",
            "- a",
            ": :",
            "[unclosed",
            "!!python/object:os.system x",
        ]
    ),
    st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=8),
    st.lists(st.integers(min_value=-3, max_value=300), max_size=4).map(
        lambda v: yaml.safe_dump(v, default_flow_style=True).strip()
    ),
)
KEYS = st.one_of(
    st.sampled_from(KNOWN), st.from_regex(r"\A(data|model|train|eval|patch)\.[a-z_]{1,10}\Z", fullmatch=True)
)


@settings(max_examples=120, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(overrides=st.lists(st.tuples(KEYS, VALUES), min_size=1, max_size=2))
def test_no_set_value_yields_an_internal_error(tmp_path_factory, overrides):
    tmp = tmp_path_factory.mktemp("sweep")
    config = {
        "data": {"kind": "segmentation", "meshes": str(tmp / "no-such-meshes"), "num_classes": 2},
        "patch": {"area": 100.0, "scales": [{"r0": 3.0, "n_samples": 400, "patch_size": 12, "n_max": 2}]},
        "model": {"name": "zernet", "widths": [4, 4]},
        "train": {"epochs": 1, "threads": 1},
        "cache_dir": str(tmp / "cache"),
    }
    path = tmp / "config.yaml"
    path.write_text(yaml.safe_dump(config))
    arguments = [f"{key}={value}" for key, value in overrides]
    code = main(
        ["train", str(path), "--run-dir", str(tmp / "run"), "--no-progress", "--workers", "0", "--set", *arguments]
    )
    assert code in (0, 2), arguments


def test_the_sweep_reaches_each_kind_of_error(tmp_path, capsys):
    """The swept messages name the key and what is expected: a few of them, pinned."""
    path = tmp_path / "config.yaml"
    path.write_text(
        yaml.safe_dump(
            {
                "data": {"kind": "segmentation", "meshes": str(tmp_path / "none"), "num_classes": 2},
                "patch": {"scales": [{"r0": 3.0, "n_max": 2}]},
            }
        )
    )
    cases = {
        "train.epochs=two": "train.epochs must be an integer >= 0, got 'two'",
        "data.num_classes=0": "data.num_classes must be an integer >= 1, got 0",
        "patch.scales.0.n_max=-1": "patch.scales.0: ",
        "data.label_kind=edge": "data.label_kind must be one of auto, vertex, face, got 'edge'",
        "train.nosuch=1": "unknown key train.nosuch",
        "model.widths=[8, -1]": "model 'zernet' cannot be built from its options (model.widths=[8, -1])",
        "train.epochs.deep=1": "train.epochs must be an integer >= 0, got {'deep': 1}",
    }
    for override, expected in cases.items():
        assert main(["train", str(path), "--run-dir", str(tmp_path / "run"), "--set", override]) == 2, override
        err = capsys.readouterr().err
        assert expected in err and "internal error" not in err, (override, err)
