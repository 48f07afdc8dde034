"""Fixtures of the training tests: a session-wide operator cache for the tiny configurations."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory):
    """Preprocessed tiny creatures, shared by every test of the session."""
    return tmp_path_factory.mktemp("zernet-cache")
