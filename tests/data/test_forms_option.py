"""``data.forms``: the training shapes' forms, their carried targets, the splits they join, their cache and the
option's errors (zernet.data.training_forms).

Creatures of 300 vertices at area 100 with the loader tests' small patches: the whole file runs in seconds.
"""

from functools import partial

import numpy as np
import pytest
from scipy.spatial import cKDTree

from zernet.data import DatasetError, LoaderOptions, ShapeSource, build_dataset, training_forms
from zernet.data.bodies.forms import closest_points
from zernet.data.synthetic import load_creature, make_creature, make_synthetic_dataset
from zernet.data.training_forms import form_sources, load_form
from zernet.geometry import Surface
from zernet.operators import PatchConfig
from zernet.training import train
from zernet.training.config import ConfigError, parse_config

AREA = 100.0
CONFIGS = [PatchConfig(r0=1.2, n_samples=1500, patch_size=30, n_max=3)]


def _creature_source(name="creature", seed=3, target="index") -> ShapeSource:
    """A creature whose target is its vertex index (``"index"``: the correspondence class, which names the
    original vertex each form vertex got its target from) or its part labels (``"segmentation"``)."""
    if target == "index":
        load = partial(_indexed_creature, seed)
    else:
        load = partial(load_creature, seed, 300, False, "segmentation")
    return ShapeSource(name, load, key=f"creature|{seed}|{target}")


def _indexed_creature(seed):
    surface, _, _ = make_creature(seed, n_vertices=300, rotate=False)
    return surface, np.arange(surface.n_vertices)


def _original(seed=3):
    surface, labels, _ = make_creature(seed, n_vertices=300, rotate=False)
    return np.asarray(surface.vertices), np.asarray(surface.faces), labels


# ------------------------------------------------------------------------------------------ carried targets
def test_a_cloud_point_takes_the_nearest_corner_of_the_triangle_it_was_drawn_in():
    vertices, faces, _ = _original()
    cloud, carried = load_form(_creature_source(), "cloud", form_seed=5)
    assert cloud.faces is None and len(carried) == len(vertices)
    # Each point lies on the original surface; its triangle and barycentric coordinates, found exactly,
    # name the corner whose target it must carry.
    face_index, barycentric, _, distance = closest_points(vertices, faces, cloud.vertices)
    assert distance.max() < 1e-9
    expected = faces[face_index, np.argmax(barycentric, axis=1)]
    np.testing.assert_array_equal(carried, expected)
    # Points near in space are near in the order (a step's sparse products read memory in sequence):
    # consecutive points are far closer than in a shuffled order.
    step = np.linalg.norm(np.diff(cloud.vertices, axis=0), axis=1)
    shuffled = np.linalg.norm(np.diff(np.random.default_rng(0).permutation(cloud.vertices), axis=0), axis=1)
    assert np.median(step) < np.median(shuffled) / 4


def test_a_one_sided_scan_keeps_each_vertex_with_its_own_target():
    vertices, _, _ = _original()
    scan, carried = load_form(_creature_source(), "partial", form_seed=1)
    assert 0 < scan.n_vertices < len(vertices)
    # The carried index is the original vertex at exactly that position.
    np.testing.assert_array_equal(scan.vertices, vertices[carried])


def test_a_noisy_cloud_carries_the_targets_of_the_surface_points_it_was_drawn_at():
    vertices, _, _ = _original()
    noisy, carried = load_form(_creature_source(), "cloud-noisy", form_seed=2)
    assert noisy.n_vertices == len(vertices) // 2
    # Noise of 0.0015 sqrt(area) per coordinate (2 mm on a 1.8 m² body): each point stays within a few
    # noise widths plus half a triangle of the vertex it was given.
    area = Surface(vertices, _original()[1]).face_areas().sum()
    offset = np.linalg.norm(noisy.vertices - vertices[carried], axis=1)
    edge = np.linalg.norm(vertices[_original()[1][:, 0]] - vertices[_original()[1][:, 1]], axis=1).max()
    assert np.median(offset) < edge
    assert offset.max() < edge + 5 * 0.0015 * np.sqrt(area) * np.sqrt(3)


