"""Fixtures of the training tests: a session-wide operator cache for the tiny configurations, and a tiny
correspondence data set in FAUST's layout."""

from __future__ import annotations

import pytest
from meshes import ellipsoid, write_faust_layout


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
