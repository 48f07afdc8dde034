"""Ground truth between two forms of bodies that share a template, and the target alignment of the matcher
(independent of the target's pose). Procedural meshes stand in for bodies: no anny needed."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from zernet.data.bodies.forms import closest_points
from zernet.geometry import Surface
from zernet.matching.bodies import LocatedForm, ground_truth_map
from zernet.matching.match import candidate_alignments
from zernet.matching.shapes import prepare_shape
from zernet.matching.train import pair_rotations, small_rotation
from zernet.operators import PatchConfig


def _template():
    sphere = trimesh.creation.icosphere(subdivisions=3)
    return np.asarray(sphere.vertices) * [0.3, 0.8, 0.2], np.asarray(sphere.faces, dtype=np.int64)


def _located(body_vertices, faces, points, name):
    face_index, barycentric, on_body, _ = closest_points(body_vertices, faces, points)
    return LocatedForm(name, "cloud", 0, Surface(points, None, name=name), face_index, barycentric, on_body)


def test_ground_truth_map_follows_the_template_between_bodies():
    """Body 2 is body 1 stretched (same template): a source point's true image is its stretched position."""
    vertices, faces = _template()
    stretch = np.array([1.3, 0.9, 1.1])
    rng = np.random.default_rng(0)
    points_1 = _located(vertices, faces, vertices[rng.choice(len(vertices), 300, replace=False)], "a")
    target_points = vertices[rng.choice(len(vertices), 400, replace=False)] * stretch
    target = _located(vertices * stretch, faces, target_points, "b")
    truth = ground_truth_map(points_1, target, vertices * stretch, faces)
    expected = points_1.on_body * stretch
    distances = np.linalg.norm(target.on_body[None] - expected[:, None], axis=2)
    # The nearest target point (by distance: the symmetric ellipsoid has exact ties between mirror points).
    np.testing.assert_allclose(distances[np.arange(300), truth], distances.min(axis=1), atol=1e-12)
    assert ground_truth_map(points_1, points_1, vertices, faces).tolist() == list(range(300))


def test_target_alignment_does_not_depend_on_the_target_pose():
    vertices, faces = _template()
    vertices = vertices * (1 + 0.05 * np.sin(7 * vertices[:, :1]))
    config = [PatchConfig(r0=4.0, n_samples=800)]
    source = prepare_shape(Surface(vertices, faces), config, 1000.0, "xyz", 10)
    rotation = small_rotation(np.random.default_rng(1), 180.0)
    turned = prepare_shape(Surface(vertices @ rotation.T, faces), config, 1000.0, "xyz", 10)
    plain = [turned_xyz for turned_xyz in (source.features @ r.T for r in candidate_alignments(source, source))]
    moved = [turned.features @ r.T for r in candidate_alignments(source, turned)]
    for a, b in zip(plain, moved):
        np.testing.assert_allclose(a, b, atol=1e-3)
    np.testing.assert_allclose(plain[0], source.features, atol=1e-4)  # the identity is a candidate


def test_pair_rotations_turn_both_shapes_nearly_alike():
    rng = np.random.default_rng(2)
    for _ in range(20):
        first, second = pair_rotations(rng, "pair", 20.0)
        relative = first.T @ second
        angle = np.degrees(np.arccos(np.clip((np.trace(relative) - 1) / 2, -1, 1)))
        assert angle <= 40.0 + 1e-6
        np.testing.assert_allclose(first @ first.T, np.eye(3), atol=1e-12)


def test_matching_configs_build_their_model():
    """Every config under configs/matching/ names a spec the descriptor model builds from."""
    from pathlib import Path

    from zernet.matching.model import DescriptorModel
    from zernet.matching.train import make_spec, read_config

    paths = sorted((Path(__file__).resolve().parents[2] / "configs" / "matching").glob("*.yaml"))
    assert paths
    for path in paths:
        config = read_config(path)
        assert {"data", "spec", "train"} <= set(config)
        model = DescriptorModel(make_spec(config))
        assert model.spec.in_channels == 3 + 16 or model.spec.feature_kind != "xyz+hks"


def test_a_partial_scan_is_always_the_source_of_its_training_pair():
    from types import SimpleNamespace

    from zernet.matching.train import oriented_pair

    forms = [SimpleNamespace(form=name) for name in ("remeshed", "partial", "cloud-noisy", "partial")]
    assert oriented_pair(forms, 0, 2) == (0, 2)
    assert oriented_pair(forms, 0, 1) == (1, 0) and oriented_pair(forms, 1, 0) == (1, 0)
    assert oriented_pair(forms, 1, 3) is None


def test_matching_config_overrides_use_the_training_syntax():
    """``python -m zernet.matching.train --set`` reads dotted keys as ``zernet train --set`` does: list
    indices, YAML values (1e-3 a float), and a misspelt section is refused."""
    from pathlib import Path

    from zernet.matching.train import read_config
    from zernet.training import ConfigError

    path = Path(__file__).resolve().parents[2] / "configs" / "matching" / "bodies.yaml"
    config = read_config(path, ["train.steps=7", "spec.patch.0.r0=4.5", "train.lr=1e-3"])
    assert config["train"]["steps"] == 7 and config["train"]["lr"] == 0.001
    assert config["spec"]["patch"][0]["r0"] == 4.5 and config["spec"]["patch"][0]["n_samples"] == 1600
    with pytest.raises(ConfigError, match="trian"):
        read_config(path, ["trian.steps=7"])
    with pytest.raises(ConfigError, match="section.key=value"):
        read_config(path, ["train.steps"])
