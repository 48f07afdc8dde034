"""Fixtures of the training tests: a session-wide operator cache for the tiny configurations, and a tiny
correspondence data set in FAUST's layout."""

from __future__ import annotations

import pytest
import trimesh
from meshes import ellipsoid


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory):
    """Preprocessed tiny creatures, shared by every test of the session."""
    return tmp_path_factory.mktemp("zernet-cache")


@pytest.fixture(scope="session")
def faust_root(tmp_path_factory):
    """Five noisy ellipsoids sharing one connectivity (642 vertices), in FAUST's layout."""
    root = tmp_path_factory.mktemp("faust")
    folder = root / "MPI-FAUST" / "training" / "registrations"
    folder.mkdir(parents=True)
    for i in range(5):
        shape = ellipsoid(noise=0.01, seed=i)
        trimesh.Trimesh(shape.vertices, shape.faces, process=False).export(folder / f"tr_reg_{i:03d}.ply")
    return root
