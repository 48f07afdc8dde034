"""Shared test set-up: small analytic meshes (builders in tests/meshes.py) as fixtures.

pytest loads this file first and, because the test folders have no ``__init__.py``, puts this folder on
``sys.path``: test modules anywhere under tests/ import the builders with ``from meshes import ...``.
"""

import pytest
import torch
from meshes import grid, icosphere, open_cylinder, tetrahedron


@pytest.fixture
def sphere_surface():
    """A 162-vertex unit icosphere named "sphere" (a fresh copy per test)."""
    return icosphere(2)


@pytest.fixture
def grid_surface():
    """A flat 4 × 4 vertex grid of area 9 named "grid"."""
    return grid(4)


@pytest.fixture
def cylinder_surface():
    """An open cylinder of radius 1.5 and height 6 with outward normals, named "cylinder"."""
    return open_cylinder()


@pytest.fixture
def tetrahedron_surface():
    """The unit corner tetrahedron with outward normals."""
    return tetrahedron()


@pytest.fixture
def one_torch_thread():
    """Tiny tensors: threads only add contention on a shared machine (a sparse gradcheck 1 s -> 24 s)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
