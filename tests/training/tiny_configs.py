"""Tiny run configurations shared by the training and command-line tests.

Six 200-vertex synthetic creatures (test_fraction 0.34: 3 train, 1 val, 2 test), one small patch scale and
a small model: an epoch takes well under a second. Three training creatures are too few to learn their parts
from (the tiny model answers the majority class on the test creatures); a test that needs a model that has
learnt its task trains :func:`sphere_config` instead: six 42-vertex spheres labelled by a plane
(``tests/meshes.py``), learnt in :data:`SPHERE_LEARNT_EPOCHS` epochs. ``tests/training/conftest.py`` offers
them as fixtures; ``tests/test_cli.py`` imports this module directly (conftest fixtures are only visible below
their folder).
"""

from __future__ import annotations

#: Epochs after which a :func:`sphere_config` run has learnt the spheres' labelling: zernet, its
#: direction-preserving variant and FeaStNet reach validation accuracy 1 by epoch 7 to 12 and test accuracy 1
#: (the majority class is 0.60 of the test sphere's vertices); a few seconds.
SPHERE_LEARNT_EPOCHS = 20


def _tiny(cache_dir, train: dict, dropout: float, renders: int) -> dict:
    return {
        "data": {
            "kind": "synthetic",
            "task": "segmentation",
            "n_shapes": 6,
            "n_vertices": 200,
            "test_fraction": 0.34,
            "val_count": 1,
            "seed": 0,
        },
        "patch": {"scales": [{"r0": 5.0, "n_samples": 800, "patch_size": 20, "n_max": 3}]},
        "model": {"name": "zernet", "widths": [8, 8, 16], "angular_resolution": 2, "dropout": dropout},
        "train": train,
        "eval": {"renders": renders, "plots": False},
        "cache_dir": str(cache_dir),
    }


def tiny_config(cache_dir, **train_options) -> dict:
    """Two epochs, dropout 0.1; ``train_options`` override ``train`` keys."""
    return _tiny(cache_dir, {"epochs": 2, "seed": 0, "threads": 1, "lr": 1e-2, **train_options}, dropout=0.1, renders=1)


def cli_config(cache_dir) -> dict:
    """One epoch: a full train/evaluate/predict cycle of the command in seconds."""
    return _tiny(cache_dir, {"epochs": 1, "seed": 0, "threads": 1, "lr": 1e-2}, dropout=0.1, renders=0)


def faults_config(cache_dir, epochs: int = 3) -> dict:
    """Dropout 0.2, so the RNG states matter for resume; no early stopping."""
    return _tiny(
        cache_dir, {"epochs": epochs, "seed": 1, "threads": 1, "lr": 1e-2, "patience": None}, dropout=0.2, renders=0
    )


def ddp_config(cache_dir) -> dict:
    """No dropout (a distributed run and its one-process replay share every random number); weight decay,
    since Adam alone is nearly invariant to the gradient's scale, so a sum instead of a mean over the
    ranks would go unnoticed."""
    return _tiny(
        cache_dir,
        {"epochs": 2, "seed": 3, "threads": 1, "lr": 1e-2, "weight_decay": 0.05, "patience": None},
        dropout=0.0,
        renders=0,
    )


def faust_run_config(root, n_vertices: int, patch: dict, train: dict | None = None, eval: dict | None = None) -> dict:
    """A correspondence run on the five meshes of a FAUST-layout folder ``root`` (3 train, 1 of them
    validation, 2 test), one epoch of a small model; ``train`` and ``eval`` entries override the defaults."""
    return {
        "data": {
            "kind": "faust",
            "root": str(root),
            "train_indices": [0, 1, 2],
            "test_indices": [3, 4],
            "val_count": 1,
            "n_vertices": n_vertices,
            "workers": 0,
        },
        "patch": {"area": 100.0, "scales": [patch]},
        "model": {"name": "zernet", "widths": [8, 16], "angular_resolution": 2, "dropout": 0.0},
        "train": {"epochs": 1, "seed": 0, "threads": 1, "lr": 1e-2, **(train or {})},
        "eval": {"renders": 0, "plots": False, **(eval or {})},
        "cache_dir": str(root / "cache"),
    }


def sphere_config(meshes, cache_dir, epochs: int = 2, **data) -> dict:
    """Segmentation of the labelled spheres written by ``meshes.write_labelled_spheres`` into ``meshes`` (the
    segmentation loader's layout; 4 train, 1 of them validation, 1 test); ``data`` entries override the
    defaults."""
    return {
        "data": {
            "kind": "segmentation",
            "meshes": str(meshes),
            "num_classes": 2,
            "val_count": 1,
            "seed": 0,
            "features": "xyz",
            **data,
        },
        "patch": {"area": 100.0, "scales": [{"r0": 3.0, "n_samples": 400, "patch_size": 12, "n_max": 2}]},
        "model": {"name": "zernet", "widths": [4, 4], "angular_resolution": 2, "dropout": 0.0},
        "train": {"epochs": epochs, "seed": 0, "threads": 1, "lr": 0.01, "patience": None},
        "eval": {"renders": 1, "plots": True},
        "cache_dir": str(cache_dir),
    }
