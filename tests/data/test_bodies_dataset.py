"""The data kind "bodies": generated bodies as a data set without files, through load_dataset and a run config.

Tiny coarse bodies (369 vertices), small patches: seconds once anny's own model cache exists.
"""

import importlib.util
import sys

import numpy as np
import pytest

from zernet.data import DATASET_KINDS, DatasetError, load_dataset
from zernet.data.bodies import BodyGenerator
from zernet.data.segmentation import HUMAN_PART_NAMES
from zernet.training import build_dataset

pytestmark = pytest.mark.skipif(importlib.util.find_spec("anny") is None, reason="needs the bodies extra (anny)")

COARSE = "coarse-369"
PATCH = {"r0": 20.0, "n_samples": 800, "patch_size": 20, "n_max": 2}


def _load(cache, **arguments):
    settings = {
        "count": 5,
        "n_test": 2,
        "topology": COARSE,
        "val_count": 1,
        "area": 1000.0,
        "workers": 0,
        "progress": False,
        "patch_configs": [PATCH],
        "cache_dir": cache,
    }
    settings.update(arguments)
    return load_dataset("bodies", **settings)


def test_segmentation_kind_holds_the_generated_bodies_and_their_parts(tmp_path):
    dataset = _load(tmp_path, task="segmentation")
    assert "bodies" in DATASET_KINDS
    assert dataset.task == "classification" and dataset.num_classes == 8 and not dataset.correspondence
    assert dataset.info["class_names"] == list(HUMAN_PART_NAMES)
    assert {split: len(indices) for split, indices in dataset.splits.items()} == {"train": 2, "val": 1, "test": 2}
    assert sorted(dataset.names[i] for i in dataset.splits["test"]) == ["body_003", "body_004"]
    generator = BodyGenerator(COARSE, "varied", seed=0, cache_dir=tmp_path)
    for number, split, index in ((0, "train", 0), (4, "test", 1)):
        record = dataset[dataset.names.index(f"body_{number:03d}")]
        body = generator.body(index, split)
        np.testing.assert_array_equal(record.target, body.parts)
        # Scaled to the requested area, otherwise the same body (vertex for vertex).
        scale = np.ptp(record.surface.vertices, axis=0) / np.ptp(body.vertices, axis=0)
        np.testing.assert_allclose(scale, scale[0], rtol=1e-9)
        assert record.surface.area == pytest.approx(1000.0, rel=1e-6)


def test_correspondence_kind_labels_every_vertex_by_its_index(tmp_path):
    dataset = _load(tmp_path, task="correspondence")
    assert dataset.correspondence and dataset.num_classes == 369
    for record in dataset:
        np.testing.assert_array_equal(record.target, np.arange(369))
        np.testing.assert_array_equal(record.surface.faces, dataset[0].surface.faces)


def test_a_second_load_needs_neither_the_body_model_nor_preprocessing(tmp_path, monkeypatch):
    first = _load(tmp_path, task="segmentation")
    monkeypatch.setitem(sys.modules, "anny", None)  # the model cannot be built any more
    again = _load(tmp_path, task="segmentation")
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a.surface.vertices, b.surface.vertices)
        np.testing.assert_array_equal(a.target, b.target)
    # Other bodies (another seed) would need the model: the error names the extra.
    with pytest.raises(DatasetError, match=r"zernet\[bodies\]"):
        _load(tmp_path, task="segmentation", body_seed=5)


def test_seeds_and_arguments(tmp_path):
    base = _load(tmp_path, task="segmentation")
    other = _load(tmp_path, task="segmentation", body_seed=1)
    assert np.abs(base[0].surface.vertices - other[0].surface.vertices).max() > 0.1
    with pytest.raises(DatasetError, match="task must be one of segmentation, correspondence"):
        _load(tmp_path, task="classification")
    with pytest.raises(DatasetError, match="n_test"):
        _load(tmp_path, count=2, n_test=2)
    with pytest.raises(TypeError, match="unknown option.*n_shapes.*data kind 'bodies'"):
        _load(tmp_path, n_shapes=3)


def test_a_run_configuration_reads_the_bodies_kind(tmp_path):
    config = {
        "data": {
            "kind": "bodies",
            "task": "correspondence",
            "count": 4,
            "n_test": 1,
            "val_count": 1,
            "topology": COARSE,
            "poses": "mild",
            "seed": 3,
            "features": "xyz+normals",
        },
        "patch": {"area": 1000, "scales": [PATCH]},
        "cache_dir": str(tmp_path),
    }
    dataset = build_dataset(config, progress=False, workers=0)
    assert dataset.correspondence and dataset.info["poses"] == "mild" and dataset.info["body_seed"] == 3
    assert dataset[0].features.shape == (369, 6)
