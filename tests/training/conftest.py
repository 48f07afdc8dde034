"""Fixtures of the training tests: a session-wide operator cache for the tiny configurations, a tiny
correspondence data set in FAUST's layout, and a segmentation run that has learnt its task."""

from __future__ import annotations

import pytest
from meshes import ellipsoid, write_faust_layout, write_labelled_spheres
from tiny_configs import SPHERE_LEARNT_EPOCHS, sphere_config

from zernet.training import train


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory):
    """Preprocessed tiny creatures, shared by every test of the session."""
    return tmp_path_factory.mktemp("zernet-cache")


@pytest.fixture(scope="session")
def ellipsoid_faust_root(tmp_path_factory):
    """Five noisy ellipsoids sharing one connectivity (642 vertices), in FAUST's layout."""
    root = tmp_path_factory.mktemp("faust")
    write_faust_layout(root, [ellipsoid(noise=0.01, seed=i) for i in range(5)])
    return root


@pytest.fixture(scope="session")
def labelled_spheres(tmp_path_factory):
    """Six labelled spheres (``meshes.write_labelled_spheres``): shape5 under test/, the rest under train/."""
    root = tmp_path_factory.mktemp("spheres")
    write_labelled_spheres(root)
    return root


@pytest.fixture(scope="session")
def learnt_sphere_run(tmp_path_factory, labelled_spheres, cache_dir):
    """A zernet run that has learnt the spheres' labelling (``SPHERE_LEARNT_EPOCHS``), its refinement chosen on
    validation among 0, 1 and 2 rings: the run folder and its metrics."""
    run_dir = tmp_path_factory.mktemp("learnt") / "run"
    config = sphere_config(labelled_spheres, cache_dir, epochs=SPHERE_LEARNT_EPOCHS)
    config["eval"] = {"renders": 0, "plots": False, "refine_rings": [0, 1, 2]}
    metrics = train(config, run_dir, progress=False, workers=0)
    return run_dir, metrics
