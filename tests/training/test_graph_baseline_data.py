"""A model that reads only the mesh graph (FeaStNet) is trained and run without patch operators."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from meshes import icosphere, majority_fraction
from tiny_configs import SPHERE_LEARNT_EPOCHS, sphere_config, tiny_config

from zernet.data import DatasetError, LoaderOptions, load_dataset
from zernet.inference import load_checkpoint, predict
from zernet.training import ConfigError, parse_config, train
from zernet.training.build import needs_operators

PATCH = [{"r0": 5.0, "n_samples": 800, "patch_size": 20, "n_max": 3}]
SYNTHETIC = dict(task="segmentation", n_shapes=4, n_vertices=200, test_fraction=0.25)


def _operator_files(cache) -> list:
    """Patch operators are cached at the top of the cache folder; the shapes themselves under shapes/."""
    return sorted(cache.glob("*.zop"))


def test_data_without_operators_has_the_same_features_edges_and_targets(tmp_path):
    def options(cache, **more):
        return LoaderOptions(patch_configs=PATCH, cache_dir=cache, n_val=1, workers=0, progress=False, **more)

    with_ops = load_dataset("synthetic", options=options(tmp_path / "a"), **SYNTHETIC)
    without = load_dataset("synthetic", options=options(tmp_path / "b", patch_operators=False), **SYNTHETIC)
    assert _operator_files(tmp_path / "a") and not _operator_files(tmp_path / "b")
    assert without.patch_configs == [] and without.splits == with_ops.splits
    for a, b in zip(with_ops, without):
        assert len(a.geometry.operators) == 1 and b.geometry.operators == []
        np.testing.assert_array_equal(a.features, b.features)
        np.testing.assert_array_equal(a.target, b.target)
        assert torch.equal(a.geometry.edge_index, b.geometry.edge_index)
        assert b.geometry.n_vertices == a.surface.n_vertices


def test_feastnet_run_builds_no_operators_and_predicts_without_them(tmp_path, labelled_spheres):
    cache = tmp_path / "cache"
    config = sphere_config(labelled_spheres, cache, epochs=SPHERE_LEARNT_EPOCHS)
    config["model"] = {"name": "feastnet", "widths": [8, 8, 16], "dropout": 0.0}
    config["eval"] = {"renders": 0, "plots": False}
    metrics = train(config, tmp_path / "run", progress=False, workers=0)
    # It learns from the mesh graph alone (measured: every test vertex right, the majority class 60 %).
    labels = np.loadtxt(labelled_spheres / "test" / "shape5.txt", dtype=np.int64)
    assert metrics["summary"]["accuracy"] > majority_fraction(labels) + 0.3
    assert not _operator_files(cache) and list((cache / "shapes").glob("*.npz"))
    checkpoint = load_checkpoint(tmp_path / "run" / "best.pt")
    assert checkpoint["preprocess"]["patch_configs"] == []
    answers = predict(tmp_path / "run", icosphere(2), cache_dir=cache)  # finer than the training spheres
    assert answers.shape == (162,) and not _operator_files(cache)


def test_operators_are_built_when_the_model_or_the_features_read_them(tmp_path):
    config = tiny_config(tmp_path, epochs=1)
    assert needs_operators(parse_config(config))  # zernet reads them
    config["model"] = {"name": "feastnet"}
    assert not needs_operators(parse_config(config))
    config["data"]["features"] = "xyz+shape"  # shape descriptors are fitted by the operators
    assert needs_operators(parse_config(config))
    config["data"]["features"] = "xyz+volume"
    with pytest.raises(ConfigError, match="data.features"):
        needs_operators(parse_config(config))
    with pytest.raises(DatasetError, match="patch_operators=False"):
        LoaderOptions(patch_configs=PATCH, feature_kind="shape", patch_operators=False)
