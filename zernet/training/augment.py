"""Training-time augmentation of the input features: random rigid rotations and scalings.

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

Each optimiser step draws one rotation and one factor per shape from a generator seeded by
``(train.seed, epoch, step)``, so a run is reproducible and a resumed run continues exactly.
Only training steps are augmented; validation, test and prediction see the shapes as they are.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from zernet.data.features import FEATURE_PARTS, feature_channels, feature_parts
from zernet.training.batch import with_directional
from zernet.training.config import ConfigError, TrainSection

__all__ = [
    "ROTATING_PARTS",
    "SCALING_PARTS",
    "augmenting",
    "feature_slices",
    "check_augmentation",
    "random_rotation",
    "augment_records",
]

#: Feature parts whose 3 channels rotate with the surface, and those that also scale with it.
ROTATING_PARTS = ("xyz", "normals")
SCALING_PARTS = ("xyz",)


def augmenting(train: TrainSection) -> bool:
    """Whether ``train`` asks for any augmentation."""
    return train.augment_rotation != "none" or train.augment_scale > 0


def feature_slices(kind: str, degrees: Sequence[int]) -> dict[str, slice]:
    """The columns of each part of feature ``kind`` (``degrees``: the Zernike degree of each patch scale)."""
    slices, start = {}, 0
    for part in feature_parts(kind):
        width = FEATURE_PARTS[part] or feature_channels(part, list(degrees))
        slices[part] = slice(start, start + width)
        start += width
    return slices


def check_augmentation(train: TrainSection, kind: str) -> None:
    """ConfigError if augmentation is asked for but feature ``kind`` has no channel it would change."""
    parts = feature_parts(kind)
    if train.augment_rotation != "none" and not set(parts) & set(ROTATING_PARTS):
        raise ConfigError(
            f"train.augment_rotation={train.augment_rotation} has no effect: the features {kind!r} are "
            "rotation-invariant (rotation changes only the xyz and normals parts); set it to none"
        )
    if train.augment_scale > 0 and not set(parts) & set(SCALING_PARTS):
        raise ConfigError(
            f"train.augment_scale={train.augment_scale} has no effect: the features {kind!r} have no "
            "xyz part; set it to 0"
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
        out.append(dataclasses.replace(record, features=features))
    return out
