"""Procedural "creatures" (no download, no optional dependency): the tests' shapes and ``configs/creatures.yaml``.

A creature is a closed surface: an ellipsoidal body with a few randomly placed parts of three kinds,

- **bump**: a round outward blob (Gaussian in the angle from its centre),
- **ridge**: an elongated outward crest along a great-circle arc,
- **dent**: a round inward depression,

made by displacing a near-uniform sphere mesh (Fibonacci points, convex hull) radially:
``x(u) = u · ρ_body(u) · (1 + Σ_k h_k g_k(u))``. Every shape gets its own seed, body axes, part count, part
positions, sizes and (optionally) a random rotation, and is scaled to :data:`SYNTHETIC_AREA`.

Tasks (``make_synthetic_dataset(task=...)``):

- ``"segmentation"`` (classification, 4 classes :data:`PART_NAMES`): the part a vertex belongs to. Vertex u
  belongs to part k when part k's normalised profile ``g_k(u)`` is the largest of all parts and at least
  :data:`PART_THRESHOLD`; otherwise to the body. Bumps and dents differ by the sign of the curvature, bumps
  and ridges by their shape (round vs elongated): position alone cannot tell them apart, since parts sit
  anywhere and the shapes are randomly rotated.
- ``"regression"``: the mean curvature H at each vertex (1/length, positive where the surface bends like a
  sphere), from the cotangent Laplacian, ``H n = Δx / 2`` with the mixed vertex areas of potpourri3d,
  lightly smoothed (two area-weighted neighbour averages) to remove discretisation noise. It depends on
  local shape only, not on where the vertex is, so xyz alone cannot predict it.

Patch settings (:func:`demo_patch_configs`) keep the paper's sampling density: the paper uses 12000 samples
on area 15000 with r0 = 5.5, i.e. 12000 · π 5.5² / 15000 ≈ 76 samples per patch disk (of which it fits 50).
Here the area is 1000 and r0 = 2.5 (a patch covers about 2 % of the surface, ~30 of 1500 vertices), so
4000 samples give 4000 · π 2.5² / 1000 ≈ 79 samples per disk, and ``patch_size = 50`` of them are fitted.
"""

from __future__ import annotations

import json
from functools import partial

import numpy as np
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from zernet.data.dataset import DatasetError, ShapeDataset
from zernet.data.options import LoaderOptions
from zernet.data.preprocess import build_dataset
from zernet.data.source import ShapeSource
from zernet.geometry import Surface
from zernet.operators import PatchConfig

__all__ = [
    "SYNTHETIC_AREA",
    "PART_NAMES",
    "PART_THRESHOLD",
    "SYNTHETIC_TASKS",
    "make_creature",
    "demo_patch_configs",
    "make_synthetic_dataset",
    "fibonacci_sphere",
    "load_creature",
]

#: Every creature is scaled to this surface area (see the module docstring for the patch density).
SYNTHETIC_AREA = 1000.0
#: Class names of the segmentation task, by label.
PART_NAMES = ("body", "bump", "ridge", "dent")
#: A vertex belongs to a part where the part's normalised profile is at least this (else to the body).
PART_THRESHOLD = 0.3
SYNTHETIC_TASKS = ("segmentation", "regression")
# Bump when the generator changes, so cached shapes of an older generator are not reused.
_GENERATOR_VERSION = 1


