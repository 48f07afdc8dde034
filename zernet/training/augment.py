"""Training-time augmentation of the input features: random rotations, scalings and smooth warps.

The patch operators are intrinsic (geodesic polar coordinates on the area-normalised surface), so a rigid
motion or a uniform scaling of a shape leaves them unchanged: only the input channels that depend on the
placement of the surface in space change. Those are the ``xyz`` part (rotated and scaled) and the ``normals``
part (rotated) of the feature kind (:mod:`zernet.data.features`); the other parts (``shape``, ``curvature``,
``ones``, ``membrane``) are invariant and left alone, so augmentation is only meaningful with ``xyz`` or
``normals`` among the features, and :func:`check_augmentation` refuses it otherwise.

Settings (``train`` section of the run configuration):

``augment_rotation``
    ``none`` (default); ``vertical``: a uniform angle about the y axis (the up axis of FAUST and of the
    generated bodies), for upright shapes; ``any``: a uniformly distributed rotation of SO(3).
``augment_scale``
    ``a`` in ``[0, 1)``: ``xyz`` is multiplied by a factor drawn uniformly from ``[1 - a, 1 + a]`` (0: off).
``augment_anisotropy``
    ``a`` in ``[0, 1)``: each axis of ``xyz`` (after the rotation) is multiplied by its own factor drawn
    uniformly from ``[1 - a, 1 + a]``: a taller, wider or deeper person.
``augment_warp``
    ``w`` in ``[0, 1)``: ``xyz`` is displaced by a smooth random field, the sum of three plane waves
    ``w r / 3 · u_k sin(2π (d_k · x) / λ_k + φ_k)`` (at most ``w r`` together) with ``r`` the shape's RMS distance from its centroid,
    random unit directions ``u_k``, ``d_k``, wavelengths ``λ_k`` uniform in ``[r, 3r]`` and phases: limbs and
    torso bend and thicken a little differently, as another person's would.

These change the input channels only: the patch operators, intrinsic to the surface, stay those of the
shape, so the network sees the same neighbourhoods with the positions of a slightly different body.

Each optimiser step draws one rotation and one factor per shape from a generator seeded by
``(train.seed, epoch, step)``, so a run is reproducible and a resumed run continues exactly.
Only training steps are augmented; validation, test and prediction see the shapes as they are.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from zernet.data.features import feature_parts, feature_slices
from zernet.inference.batch import with_directional
from zernet.training.config import ConfigError, TrainSection

__all__ = [
    "ROTATING_PARTS",
    "SCALING_PARTS",
    "augmenting",
    "check_augmentation",
    "random_rotation",
    "smooth_warp",
    "augment_records",
]

#: Feature parts whose 3 channels rotate with the surface, and those that also scale with it.
ROTATING_PARTS = ("xyz", "normals")
SCALING_PARTS = ("xyz",)


def augmenting(train: TrainSection) -> bool:
    """Whether ``train`` asks for any augmentation."""
    return (
        train.augment_rotation != "none"
        or train.augment_scale > 0
        or train.augment_anisotropy > 0
        or train.augment_warp > 0
    )


def check_augmentation(train: TrainSection, kind: str) -> None:
    """ConfigError if augmentation is asked for but feature ``kind`` has no channel it would change."""
    parts = feature_parts(kind)
    if train.augment_rotation != "none" and not set(parts) & set(ROTATING_PARTS):
        raise ConfigError(
            f"train.augment_rotation={train.augment_rotation} has no effect: the features {kind!r} are "
            "rotation-invariant (rotation changes only the xyz and normals parts); set it to none"
        )
    for name in ("augment_scale", "augment_anisotropy", "augment_warp"):
        if getattr(train, name) > 0 and not set(parts) & set(SCALING_PARTS):
            raise ConfigError(
                f"train.{name}={getattr(train, name)} has no effect: the features {kind!r} have no xyz part; "
                "set it to 0"
            )


def random_rotation(rng: np.random.Generator, mode: str) -> np.ndarray:
    """A 3x3 rotation: ``vertical`` about y by a uniform angle, ``any`` uniform on SO(3), ``none`` identity."""
    if mode == "none":
        return np.eye(3)
    if mode == "vertical":
        angle = rng.uniform(0.0, 2.0 * np.pi)
        c, s = np.cos(angle), np.sin(angle)
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    if mode == "any":
        # Uniform on SO(3): a uniformly random unit quaternion (Shoemake 1992).
        u1, u2, u3 = rng.uniform(size=3)
        a, b = np.sqrt(1.0 - u1), np.sqrt(u1)
        x, y, z, w = (
            a * np.sin(2 * np.pi * u2),
            a * np.cos(2 * np.pi * u2),
            b * np.sin(2 * np.pi * u3),
            b * np.cos(2 * np.pi * u3),
        )
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )
    raise ValueError(f"augment_rotation must be none, vertical or any, got {mode!r}")


def _unit_vectors(rng: np.random.Generator, count: int) -> np.ndarray:
    vectors = rng.normal(size=(count, 3))
    return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)


def smooth_warp(xyz: np.ndarray, rng: np.random.Generator, amplitude: float) -> np.ndarray:
    """``xyz`` (N, 3) displaced by the smooth random field of ``augment_warp`` (module docstring)."""
    centred = xyz - xyz.mean(axis=0)
    radius = float(np.sqrt((centred**2).sum(axis=1).mean()))
    moves, directions = _unit_vectors(rng, 3), _unit_vectors(rng, 3)
    wavelengths = rng.uniform(radius, 3.0 * radius, size=3)
    phases = rng.uniform(0.0, 2.0 * np.pi, size=3)
    waves = np.sin(2.0 * np.pi * (centred @ directions.T) / wavelengths + phases)  # (N, 3): one column per wave
    return xyz + (amplitude * radius / 3.0) * (waves @ moves)


def augment_records(
    records: Sequence,
    train: TrainSection,
    kind: str,
    degrees: Sequence[int],
    epoch: int,
    step: int,
    directional_order: int | None = None,
) -> list:
    """Copies of ``records`` with rotated and scaled placement-dependent features (see the module docstring).

    The copies share everything but ``features`` with the originals (whose features are never changed);
    directional operators of ``directional_order`` are built on the originals first, so the data set keeps
    them for later epochs. Without augmentation, ``records`` come back as they are.
    """
    if not augmenting(train):
        return list(records)
    slices = feature_slices(kind, degrees)
    rng = np.random.default_rng([int(train.seed), int(epoch), int(step), 0xA06])
    out = []
    for record in records:
        with_directional(record, directional_order)
        rotation = random_rotation(rng, train.augment_rotation).astype(np.float32)
        factor = np.float32(
            rng.uniform(1.0 - train.augment_scale, 1.0 + train.augment_scale) if train.augment_scale > 0 else 1.0
        )
        features = np.array(record.features, dtype=np.float32, copy=True)
        for part in ROTATING_PARTS:
            if part in slices:
                columns = slices[part]
                features[:, columns] = features[:, columns] @ rotation.T
        for part in SCALING_PARTS:
            if part in slices:
                features[:, slices[part]] *= factor
        # Drawn after the rotation and factor, so runs without them draw exactly as before.
        if train.augment_anisotropy > 0:
            axes = rng.uniform(1.0 - train.augment_anisotropy, 1.0 + train.augment_anisotropy, size=3)
            features[:, slices["xyz"]] *= axes.astype(np.float32)
        if train.augment_warp > 0:
            xyz = features[:, slices["xyz"]].astype(np.float64)
            features[:, slices["xyz"]] = smooth_warp(xyz, rng, train.augment_warp).astype(np.float32)
        out.append(dataclasses.replace(record, features=features))
    return out
