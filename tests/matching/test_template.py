"""The template matcher: pose candidates that do not depend on the pose, the rigid fit, the shipped model
on small held-out generated bodies (whole, turned, one-sided), and its file format."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch

from zernet.geometry import Surface
from zernet.matching import match_surfaces
from zernet.matching.match import load_matcher
from zernet.matching.model import DescriptorModel
from zernet.matching.template import (
    PRETRAINED_TEMPLATE_MODEL,
    TEMPLATE_PART_MODEL,
    TemplateModel,
    _fitted_rotation,
    candidate_rotations,
    load_template_model,
    template_shape,
)
from zernet.training.augment import random_rotation

needs_bodies = pytest.mark.skipif(
    importlib.util.find_spec("anny") is None or importlib.util.find_spec("pymeshlab") is None,
    reason="needs the bodies extra (anny, pymeshlab)",
)

#: Bound on the shipped template model's mean Euclidean error (x100 / sqrt(target area)) on the two coarse-615
#: pairs below, whole and with the target turned: measured 0.87 and 0.85 (the same turned).
ERROR_BOUND = 1.5
#: The same for the front half of a body matched into another whole body (same unit): measured 2.45.
ONE_SIDED_ERROR_BOUND = 4.0


def _ellipsoid_points(rng) -> np.ndarray:
    return rng.standard_normal((500, 3)) * [0.2, 0.9, 0.45]


def test_principal_candidates_do_not_depend_on_the_pose():
    rng = np.random.default_rng(0)
    points = _ellipsoid_points(rng)
    turn = random_rotation(rng, "any")
    given = candidate_rotations(points)
    turned = candidate_rotations(points @ turn.T)
    assert len(given) == 8
    # Each candidate of the turned points, applied after the turn, is a candidate of the points themselves.
    for candidate in turned:
        assert min(np.abs(candidate @ turn - other).max() for other in given) < 1e-8
    for candidate in given:
        assert np.allclose(candidate @ candidate.T, np.eye(3)) and np.isclose(np.linalg.det(candidate), 1.0)


def test_the_rigid_fit_recovers_a_rotation_whatever_the_weights():
    rng = np.random.default_rng(1)
    points = _ellipsoid_points(rng)
    turn = random_rotation(rng, "any")
    weights = rng.uniform(0.1, 1.0, len(points))
    fitted = _fitted_rotation(points, points @ turn.T + [0.3, -2.0, 1.0], weights)
    np.testing.assert_allclose(fitted, turn, atol=1e-10)


def test_shipped_template_model_is_in_the_package_with_its_provenance():
    model = load_template_model()
    assert PRETRAINED_TEMPLATE_MODEL.is_file() and PRETRAINED_TEMPLATE_MODEL.stat().st_size < 8 * 2**20
    assert {"command", "commit", "config"} <= set(model.provenance)
    assert model.template_positions.shape == (model.n_classes, 3) and not model.network.training
    # None loads the template model; a descriptor model file loads as one.
    from zernet.matching.model import PRETRAINED_MODEL

    assert isinstance(load_matcher(None), TemplateModel)
    assert isinstance(load_matcher(PRETRAINED_MODEL), DescriptorModel)


def test_a_file_that_is_no_template_model_is_refused(tmp_path):
    path = tmp_path / "other.pt"
    torch.save({"format": "something-else"}, path)
    with pytest.raises(ValueError, match="not a zernet template model"):
        load_template_model(path)
    with pytest.raises(FileNotFoundError):
        load_template_model(tmp_path / "missing.pt")


@pytest.fixture(scope="module")
def held_out_bodies(tmp_path_factory):
    from zernet.matching.bodies import body_forms

    cache = tmp_path_factory.mktemp("cache")
    return body_forms(range(3), "test", {"remeshed": 1.0}, 0, "coarse-615", "varied", 0, cache)


def _error(forms, body_vertices, faces, a, b, result) -> float:
    from zernet.matching.bodies import ground_truth_map

    truth = ground_truth_map(forms[a], forms[b], body_vertices[forms[b].body], faces)
    target = forms[b].surface.vertices
    return (
        100 * np.linalg.norm(target[result.vertex_map] - target[truth], axis=1).mean() / np.sqrt(forms[b].surface.area)
    )


@needs_bodies
def test_shipped_template_model_matches_held_out_bodies_in_any_pose(held_out_bodies, one_torch_thread):
    forms, body_vertices, faces = held_out_bodies
    model = load_template_model()
    turn = random_rotation(np.random.default_rng(2), "any")
    errors, turned_errors = [], []
    for a, b in ((0, 1), (1, 2)):
        result, source, target = match_surfaces(forms[a].surface, forms[b].surface, model)
        assert result.vertex_map.shape == (forms[a].surface.n_vertices,)
        assert result.reverse_map.shape == (forms[b].surface.n_vertices,)
        assert result.fmap.ndim == 2 and 0 <= result.confidence.min() <= result.confidence.max() <= 1
        errors.append(_error(forms, body_vertices, faces, a, b, result))
        turned_target = Surface(forms[b].surface.vertices @ turn.T, forms[b].surface.faces)
        turned, _, _ = match_surfaces(forms[a].surface, turned_target, model)
        turned_errors.append(_error(forms, body_vertices, faces, a, b, turned))
    assert np.mean(errors) < ERROR_BOUND, errors
    assert np.mean(turned_errors) < ERROR_BOUND, turned_errors
    # Every candidate starts from the principal axes: the turn changes nothing but rounding.
    np.testing.assert_allclose(turned_errors, errors, atol=0.05)


@needs_bodies
def test_a_one_sided_scan_is_matched_into_the_whole_body(held_out_bodies, one_torch_thread):
    from zernet.matching.bodies import ground_truth_map

    forms, body_vertices, faces = held_out_bodies
    source = forms[0].surface
    # The half facing +z (the front), as a camera in front of the body would see it.
    kept = np.flatnonzero(source.vertices[:, 2] > np.median(source.vertices[:, 2]))
    inside = np.isin(source.faces, kept).all(axis=1)
    renumber = np.full(source.n_vertices, -1)
    renumber[kept] = np.arange(len(kept))
    front = Surface(source.vertices[kept], renumber[source.faces[inside]], name="front")
    result, _, _ = match_surfaces(front, forms[1].surface, same_scale=True)
    # The front's vertices go where the ground truth sends them (measured 2.45; the whole body's match gives
    # 0.78 on the same vertices; pairs whose limbs go to the wrong limb score 10 to 19, issue 51).
    truth = ground_truth_map(forms[0], forms[1], body_vertices[forms[1].body], faces)[kept]
    target = forms[1].surface.vertices
    error = 100 * np.linalg.norm(target[result.vertex_map] - target[truth], axis=1).mean()
    assert error / np.sqrt(forms[1].surface.area) < ONE_SIDED_ERROR_BOUND


def _tiny_checkpoint(n_classes: int) -> dict:
    from zernet.inference import build_model_from_spec

    spec = {"name": "zernet", "in_channels": 19, "out_channels": n_classes, "options": {"widths": [8, 8], "n_max": 5}}
    patch = {
        "r0": 5.5,
        "n_samples": 500,
        "n_max": 5,
        "inner_radius": 1.375,
        "subtract_center": True,
        "backend": "front",
    }
    return {
        "task": "classification",
        "num_classes": n_classes,
        "model_spec": spec,
        "model": build_model_from_spec(spec).state_dict(),
        "feature_stats": None,
        "preprocess": {"patch_configs": [patch], "area": None, "unit_scale": 90.0, "feature_kind": "xyz+hks"},
    }


def test_a_template_model_file_round_trips(tmp_path):
    from zernet.matching.template import save_template_model

    checkpoint = _tiny_checkpoint(12)
    positions = np.random.default_rng(3).standard_normal((12, 3))
    provenance = {"command": "test", "commit": "abc", "config": {}, "training_area": 15000.0, "coarse_vertices": 300}
    path = save_template_model(checkpoint, positions, tmp_path / "t.pt", provenance)
    model = load_template_model(path)
    assert model.area == 15000.0 and model.coarse_vertices == 300 and model.feature_kind == "xyz+hks"
    np.testing.assert_allclose(model.template_positions, positions, rtol=1e-6, atol=1e-6)
    for key, value in checkpoint["model"].items():  # stored in float16
        torch.testing.assert_close(model.network.state_dict()[key], value.half().float())
    assert isinstance(load_matcher(path), TemplateModel)
    with pytest.raises(ValueError, match="one class per template vertex"):
        save_template_model(_tiny_checkpoint(5), positions, tmp_path / "u.pt", provenance)


def test_a_fine_tune_records_the_file_it_started_from_and_that_file_s_own_history(tmp_path):
    import hashlib

    from zernet.matching.template import save_template_model
    from zernet.matching.train_template import init_provenance

    first = {"command": "first", "commit": "abc", "config": {}, "training_area": 15000.0, "coarse_vertices": 300}
    path = save_template_model(_tiny_checkpoint(12), np.zeros((12, 3)), tmp_path / "first.pt", first)
    recorded = init_provenance(str(path))
    assert recorded["file"] == "first.pt"
    assert recorded["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert recorded["provenance"]["command"] == "first"
    assert init_provenance("pretrained:bodies-xyz-hks") == {"name": "pretrained:bodies-xyz-hks"}
    assert init_provenance(None) is None
    (tmp_path / "other.pt").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="other.pt"):
        init_provenance(str(tmp_path / "other.pt"))


def test_the_training_folder_and_config_of_the_recipe(tmp_path):
    import trimesh

    from zernet.matching.train_template import FORMS, TEST_FORMS, template_config, write_training_folder
    from zernet.training.config import parse_config

    bodies = tmp_path / "bodies"
    sphere = trimesh.creation.icosphere(subdivisions=1)
    for split in ("train", "test"):
        for directory in ["segmentation/meshes"] + [f"forms/{form}/meshes" for form in FORMS]:
            (bodies / directory / split).mkdir(parents=True)
            sphere.export(bodies / directory / split / "body_000.ply")
        for form in FORMS:
            (bodies / "forms" / form / "correspondence" / split).mkdir(parents=True)
            (bodies / "forms" / form / "correspondence" / split / "body_000.txt").write_text(
                "3\n" * len(sphere.vertices)
            )
    folder = write_training_folder(bodies, tmp_path / "folder", len(sphere.vertices))
    assert len(list((folder / "meshes" / "train").iterdir())) == 1 + len(FORMS)
    assert len(list((folder / "labels" / "test").iterdir())) == 1 + len(TEST_FORMS)
    labels = np.loadtxt(folder / "labels" / "train" / "body_000.txt", dtype=int)
    np.testing.assert_array_equal(labels, np.arange(len(sphere.vertices)))  # as generated: vertex i is i
    assert set(np.loadtxt(folder / "labels" / "train" / "body_000_partial.txt", dtype=int)) == {3}
    config = parse_config(template_config(folder, len(sphere.vertices), 90.0, 8, "pretrained:bodies-xyz-hks"))
    assert config.data.options["num_classes"] == len(sphere.vertices) and config.train.epochs == 8


@needs_bodies
def test_the_template_feature_says_where_on_the_body_a_vertex_lies_in_any_pose(tmp_path, one_torch_thread):
    from zernet.data.bodies import BodyGenerator
    from zernet.data.features import compute_features, feature_channels

    # A held-out body in the model's own topology: its vertex i lies at template vertex i.
    body = BodyGenerator("coarse-1229", "varied", seed=0, cache_dir=tmp_path).body(0, "test").surface()
    # The part reads its own model, not the matcher's default: models trained on the part learnt its positions.
    assert TEMPLATE_PART_MODEL != PRETRAINED_TEMPLATE_MODEL
    model = load_template_model(TEMPLATE_PART_MODEL)
    features = compute_features(body, "xyz+template", cache_dir=tmp_path)
    assert features.shape == (body.n_vertices, feature_channels("xyz+template")) == (body.n_vertices, 6)
    positions = features[:, 3:]
    scale = model.provenance["unit_scale"] * np.sqrt(body.area / model.area)
    height = np.ptp(model.template_positions[:, 1])
    errors = np.linalg.norm(positions / scale - model.template_positions, axis=1)
    assert np.median(errors) < 0.02 * height, np.median(errors) / height
    read_by_the_part_model = template_shape(model, body).positions * scale
    np.testing.assert_allclose(positions, read_by_the_part_model, rtol=0, atol=1e-3 * height * scale)
    # Turned and moved, the body reads the same positions (unlike its xyz).
    turn = random_rotation(np.random.default_rng(3), "any")
    moved = Surface(body.vertices @ turn.T + [10.0, -4.0, 2.0], body.faces)
    moved_positions = compute_features(moved, "template")
    assert np.median(np.linalg.norm(moved_positions - positions, axis=1)) < 0.005 * height * scale
    # Read back from the cache: the same values.
    np.testing.assert_array_equal(compute_features(body, "template", cache_dir=tmp_path), positions)
    assert len(list((tmp_path / "template").glob("*.npz"))) == 1


@needs_bodies
def test_registered_scans_are_labelled_by_the_consensus_of_their_template_reads(tmp_path, one_torch_thread):
    from zernet.data.bodies import BodyGenerator
    from zernet.matching.train_template import consensus_labels, write_registration_folder

    # Bodies in the model's own topology share one triangulation, and vertex i lies at template vertex i.
    generator = BodyGenerator("coarse-1229", "varied", seed=0, cache_dir=tmp_path)
    bodies = [generator.body(i, "test").surface() for i in range(3)]
    for i, body in enumerate(bodies):
        body.name = f"body_{i}.ply"
    model = load_template_model()
    consensus = consensus_labels(model, bodies, cache_dir=tmp_path)
    template = model.template_positions
    miss = np.linalg.norm(template[consensus["labels"]] - template, axis=1)
    spacing = np.median(np.linalg.norm(template[1:] - template[:-1], axis=1))
    assert np.median(miss) <= spacing and np.mean(miss < 0.1) > 0.97  # at most a template vertex off; no limb
    assert consensus["rotations"].shape == (3, 3, 3) and consensus["spread"].shape == (3,)

    folder = write_registration_folder(model, bodies, consensus["labels"], consensus["rotations"], tmp_path / "f")
    import trimesh

    for i, body in enumerate(bodies):
        mesh = trimesh.load(folder / "meshes" / "train" / f"body_{i}.ply", process=False)
        labels = np.loadtxt(folder / "labels" / "train" / f"body_{i}.txt", dtype=int)
        assert len(labels) == len(mesh.vertices) and abs(mesh.area - model.area) < 1e-6 * model.area
        # Turned back out of the model's frame and scaled down, each vertex is where its body vertex was.
        back = mesh.vertices @ consensus["rotations"][i] / np.sqrt(model.area / body.area)
        nearest = np.linalg.norm(back[:, None] - body.vertices[None], axis=2).argmin(axis=1)
        np.testing.assert_array_equal(labels, consensus["labels"][nearest])


def test_a_consensus_needs_scans_that_share_one_triangulation():
    import trimesh

    from zernet.matching.train_template import consensus_labels

    mesh = trimesh.creation.icosphere(subdivisions=1)
    sphere = Surface(mesh.vertices, mesh.faces, name="sphere.ply")
    other = Surface(mesh.vertices, mesh.faces[:, ::-1], name="flipped.ply")
    with pytest.raises(ValueError, match="flipped.ply.*share one triangulation"):
        consensus_labels(None, [sphere, sphere, other])
    with pytest.raises(ValueError, match="at least 3"):
        consensus_labels(None, [sphere, sphere])


@needs_bodies
def test_a_fine_tune_on_registered_scans_writes_a_template_model_with_its_provenance(tmp_path, one_torch_thread):
    import json

    import trimesh

    from zernet.data.bodies import BodyGenerator
    from zernet.matching.train_template import main

    scans = tmp_path / "scans"
    scans.mkdir()
    generator = BodyGenerator("coarse-1229", "varied", seed=1, cache_dir=tmp_path)
    for i in range(3):
        body = generator.body(i, "test").surface()
        trimesh.Trimesh(body.vertices, body.faces, process=False).export(scans / f"scan_{i}.ply")
    out = tmp_path / "fine_tuned.pt"
    argv = [str(scans), str(tmp_path / "run"), "--registrations", "--out", str(out), "--epochs", "1", "--threads", "1"]
    assert main(argv) == 0
    model = load_template_model(out)
    shipped = load_template_model()
    np.testing.assert_array_equal(model.template_positions, shipped.template_positions)
    assert model.area == shipped.area and model.coarse_vertices == shipped.coarse_vertices
    provenance = model.provenance
    assert provenance["registrations"]["scans"] == 3 and provenance["init_from"]["file"] == "bodies-match-template.pt"
    assert provenance["config"]["data"]["forms"] and provenance["config"]["train"]["init_from"].endswith(".pt")
    spread = json.loads((tmp_path / "run" / "consensus.json").read_text())["spread_p95"]
    assert sorted(spread) == ["scan_0.ply", "scan_1.ply", "scan_2.ply"]


def test_registrations_that_do_not_share_a_triangulation_are_refused_by_name(tmp_path):
    import trimesh

    from zernet.matching.train_template import main

    scans = tmp_path / "scans"
    scans.mkdir()
    mesh = trimesh.creation.icosphere(subdivisions=2)
    for i in range(2):
        mesh.export(scans / f"scan_{i}.ply")
    trimesh.Trimesh(mesh.vertices, np.roll(mesh.faces, 1, axis=0), process=False).export(scans / "scan_2.ply")
    argv = [str(scans), str(tmp_path / "run"), "--registrations", "--out", str(tmp_path / "m.pt")]
    with pytest.raises(SystemExit, match="scan_2.ply.*share one triangulation"):
        main(argv)
    (scans / "scan_2.ply").write_text("not a mesh")
    with pytest.raises(SystemExit, match="scan_2.ply"):
        main(argv)
    with pytest.raises(SystemExit, match="no such folder"):
        main([str(tmp_path / "none"), str(tmp_path / "run2"), "--registrations", "--out", str(tmp_path / "m.pt")])
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit, match="no registered scans"):
        main([str(tmp_path / "empty"), str(tmp_path / "run2"), "--registrations", "--out", str(tmp_path / "m.pt")])