def fibonacci_sphere(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Near-uniform unit-sphere mesh: n Fibonacci-spiral points and their convex hull.

    Returns (vertices (n, 3) float64, faces (F, 3) int64) with counter-clockwise faces seen from outside.
    """
    if n < 12:
        raise DatasetError(f"a synthetic shape needs at least 12 vertices, got {n}")
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5**0.5) * i
    radius = np.sqrt(1.0 - z**2)
    points = np.stack([radius * np.cos(phi), radius * np.sin(phi), z], axis=1)
    faces = ConvexHull(points).simplices.astype(np.int64)
    # Qhull does not orient simplices: flip those whose normal points inwards.
    a, b, c = points[faces[:, 0]], points[faces[:, 1]], points[faces[:, 2]]
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), a + b + c) < 0
    faces[inward] = faces[inward][:, ::-1]
    return points, faces


def _random_directions(rng: np.random.Generator, count: int, min_angle: float) -> np.ndarray:
    """``count`` unit vectors at least ``min_angle`` apart when possible (rejection sampling, then relaxed)."""
    chosen: list[np.ndarray] = []
    attempts = 0
    while len(chosen) < count:
        candidate = rng.normal(size=3)
        candidate /= np.linalg.norm(candidate)
        attempts += 1
        limit = min_angle if attempts < 2000 else 0.0
        if all(np.arccos(np.clip(candidate @ c, -1, 1)) >= limit for c in chosen):
            chosen.append(candidate)
    return np.array(chosen)


def make_creature(
    seed: int,
    n_vertices: int = 1500,
    rotate: bool = True,
    area: float = SYNTHETIC_AREA,
    parts: tuple[tuple[int, int], tuple[int, int], tuple[int, int]] = ((2, 4), (2, 3), (2, 3)),
) -> tuple[Surface, np.ndarray, np.ndarray]:
    """One random creature.

    Args:
        seed: everything about the shape follows from it.
        n_vertices: mesh size (the vertex count is exact; ~2 n faces).
        rotate: apply a uniformly random rotation, so that absolute position says nothing about the labels.
        area: surface area of the result.
        parts: (min, max) inclusive counts of bumps, ridges and dents.

    Returns:
        (surface, labels (N,) int64 in 0..3 = :data:`PART_NAMES`, mean curvature (N,) float64 at ``area``).
    """
    rng = np.random.default_rng(seed)
    directions, faces = fibonacci_sphere(n_vertices)
    axes = rng.uniform(0.8, 1.25, size=3)
    body = 1.0 / np.sqrt(((directions / axes) ** 2).sum(axis=1))

    kinds = [kind for kind, (low, high) in zip((1, 2, 3), parts) for _ in range(rng.integers(low, high + 1))]
    centres = _random_directions(rng, len(kinds), min_angle=0.8)
    displacement = np.zeros(n_vertices)
    profiles = np.zeros((len(kinds), n_vertices))
    for k, (kind, centre) in enumerate(zip(kinds, centres)):
        if kind == 2:  # ridge: distance to a great-circle arc of half-length L through the centre
            tangent = np.cross(centre, rng.normal(size=3))
            tangent /= np.linalg.norm(tangent)
            binormal = np.cross(centre, tangent)
            along = np.arctan2(directions @ tangent, directions @ centre)
            across = np.arcsin(np.clip(directions @ binormal, -1, 1))
            half_length, width = rng.uniform(0.45, 0.75), rng.uniform(0.12, 0.16)
            distance2 = across**2 + np.maximum(np.abs(along) - half_length, 0.0) ** 2
            height = rng.uniform(0.15, 0.25)
        else:  # bump (outward) or dent (inward): round, Gaussian in the angle from the centre
            width = rng.uniform(0.22, 0.32)
            distance2 = np.arccos(np.clip(directions @ centre, -1, 1)) ** 2
            height = rng.uniform(0.25, 0.4) if kind == 1 else -rng.uniform(0.15, 0.25)
        profiles[k] = np.exp(-distance2 / (2 * width**2))
        displacement += height * profiles[k]

    vertices = directions * (body * (1.0 + displacement))[:, None]
    labels = np.zeros(n_vertices, dtype=np.int64)
    if kinds:
        strongest = profiles.argmax(axis=0)
        owned = profiles.max(axis=0) >= PART_THRESHOLD
        labels[owned] = np.array(kinds)[strongest[owned]]

    # Scale to the requested area (about the origin; the creature is roughly centred there).
    cross = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    vertices *= np.sqrt(area / (0.5 * np.linalg.norm(cross, axis=1).sum()))
    if rotate:
        vertices = vertices @ Rotation.random(random_state=rng).as_matrix().T
    surface = Surface(vertices, faces, name=f"creature(seed={seed})")
    curvature = surface.mean_curvature(smoothing_steps=2)
    return surface, labels, curvature


def load_creature(seed: int, n_vertices: int, rotate: bool, task: str) -> tuple[Surface, np.ndarray]:
    """ShapeSource loader of one creature and its ``task`` target (module level, so workers can unpickle it)."""
    surface, labels, curvature = make_creature(seed, n_vertices=n_vertices, rotate=rotate)
    return surface, labels if task == "segmentation" else curvature


def demo_patch_configs(n_scales: int = 1, **overrides) -> list[PatchConfig]:
    """Patch settings for the synthetic creatures (paper density, see the module docstring).

    Scale s (0-based) has radius ``2.5 · 2**s`` and ``n_samples = 4000`` (the larger scale sees the same
    samples, so its disks hold four times as many and ``patch_size`` still picks 50 of them).
    ``overrides`` are passed to every PatchConfig (e.g. ``n_max=3``).
    """
    if n_scales < 1:
        raise DatasetError(f"n_scales must be >= 1, got {n_scales}")
    settings = {"n_samples": 4000, "patch_size": 50}
    settings.update(overrides)
    return [PatchConfig(r0=2.5 * 2**s, **settings) for s in range(n_scales)]


def make_synthetic_dataset(
    task: str = "segmentation",
    n_shapes: int = 40,
    n_vertices: int = 1500,
    rotate: bool = True,
    test_fraction: float = 0.2,
    area: float | None = None,
    options: LoaderOptions = LoaderOptions(),
) -> ShapeDataset:
    """The built-in data set of ``n_shapes`` creatures (registry names "synthetic" / "synthetic-parts").

    Shape i is generated from seed ``options.seed * 100003 + i``; the last ``round(test_fraction · n_shapes)``
    shapes are the test split, and ``options.n_val`` shapes (count or fraction, default 0.1) are carved from
    the rest, seeded. ``options.patch_configs`` defaults to :func:`demo_patch_configs` (), tuned for ``area``
    = :data:`SYNTHETIC_AREA` (the default, also for None; another area rescales the shapes and the curvature
    target). Returns a :class:`ShapeDataset` with task "classification" (4 classes, :data:`PART_NAMES`) or
    "regression" (mean curvature; its area exponent is -1/2, so it stays consistent if a different area is
    forced).
    """
    options = options.with_defaults(n_val=0.1, patch_configs=demo_patch_configs())
    if task not in SYNTHETIC_TASKS:
        raise DatasetError(f"synthetic task must be one of {SYNTHETIC_TASKS}, got {task!r}")
    if n_shapes < 2:
        raise DatasetError(f"the synthetic data set needs at least 2 shapes (train and test), got {n_shapes}")
    if not 0 < test_fraction < 1:
        raise DatasetError(f"test_fraction must be in (0, 1), got {test_fraction}")
    target_exponent = -0.5 if task == "regression" else 0.0  # curvature is 1/length
    sources = []
    for i in range(n_shapes):
        shape_seed = options.seed * 100003 + i
        key = json.dumps(
            {"generator": _GENERATOR_VERSION, "seed": shape_seed, "n": n_vertices, "rotate": rotate, "task": task}
        )
        sources.append(
            ShapeSource(
                name=f"creature_{i:03d}",
                load=partial(load_creature, shape_seed, n_vertices, rotate, task),
                key=key,
                target_exponent=target_exponent,
            )
        )
    n_test = min(n_shapes - 1, max(1, int(round(test_fraction * n_shapes))))
    names = [s.name for s in sources]
    return build_dataset(
        sources,
        target_area=SYNTHETIC_AREA if area is None else area,
        task="classification" if task == "segmentation" else "regression",
        num_classes=len(PART_NAMES) if task == "segmentation" else None,
        split_names={"train": names[: n_shapes - n_test], "test": names[n_shapes - n_test :]},
        info={
            "kind": "synthetic",
            "task": task,
            "class_names": list(PART_NAMES) if task == "segmentation" else None,
            "n_vertices": n_vertices,
            "rotate": rotate,
            "target_exponent": target_exponent,
        },
        **options.build_arguments(),
    )
