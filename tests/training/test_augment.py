"""Augmentation by rigid rotations and scalings: only the placement-dependent inputs change, exactly as a rigid
motion of the surface would change them; reproducible per (seed, epoch, step); refused where meaningless."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tiny_configs import tiny_config

from zernet.data.dataset import ShapeRecord
from zernet.data.features import compute_features, feature_channels, feature_slices
from zernet.data.synthetic import make_creature
from zernet.inference import load_checkpoint
from zernet.training import ConfigError, train
from zernet.training.augment import (
    augment_records,
    augmenting,
    check_augmentation,
    random_rotation,
    smooth_warp,
)
from zernet.training.config import TrainSection


def _record(kind: str = "xyz+normals+ones") -> ShapeRecord:
    surface = make_creature(seed=3, n_vertices=150)[0]
    features = compute_features(surface, kind)
    return ShapeRecord(name="creature", surface=surface, features=features, target=None, geometry=None)


@pytest.mark.parametrize("mode", ["vertical", "any"])
def test_rotations_are_proper(mode):
    rng = np.random.default_rng(0)
    for _ in range(20):
        rotation = random_rotation(rng, mode)
        assert np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(rotation), 1.0)
        if mode == "vertical":  # the up axis y stays put
            assert np.allclose(rotation @ [0.0, 1.0, 0.0], [0.0, 1.0, 0.0])


def test_any_rotation_is_uniform():
    """Uniform on SO(3): E[R] = 0 and E[R_ij^2] = 1/3."""
    rng = np.random.default_rng(1)
    rotations = np.stack([random_rotation(rng, "any") for _ in range(4000)])
    assert np.abs(rotations.mean(axis=0)).max() < 0.05
    assert np.allclose((rotations**2).mean(axis=0), 1.0 / 3.0, atol=0.03)


def test_feature_slices_follow_the_parts():
    slices = feature_slices("ones+xyz+shape+normals", [5])
    assert slices["ones"] == slice(0, 1) and slices["xyz"] == slice(1, 4)
    width = feature_channels("shape", 5)
    assert slices["shape"] == slice(4, 4 + width) and slices["normals"] == slice(4 + width, 7 + width)


def test_augmented_features_are_a_rigid_motion_and_scaling():
    record = _record()
    original = record.features.copy()
    train = TrainSection(augment_rotation="any", augment_scale=0.2, seed=5)
    (copy,) = augment_records([record], train, "xyz+normals+ones", [3], epoch=2, step=7)
    assert np.array_equal(record.features, original)  # the data set's record is left alone
    xyz, normals, ones = copy.features[:, :3], copy.features[:, 3:6], copy.features[:, 6]
    # Rotation plus a factor f: Gram matrices of xyz scale by f^2, of normals stay, xyz . n scales by f.
    gram_before = original[:, :3] @ original[:, :3].T
    factor = np.sqrt((xyz @ xyz.T).trace() / gram_before.trace())
    assert 0.8 <= factor <= 1.2 and abs(factor - 1.0) > 1e-4
    assert np.allclose(xyz @ xyz.T, factor**2 * gram_before, atol=1e-4)
    assert np.allclose(normals @ normals.T, original[:, 3:6] @ original[:, 3:6].T, atol=1e-5)
    assert np.allclose((xyz * normals).sum(1), factor * (original[:, :3] * original[:, 3:6]).sum(1), atol=1e-5)
    assert not np.allclose(xyz, factor * original[:, :3], atol=1e-3)  # really rotated
    assert np.array_equal(ones, original[:, 6])
    # The same rotation acts on xyz and normals: solve it from xyz and apply it to the normals.
    rotation, *_ = np.linalg.lstsq(original[:, :3] * factor, xyz, rcond=None)
    assert np.allclose(original[:, 3:6] @ rotation, normals, atol=1e-4)


def test_reproducible_per_step_and_different_across_steps():
    record = _record("xyz")
    train = TrainSection(augment_rotation="vertical", seed=0)
    first = augment_records([record], train, "xyz", [3], epoch=1, step=1)[0].features
    again = augment_records([record], train, "xyz", [3], epoch=1, step=1)[0].features
    other = augment_records([record], train, "xyz", [3], epoch=1, step=2)[0].features
    assert np.array_equal(first, again) and not np.allclose(first, other)
    assert np.allclose(first[:, 1], record.features[:, 1])  # vertical: heights unchanged


def test_no_augmentation_returns_the_records_themselves():
    record = _record("xyz")
    assert not augmenting(TrainSection())
    assert augment_records([record], TrainSection(), "xyz", [3], 1, 1)[0] is record


@pytest.mark.parametrize(
    "kind, train, message",
    [
        ("shape", TrainSection(augment_rotation="any"), "rotation-invariant"),
        ("ones+curvature", TrainSection(augment_rotation="vertical"), "rotation-invariant"),
        ("normals", TrainSection(augment_scale=0.1), "no xyz part"),
        ("normals", TrainSection(augment_anisotropy=0.1), "augment_anisotropy.*no xyz part"),
        ("shape", TrainSection(augment_warp=0.05), "augment_warp.*no xyz part"),
    ],
)
def test_meaningless_augmentation_is_refused(kind, train, message):
    with pytest.raises(ConfigError, match=message):
        check_augmentation(train, kind)


def test_check_accepts_what_changes_something():
    check_augmentation(TrainSection(augment_rotation="any", augment_scale=0.1), "xyz+shape")
    check_augmentation(TrainSection(augment_rotation="any"), "normals")


def test_anisotropy_scales_each_axis_by_its_own_factor_and_leaves_the_rest():
    record = _record()
    train = TrainSection(augment_anisotropy=0.2, seed=1)
    assert augmenting(train)
    (copy,) = augment_records([record], train, "xyz+normals+ones", [3], epoch=1, step=3)
    factors = copy.features[:, :3] / record.features[:, :3]
    assert np.allclose(factors, factors[0], atol=1e-5)  # one factor per axis, for every vertex
    assert np.all((factors[0] >= 0.8) & (factors[0] <= 1.2)) and np.ptp(factors[0]) > 1e-3
    assert np.array_equal(copy.features[:, 3:], record.features[:, 3:])  # normals and ones untouched


def test_warp_is_a_smooth_bounded_displacement():
    rng = np.random.default_rng(4)
    xyz = rng.normal(size=(2000, 3))
    radius = np.sqrt(((xyz - xyz.mean(0)) ** 2).sum(1).mean())
    moved = smooth_warp(xyz, np.random.default_rng(7), 0.05)
    displacement = moved - xyz
    size = np.linalg.norm(displacement, axis=1)
    assert size.max() <= 0.05 * radius + 1e-12 and size.std() > 0  # bounded, and not a translation
    # Smooth: displacements differ by at most (amplitude r / 3) * sum_k 2 pi / lambda_k * distance, with
    # every wavelength >= r, i.e. by at most 2 pi * amplitude times the distance between the points.
    i, j = rng.integers(0, len(xyz), size=(2, 500))
    change = np.linalg.norm(displacement[i] - displacement[j], axis=1)
    distance = np.linalg.norm(xyz[i] - xyz[j], axis=1)
    assert np.all(change <= 2 * np.pi * 0.05 * distance + 1e-12)
    np.testing.assert_array_equal(moved, smooth_warp(xyz, np.random.default_rng(7), 0.05))


def test_training_with_augmentation_is_reproducible_and_differs(tmp_path, cache_dir):
    weights = []
    for name, options in (
        ("a", {"augment_rotation": "any", "augment_scale": 0.1}),
        ("b", {"augment_rotation": "any", "augment_scale": 0.1}),
        ("plain", {}),
    ):
        train(tiny_config(cache_dir, epochs=1, **options), tmp_path / name, progress=False, workers=0)
        weights.append(load_checkpoint(tmp_path / name / "last.pt")["model"])
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])
    assert any(not torch.equal(weights[0][k], weights[2][k]) for k in weights[0])


def test_training_refuses_rotation_of_invariant_features(tmp_path, cache_dir):
    config = tiny_config(cache_dir, epochs=1, augment_rotation="any")
    config["data"]["features"] = "ones"
    with pytest.raises(ConfigError, match="augment_rotation"):
        train(config, tmp_path / "run", progress=False, workers=0)