def test_a_remeshed_form_has_the_nearest_original_label_away_from_part_boundaries():
    pytest.importorskip("pymeshlab")
    vertices, faces, labels = _original()
    remeshed, carried = load_form(_creature_source(target="segmentation"), "remeshed", form_seed=0)
    assert remeshed.faces is not None and carried.dtype.kind == "i"
    _, nearest = cKDTree(vertices).query(remeshed.vertices)
    # A vertex is inside a part when it and every neighbour share its label.
    inside = np.ones(len(vertices), dtype=bool)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        differs = labels[faces[:, a]] != labels[faces[:, b]]
        inside[faces[differs, a]] = inside[faces[differs, b]] = False
    interior = inside[nearest]
    assert interior.sum() >= 40  # enough vertices inside parts to test on
    np.testing.assert_array_equal(carried[interior], labels[nearest[interior]])
    assert len(np.unique(carried)) == len(np.unique(labels))


def test_a_decimated_form_is_repaired_and_its_targets_follow_the_vertices():
    vertices, faces, _ = _original()
    decimated, carried = load_form(_creature_source(), "decimated", form_seed=0)
    assert decimated.n_vertices < len(vertices) and len(carried) == decimated.n_vertices
    # Every carried vertex is a corner of the original triangle closest to the form's vertex.
    face_index, _, _, _ = closest_points(vertices, faces, decimated.vertices)
    assert (faces[face_index] == carried[:, None]).any(axis=1).all()


def test_forms_are_the_same_for_the_same_seed_and_differ_for_another():
    first, _ = load_form(_creature_source(), "cloud", form_seed=7)
    again, _ = load_form(_creature_source(), "cloud", form_seed=7)
    other, _ = load_form(_creature_source(), "cloud", form_seed=8)
    np.testing.assert_array_equal(first.vertices, again.vertices)
    assert not np.allclose(first.vertices, other.vertices)


def test_a_shape_without_a_per_vertex_target_or_without_faces_gets_no_form():
    cloud_source = ShapeSource("points", partial(_as_cloud, 3))
    with pytest.raises(DatasetError, match="point cloud; forms are made from triangle meshes"):
        load_form(cloud_source, "cloud", 0)
    untargeted = ShapeSource("bare", partial(_without_target, 3))
    with pytest.raises(DatasetError, match="has no target"):
        load_form(untargeted, "cloud", 0)


def _as_cloud(seed):
    surface, labels, _ = make_creature(seed, n_vertices=300, rotate=False)
    return Surface(surface.vertices, None), labels


def _without_target(seed):
    surface, _, _ = make_creature(seed, n_vertices=300, rotate=False)
    return surface, None


# ------------------------------------------------------------------------------------------ which shapes
def test_rates_give_whole_copies_and_a_seeded_share():
    training = [_creature_source(f"s{i}", seed=i) for i in range(8)]
    made = form_sources(training, {"cloud": 2, "partial": 0.25}, seed=0)
    names = {form: [source.name for source in sources] for form, sources in made.items()}
    assert names["cloud"] == [f"s{i}#cloud{copy}" for i in range(8) for copy in ("", "2")]
    assert len(names["partial"]) == 2
    # A form's draws do not depend on the other forms asked for; another seed draws other shapes.
    assert [s.name for s in form_sources(training, {"partial": 0.25}, seed=0)["partial"]] == names["partial"]
    other_seeds = [[s.name for s in form_sources(training, {"partial": 0.25}, seed)["partial"]] for seed in (1, 2, 3)]
    assert any(other != names["partial"] for other in other_seeds)


def test_forms_join_the_training_split_only_and_are_cached(tmp_path, monkeypatch):
    options = LoaderOptions(
        patch_configs=CONFIGS, cache_dir=tmp_path, n_val=2, workers=0, progress=False, forms={"cloud": 1}
    )
    dataset = make_synthetic_dataset(n_shapes=6, n_vertices=300, test_fraction=0.2, area=AREA, options=options)
    names = dataset.names
    originals = [names[i] for i in dataset.splits["train"] if "#" not in names[i]]
    made = [names[i] for i in dataset.splits["train"] if "#" in names[i]]
    # Every training shape (not the 2 validation or the test shape) has its cloud, in training only.
    assert sorted(made) == sorted(f"{name}#cloud" for name in originals)
    for split in ("val", "test"):
        assert not any("#" in names[i] for i in dataset.splits[split])
    assert dataset.info["forms"] == {"cloud": len(originals)}
    record = dataset[names.index(made[0])]
    assert record.target.dtype == np.int64 and record.n_vertices == 300
    assert set(np.unique(record.target)) <= set(range(dataset.num_classes))

    # A second build reads every form back from the cache: none is made again.
    def refuse(*arguments):
        raise AssertionError("a cached form was made again")

    monkeypatch.setattr(training_forms, "load_form", refuse)
    again = make_synthetic_dataset(n_shapes=6, n_vertices=300, test_fraction=0.2, area=AREA, options=options)
    assert again.names == names
    np.testing.assert_array_equal(again[made[0]].surface.vertices, record.surface.vertices)


def test_a_regression_target_is_carried_and_area_scaled_like_its_shape(tmp_path):
    sources = [
        ShapeSource(f"s{i}", partial(load_creature, i, 300, False, "regression"), key=f"s{i}", target_exponent=-0.5)
        for i in range(3)
    ]
    dataset = build_dataset(
        sources,
        CONFIGS,
        tmp_path,
        AREA,
        "regression",
        None,
        {"train": ["s0", "s1"], "test": ["s2"]},
        n_val=0,
        workers=0,
        progress=False,
        forms={"partial": 1},
    )
    original, scan = dataset["s0"], dataset["s0#partial"]
    assert scan.target.dtype == np.float32 and len(scan.target) == scan.n_vertices
    ratio = scan.scale / original.scale
    assert ratio > 1.05  # one side of a closed shape is enlarged to the whole area
    # The scan's vertices are original vertices: back in the files' units, at the same place; each carries
    # the original's value, scaled by each shape's own normalisation (curvature: 1 / length).
    _, nearest = cKDTree(_unscaled(original)).query(_unscaled(scan))
    np.testing.assert_allclose(_unscaled(scan), _unscaled(original)[nearest], atol=1e-9)
    np.testing.assert_allclose(scan.target * ratio, original.target[nearest], rtol=1e-5, atol=1e-6)


def _unscaled(record) -> np.ndarray:
    """A record's vertices in its file's units (the area normalisation keeps the area-weighted centroid)."""
    weights = record.surface.vertex_areas()
    centroid = weights @ record.surface.vertices / weights.sum()
    return centroid + (record.surface.vertices - centroid) / record.scale


# ------------------------------------------------------------------------------------------ the option's errors
@pytest.mark.parametrize(
    "forms, message",
    [
        ({"clouds": 1}, "data.forms: unknown form 'clouds'; choose from remeshed, decimated, cloud"),
        ({"cloud": -0.5}, r"data.forms.cloud must be a number >= 0"),
        ({"cloud": "many"}, r"data.forms.cloud must be a number >= 0"),
        ({"original": 1}, "'original' is not a form to add"),
        (["cloud"], "data.forms must map form names to rates"),
    ],
)
def test_the_configuration_refuses_a_bad_forms_option(forms, message):
    with pytest.raises(ConfigError, match=message):
        parse_config({"data": {"kind": "synthetic", "forms": forms}})


def test_a_form_whose_package_is_missing_is_named_with_its_extra(monkeypatch):
    monkeypatch.setattr(training_forms.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(DatasetError, match=r"the 'remeshed' form needs pymeshlab: pip install 'zernet\[bodies\]'"):
        LoaderOptions(forms={"remeshed": 0.5})
    assert LoaderOptions(forms={"remeshed": 0, "cloud": 1}).forms == {"cloud": 1.0}


# ------------------------------------------------------------------------------------------ a run reports them
def test_a_run_says_which_forms_it_trained_on(tmp_path):
    config = {
        "data": {
            "kind": "synthetic",
            "task": "segmentation",
            "n_shapes": 6,
            "n_vertices": 200,
            "test_fraction": 0.34,
            "val_count": 1,
            "seed": 0,
            "workers": 0,
            "forms": {"cloud": 1, "partial": 0.34},
        },
        "patch": {"scales": [{"r0": 5.0, "n_samples": 800, "patch_size": 20, "n_max": 3}]},
        "model": {"name": "zernet", "widths": [8, 8], "angular_resolution": 2},
        "train": {"epochs": 1, "threads": 1},
        "eval": {"renders": 0, "plots": False},
        "cache_dir": str(tmp_path / "cache"),
    }
    metrics = train(config, tmp_path / "run", progress=False, workers=0)
    # 6 creatures: 2 test, 1 validation, 3 training ones, each with its cloud and one of them one-sided.
    assert metrics["forms"] == {"cloud": 3, "partial": 1}
    log = (tmp_path / "run" / "train.log").read_text()
    assert "7 train / 1 val / 2 test shapes" in log
    assert "forms of the training shapes (data.forms), in the train count: 3 cloud, 1 partial" in log
