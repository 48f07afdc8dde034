"""Data sets: containers, splits, loader options, preprocessing and its cache, the four loaders and their errors.

Meshes here are tiny (icospheres of 162 vertices, creatures of 300) so the whole file runs in seconds.
"""

import json
import os
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import trimesh

from zernet.data import (
    DatasetError,
    LoaderOptions,
    PreprocessError,
    ShapeSource,
    SkippedShapesWarning,
    build_dataset,
    load_dataset,
    synthetic,
)
from zernet.data.cache import shape_cache_path
from zernet.data.dataset import carve_validation
from zernet.data.faust import load_faust, registration_numbers
from zernet.data.features import MEMBRANE_PRESTRESSES, default_features, feature_channels
from zernet.data.regression import leave_one_out_splits, load_aneurysm, load_regression
from zernet.data.segmentation import face_to_vertex_labels, load_segmentation
from zernet.data.synthetic import PART_NAMES, load_creature, make_creature, make_synthetic_dataset
from zernet.geometry import Surface
from zernet.operators import PatchConfig

# Tiny surfaces are normalised to area 100 (an icosphere of radius ~2.8); r0 = 1.2 keeps ~10 vertices and,
# with 1500 samples, ~70 samples per patch disk.
AREA = 100.0
CONFIGS = [PatchConfig(r0=1.2, n_samples=1500, patch_size=30, n_max=3)]


def _sphere(seed: int = 0, subdivisions: int = 2, noise: float = 0.03):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    rng = np.random.default_rng(seed)
    vertices = np.asarray(mesh.vertices) * (1 + noise * rng.standard_normal((len(mesh.vertices), 1)))
    return vertices, np.asarray(mesh.faces)


def _write_ply(path, vertices, faces):
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.Trimesh(vertices, faces, process=False).export(path)


# ------------------------------------------------------------------------------------------ containers
def test_default_features_are_centred_at_the_area_weighted_centroid():
    vertices, faces = _sphere()
    surface = Surface(vertices + np.array([5.0, -2.0, 1.0]), faces)
    features = default_features(surface)
    assert features.dtype == np.float32 and features.shape == (len(vertices), 3)
    np.testing.assert_allclose(surface.vertex_areas() @ features, 0.0, atol=1e-4)


def test_validation_is_carved_from_train_seeded_and_disjoint():
    train, val = carve_validation(range(10), 3, seed=1)
    assert len(val) == 3 and not set(train) & set(val) and sorted(train + val) == list(range(10))
    assert carve_validation(range(10), 3, seed=1) == (train, val)
    assert carve_validation(range(10), 0.25, seed=1)[1].__len__() == 2
    assert carve_validation([4], 3, seed=0) == ([4], [])  # one training shape always stays


# ------------------------------------------------------------------------------------ synthetic + cache
def test_creature_labels_and_curvature():
    surface, labels, curvature = make_creature(3, n_vertices=600)
    assert surface.n_vertices == 600 and surface.area == pytest.approx(1000.0)
    assert set(np.unique(labels)) <= set(range(len(PART_NAMES))) and (labels == 0).any() and (labels > 0).any()
    # Bumps bend more than the body on average; dents bend the other way.
    assert curvature[labels == 1].mean() > curvature[labels == 0].mean() > curvature[labels == 3].mean()


SYNTHETIC_CONFIGS = (PatchConfig(r0=4.0, n_samples=1000, patch_size=30, n_max=3),)


def _no_creature(*args):
    raise AssertionError("a cached creature was generated again")


def test_synthetic_dataset_records_splits_subset_and_cache(tmp_path, monkeypatch):
    options = LoaderOptions(patch_configs=SYNTHETIC_CONFIGS, cache_dir=tmp_path, workers=0, progress=False, n_val=1)
    dataset = make_synthetic_dataset("segmentation", n_shapes=5, n_vertices=300, options=options)
    assert dataset.task == "classification" and dataset.num_classes == 4 and len(dataset) == 5
    assert dataset.splits["test"] == [4] and len(dataset.splits["val"]) == 1
    assert sorted(dataset.splits["train"] + dataset.splits["val"]) == [0, 1, 2, 3]
    record = dataset[0]
    assert record.features.shape == (300, 3) and record.target.dtype == np.int64
    assert len(record.geometry.operators) == 1 and record.geometry.operators[0].n_vertices == 300
    edges = record.geometry.edge_index.numpy()
    assert edges.shape[0] == 2 and set(map(tuple, edges.T)) == set(map(tuple, edges[::-1].T))
    sub = dataset.subset([4, 0])
    assert sub.names == ["creature_004", "creature_000"] and sub.splits["test"] == [0]
    assert dataset.split("test").names == ["creature_004"]

    # Every shape now comes from the cache: the generator is not called again (workers=0: in this process).
    monkeypatch.setattr(synthetic, "make_creature", _no_creature)
    again = make_synthetic_dataset("segmentation", n_shapes=5, n_vertices=300, options=options)
    np.testing.assert_array_equal(again[2].target, dataset[2].target)
    monkeypatch.undo()

    regression = load_dataset(
        "synthetic-curvature",
        patch_configs=SYNTHETIC_CONFIGS,
        cache_dir=tmp_path,
        workers=0,
        progress=False,
        n_shapes=3,
        n_vertices=300,
        val_count=1,
    )
    assert regression.task == "regression" and regression[0].target.dtype == np.float32
    with pytest.raises(TypeError, match="unknown option"):
        load_dataset("synthetic", cache_dir=tmp_path, n_shape=3)


def test_load_dataset_with_options_matches_the_keyword_interface(tmp_path):
    keywords = dict(
        patch_configs=list(SYNTHETIC_CONFIGS),
        cache_dir=tmp_path,
        workers=0,
        progress=False,
        seed=2,
        val_count=1,
        feature_kind="xyz+normals",
    )
    by_keywords = load_dataset("synthetic-parts", n_shapes=4, n_vertices=300, **keywords)
    options = LoaderOptions(
        patch_configs=SYNTHETIC_CONFIGS,
        cache_dir=tmp_path,
        workers=0,
        progress=False,
        seed=2,
        n_val=1,
        feature_kind="xyz+normals",
    )
    by_options = load_dataset("synthetic-parts", options=options, n_shapes=4, n_vertices=300)
    assert by_options.splits == by_keywords.splits and by_options.in_channels == 6
    np.testing.assert_array_equal(by_options[1].features, by_keywords[1].features)
    # Shared options go inside options when it is given; unknown arguments are named with what the kind takes.
    with pytest.raises(TypeError, match="workers: give shared options inside options"):
        load_dataset("synthetic", options=options, workers=2)
    with pytest.raises(
        TypeError,
        match=r"unknown option\(s\) bogus for data kind 'faust' \(it takes: area, "
        r"n_vertices, root, test_indices, train_indices, val_indices; and the shared options",
    ):
        load_dataset("faust", options=options, root=tmp_path, bogus=1)
    with pytest.raises(TypeError, match="fixes the task"):
        load_dataset("synthetic-curvature", options=options, task="segmentation")
    with pytest.raises(DatasetError, match="unknown data set kind 'fuast'"):
        load_dataset("fuast", options=options)


def test_loader_options_defaults_and_checks():
    options = LoaderOptions(patch_configs={"r0": 2.0})
    assert options.patch_configs == (PatchConfig(r0=2.0),) and LoaderOptions(patch_configs=[]).patch_configs is None
    filled = LoaderOptions(n_val=3).with_defaults(n_val=8, patch_configs=SYNTHETIC_CONFIGS)
    assert (filled.n_val, filled.on_error, filled.patch_configs) == (3, "raise", SYNTHETIC_CONFIGS)
    assert LoaderOptions(on_error="skip").with_defaults(n_val=0.1).build_arguments()["on_error"] == "skip"
    with pytest.raises(DatasetError, match="on_error must be one of raise, skip, got 'ignore'"):
        LoaderOptions(on_error="ignore")
    with pytest.raises(ValueError, match="with_defaults first"):
        LoaderOptions().build_arguments()
    with pytest.raises(DatasetError, match=r"unknown feature kind 'xyz\+colour'"):
        LoaderOptions(feature_kind="xyz+colour")


def test_shape_cache_paths_are_unchanged():
    """Cache file names computed before the data package was restructured: existing caches stay valid.
    (Recomputed once when the patch config gained ``precision``, issue 50: features read from the patch
    operator, such as the shape descriptors, depend on the precision its cache stores.)"""
    config = [PatchConfig(r0=4.0, n_samples=1000, patch_size=30, n_max=3, backend="fast")]

    def source(seed, task, exponent):
        key = json.dumps({"generator": 1, "seed": seed, "n": 300, "rotate": True, "task": task})
        return ShapeSource(f"creature_{seed:03d}", partial(load_creature, seed, 300, True, task), key, exponent)

    assert shape_cache_path(Path("c"), source(0, "segmentation", 0.0), 1000.0, config, False) == Path(
        "c/shapes/creature_000-0ab9e487ba786f8778d6.npz"
    )
    assert shape_cache_path(Path("c"), source(1, "regression", -0.5), 1000.0, config, False) == Path(
        "c/shapes/creature_001-3b0c434f7663a50813dd.npz"
    )
    assert shape_cache_path(Path("c"), ShapeSource("x", load_creature), 1000.0, config, False) is None


def _sphere_source(seed):
    vertices, faces = _sphere(seed)
    return Surface(vertices, faces, name=f"sphere{seed}"), np.arange(len(vertices)) % 2


def _broken_source():
    raise DatasetError("broken.ply: vertex 3 is NaN")


def test_failures_are_reported_by_name_and_others_go_on(tmp_path):
    sources = [
        ShapeSource("a", partial(_sphere_source, 0)),
        ShapeSource("bad", _broken_source),
        ShapeSource("b", partial(_sphere_source, 1)),
    ]
    common = dict(
        patch_configs=CONFIGS,
        cache_dir=tmp_path,
        target_area=AREA,
        task="classification",
        num_classes=2,
        split_names={"train": ["a", "bad"], "test": ["b"]},
        workers=0,
        progress=False,
    )
    # By default a failing shape stops the build, after every shape was tried, naming it and its reason.
    with pytest.raises(
        PreprocessError, match="1 of 3 shapes failed to load or preprocess:\n  bad: broken.ply: vertex 3 is NaN"
    ) as caught:
        build_dataset(sources, **common)
    assert caught.value.failures == {"bad": "broken.ply: vertex 3 is NaN"} and caught.value.total == 3
    with pytest.warns(SkippedShapesWarning, match="bad: broken.ply: vertex 3 is NaN"):
        dataset = build_dataset(sources, on_error="skip", **common)
    assert dataset.names == ["a", "b"] and dataset.splits["train"] == [0] and "bad" in dataset.failures
    with pytest.raises(PreprocessError, match="1 of 1"):
        build_dataset([sources[1]], on_error="skip", **{**common, "split_names": {"train": ["bad"]}})


def test_parallel_workers_match_in_process(tmp_path):
    sources = [ShapeSource(f"s{i}", partial(_sphere_source, i), key=f"sphere-{i}") for i in range(3)]
    common = dict(
        patch_configs=CONFIGS,
        target_area=AREA,
        task="classification",
        num_classes=2,
        split_names={"train": ["s0", "s1"], "test": ["s2"]},
        progress=False,
    )
    parallel = build_dataset(sources, cache_dir=tmp_path / "p", workers=2, **common)
    serial = build_dataset(sources, cache_dir=tmp_path / "s", workers=0, **common)
    for a, b in zip(parallel, serial):
        np.testing.assert_allclose(a.features, b.features)
        assert (a.geometry.operators[0].matrix != b.geometry.operators[0].matrix).nnz == 0
    lazy = build_dataset(sources, cache_dir=tmp_path / "s", workers=0, in_memory=False, **common)
    assert not lazy.in_memory and serial.in_memory
    np.testing.assert_array_equal(lazy.target(1), serial[1].target)
    np.testing.assert_allclose(lazy[1].features, serial[1].features)


# ------------------------------------------------------------------------------------------------- FAUST
@pytest.fixture
def fake_faust(tmp_path):
    """tmp/MPI-FAUST/training/registrations/tr_reg_000..005.ply with one shared connectivity."""
    folder = tmp_path / "MPI-FAUST" / "training" / "registrations"
    for i in range(6):
        vertices, faces = _sphere(i)
        _write_ply(folder / f"tr_reg_{i:03d}.ply", vertices, faces)
    return tmp_path, folder


def test_faust_layout_splits_and_targets(fake_faust):
    root, folder = fake_faust
    kwargs = dict(
        area=AREA,
        train_indices=range(4),
        test_indices=[4, 5],
        n_vertices=None,
        options=LoaderOptions(patch_configs=CONFIGS, cache_dir=root / "cache", n_val=1, workers=0, progress=False),
    )
    dataset = load_faust(root, **kwargs)
    assert dataset.correspondence and dataset.num_classes == 162 and len(dataset) == 6
    assert [dataset.names[i] for i in dataset.splits["test"]] == ["tr_reg_004", "tr_reg_005"]
    assert len(dataset.splits["val"]) == 1 and not set(dataset.splits["val"]) & set(dataset.splits["test"])
    np.testing.assert_array_equal(dataset[3].target, np.arange(162))
    assert dataset[0].surface.area == pytest.approx(AREA)
    for other_root in (root / "MPI-FAUST", folder):  # also accepted as root
        assert load_faust(other_root, **kwargs).names == dataset.names
    ranged = load_faust(root, **{**kwargs, "train_indices": "0:4", "test_indices": "4:6"})
    assert ranged.names == dataset.names and ranged.splits == dataset.splits


def test_faust_validation_by_person_is_the_given_registrations(fake_faust):
    root, _ = fake_faust
    options = LoaderOptions(patch_configs=CONFIGS, cache_dir=root / "cache", n_val=1, workers=0, progress=False)
    kwargs = dict(area=AREA, train_indices="0:4", test_indices=[5], n_vertices=None, options=options)
    dataset = load_faust(root, **kwargs, val_indices=[4])
    # n_val is ignored: the validation split is exactly the named scan, training keeps all four.
    assert [dataset.names[i] for i in dataset.splits["val"]] == ["tr_reg_004"]
    assert [dataset.names[i] for i in dataset.splits["train"]] == [f"tr_reg_{i:03d}" for i in range(4)]
    with pytest.raises(DatasetError, match=r"\[3\] are in both the train and the validation split"):
        load_faust(root, **kwargs, val_indices=[3])
    with pytest.raises(DatasetError, match=r"\[5\] are in both the validation and the test split"):
        load_faust(root, **kwargs, val_indices=[4, 5])


def test_registration_ranges_follow_the_slice_convention_and_bad_ones_are_named():
    assert registration_numbers("0:180", "train_indices") == list(range(180))
    assert registration_numbers(" 180:200", "test_indices") == list(range(180, 200))
    assert registration_numbers(range(3), "train_indices") == [0, 1, 2]
    for bad in ("5:5", "0-180", "a:3", "3:"):
        with pytest.raises(DatasetError, match=f"train_indices {bad!r}"):
            registration_numbers(bad, "train_indices")
    with pytest.raises(DatasetError, match="quoted range"):
        registration_numbers(620, "test_indices")  # YAML 1.1 reads an unquoted 10:20 as 620
    with pytest.raises(DatasetError, match="negative"):
        registration_numbers([3, -1], "test_indices")


def test_faust_errors_name_the_problem(fake_faust, tmp_path):
    root, folder = fake_faust
    kwargs = dict(
        area=AREA,
        train_indices=range(4),
        test_indices=[4, 5],
        options=LoaderOptions(patch_configs=CONFIGS, cache_dir=root / "cache", workers=0, progress=False),
    )
    with pytest.raises(DatasetError, match="does not exist"):
        load_faust(tmp_path / "nowhere", **kwargs)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="MPI-FAUST/training/registrations/tr_reg_000.ply"):
        load_faust(tmp_path / "empty", **kwargs)
    with pytest.raises(DatasetError, match="6890"):
        load_faust(root, **kwargs)  # the fake meshes have 162 vertices, FAUST 6890
    kwargs["n_vertices"] = None
    os.remove(folder / "tr_reg_002.ply")
    with pytest.raises(DatasetError, match="missing: tr_reg_002.ply"):
        load_faust(root, **kwargs)
    vertices, faces = _sphere(2)
    _write_ply(folder / "tr_reg_002.ply", vertices, faces[:, [1, 0, 2]][::-1])
    with pytest.raises(PreprocessError, match="tr_reg_002.ply: its connectivity"):
        load_faust(root, **kwargs)


# ------------------------------------------------------------------------------------------ segmentation
def test_face_to_vertex_rule_area_weighted_majority_and_ties():
    # Square split in two triangles of equal area with labels 3 and 1: the shared vertices tie -> 1.
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    labels = face_to_vertex_labels(faces, np.array([3, 1]), np.array([1.0, 1.0]), 4)
    np.testing.assert_array_equal(labels, [1, 3, 1, 1])
    # A larger face wins over a smaller one.
    labels = face_to_vertex_labels(faces, np.array([3, 1]), np.array([2.0, 1.0]), 4)
    np.testing.assert_array_equal(labels, [3, 3, 3, 1])


def test_segmentation_shared_one_based_face_labels(tmp_path):
    vertices, faces = _sphere(0)
    for i in range(4):
        _write_ply(tmp_path / "meshes" / f"body{i}.ply", _sphere(i)[0], faces)
    face_labels = np.where(vertices[faces].mean(axis=1)[:, 2] > 0, 2, 1)  # 1-based: upper half part 2
    np.savetxt(tmp_path / "faust_seg.txt", face_labels, fmt="%d")
    options = LoaderOptions(patch_configs=CONFIGS, cache_dir=tmp_path / "cache", n_val=1, workers=0, progress=False)
    dataset = load_segmentation(
        tmp_path / "meshes", tmp_path / "faust_seg.txt", area=AREA, num_classes=2, test=["body3"], options=options
    )
    assert dataset.info["label_base"] == 1 and dataset.num_classes == 2
    target = dataset[dataset.index("body0")].target
    upper = vertices[:, 2] > 0.3
    assert np.all(target[upper] == 1) and np.all(target[vertices[:, 2] < -0.3] == 0)


def test_class_names_come_from_the_data_never_from_the_class_count(tmp_path):
    """8 classes are not the human benchmark's parts unless the data says so: the names come from
    class_names, else a class_names.txt beside the labels, else "part 1" .. "part N"."""
    vertices, faces = _sphere(0)
    for i in range(3):
        _write_ply(tmp_path / "m" / f"s{i}.ply", _sphere(i)[0], faces)
        np.savetxt(tmp_path / "m" / f"s{i}.txt", np.arange(len(vertices)) % 8, fmt="%d")
    options = LoaderOptions(patch_configs=CONFIGS, cache_dir=tmp_path / "c", n_val=1, workers=0, progress=False)

    def names(**arguments):
        return load_segmentation(
            tmp_path / "m", area=AREA, num_classes=8, test=["s2"], options=options, **arguments
        ).info["class_names"]

    assert names() == [f"part {i}" for i in range(1, 9)]
    scan_order = ["head", "hand", "forearm", "upper arm", "torso", "thigh", "shin", "foot"]
    (tmp_path / "m" / "class_names.txt").write_text("\n".join(scan_order) + "\n")
    assert names() == scan_order
    assert names(class_names=list("abcdefgh")) == list("abcdefgh")  # given names win over the file
    with pytest.raises(DatasetError, match=r"data.class_names: 2 class names for 8 classes"):
        names(class_names=["a", "b"])
    (tmp_path / "m" / "class_names.txt").write_text("head\ntorso\n")
    with pytest.raises(DatasetError, match=r"class_names.txt: 2 class names for 8 classes"):
        names()


def test_an_unreadable_label_file_fails_its_own_shape_like_any_bad_shape(tmp_path):
    vertices, faces = _sphere(0)
    for i in range(3):
        _write_ply(tmp_path / "m" / f"s{i}.ply", _sphere(i)[0], faces)
        np.savetxt(tmp_path / "m" / f"s{i}.txt", (vertices[:, 2] > 0).astype(int), fmt="%d")
    lines = (tmp_path / "m" / "s1.txt").read_text().splitlines()
    lines[20] = "torso"
    (tmp_path / "m" / "s1.txt").write_text("\n".join(lines) + "\n")
    options = LoaderOptions(patch_configs=CONFIGS, cache_dir=tmp_path / "c", n_val=0, workers=0, progress=False)
    with pytest.raises(PreprocessError, match=r"1 of 3 shapes.*\n  s1: .*s1.txt: line 21: 'torso' is not a number"):
        load_segmentation(tmp_path / "m", area=AREA, num_classes=2, test=["s2"], options=options)
    with pytest.warns(SkippedShapesWarning, match="s1.txt: line 21"):
        dataset = load_segmentation(
            tmp_path / "m", area=AREA, num_classes=2, test=["s2"], options=replace(options, on_error="skip")
        )
    assert dataset.names == ["s0", "s2"] and list(dataset.failures) == ["s1"]


def test_segmentation_label_count_mismatch_names_both_files(tmp_path):
    vertices, faces = _sphere(0)
    _write_ply(tmp_path / "m" / "a.ply", vertices, faces)
    np.savetxt(tmp_path / "m" / "a.txt", np.zeros(100), fmt="%d")
    with pytest.raises(PreprocessError, match=r"a\.txt: has 100 labels but .*a\.ply has 162 vertices and 320"):
        load_segmentation(
            tmp_path / "m",
            area=AREA,
            num_classes=2,
            test=["a"],
            options=LoaderOptions(patch_configs=CONFIGS, cache_dir=tmp_path / "c", workers=0, progress=False),
        )


# -------------------------------------------------------------------------------------------- regression
def test_aneurysm_mat_layout_area_exponent_and_leave_one_out(tmp_path):
    names = []
    for i in range(3):
        vertices, faces = _sphere(i)
        scaled = Surface(vertices, faces)
        vertices = vertices * np.sqrt(100.0 / scaled.area)  # the files are at area 100
        stress = 0.1 + 0.01 * vertices[:, 2:3]
        scipy.io.savemat(
            tmp_path / f"TP_Ia{i}I.mat", {"X": vertices, "F": (faces + 1).astype(np.uint16), "J2m": stress}
        )
        names.append(f"TP_Ia{i}I")
    common = dict(options=LoaderOptions(patch_configs=CONFIGS, cache_dir=tmp_path / "c", workers=0, progress=False))
    dataset = load_aneurysm(tmp_path, **common)
    assert dataset.task == "regression" and sorted(dataset.names) == names
    record = dataset[0]
    stress = scipy.io.loadmat(tmp_path / f"{record.name}.mat")["J2m"][:, 0]
    np.testing.assert_allclose(record.target, stress, rtol=1e-5)  # area 100: unchanged
    big = load_aneurysm(tmp_path, area=400.0, **common)
    np.testing.assert_allclose(big[0].target, 2 * stress, rtol=1e-5)  # sqrt(400 / 100)

    fold = leave_one_out_splits(dataset.names, "TP_Ia1I", n_val=1, seed=0)
    assert [dataset.names[i] for i in fold["test"]] == ["TP_Ia1I"] and len(fold["val"]) == 1
    assert sorted(fold["train"] + fold["val"] + fold["test"]) == [0, 1, 2]
    assert dataset.with_splits(fold).split("test").names == ["TP_Ia1I"]


def test_aneurysm_recipe_features_through_the_pipeline(tmp_path):
    """The aneurysm recipe's input: shape + curvature + membrane, built from the files and cached."""
    for i in range(2):
        vertices, faces = _sphere(i, noise=0.0)
        vertices = vertices * np.sqrt(100.0 / Surface(vertices, faces).area)
        scipy.io.savemat(
            tmp_path / f"TP_Ia{i}I.mat",
            {"X": vertices, "F": (faces + 1).astype(np.uint16), "J2m": np.full((len(vertices), 1), 0.1)},
        )
    options = LoaderOptions(
        patch_configs=CONFIGS,
        cache_dir=tmp_path / "c",
        workers=0,
        progress=False,
        feature_kind="shape+curvature+membrane",
        n_val=0,
    )
    dataset = load_aneurysm(tmp_path, test=["TP_Ia1I"], options=options)
    record = dataset[0]
    assert record.features.shape == (record.n_vertices, dataset.in_channels)
    assert dataset.in_channels == feature_channels("shape+curvature+membrane", [c.n_max for c in CONFIGS])
    # Closed spheres of area 100: membrane stress R/2/(1 + τ/(1 + ν)) with R = sqrt(100 / 4π).
    radius = np.sqrt(100.0 / (4 * np.pi))
    expected = np.log(radius / 2 / (1 + np.array(MEMBRANE_PRESTRESSES) / 1.45))
    np.testing.assert_allclose(np.median(record.features[:, -3:], axis=0), expected, atol=0.02)
    dataset[1]
    # Both files hold the same sphere: the cache is keyed by geometry, one entry per prestress.
    assert len(list((tmp_path / "c" / "membrane").glob("*.npy"))) == len(MEMBRANE_PRESTRESSES)


def test_generic_regression_and_value_count_mismatch(tmp_path):
    vertices, faces = _sphere(0)
    _write_ply(tmp_path / "a.ply", vertices, faces)
    np.save(tmp_path / "a.npy", vertices[:, 0])
    _write_ply(tmp_path / "b.ply", vertices, faces)
    np.savetxt(tmp_path / "b.txt", vertices[:, 1])
    common = dict(
        area=AREA, options=LoaderOptions(patch_configs=CONFIGS, cache_dir=tmp_path / "c", workers=0, progress=False)
    )
    dataset = load_regression(tmp_path, test=["b"], **common)
    assert dataset.names == ["a", "b"] and dataset.splits["test"] == [1]
    np.savetxt(tmp_path / "b.txt", vertices[:10, 1])
    with pytest.raises(PreprocessError, match=r"b\.txt: has 10 values but .*b\.ply has 162 vertices"):
        load_regression(tmp_path, **common)
    common["options"] = replace(common["options"], on_error="skip")
    with pytest.warns(SkippedShapesWarning, match=r"b\.txt: has 10 values but .*b\.ply has 162 vertices"):
        assert load_regression(tmp_path, **common).names == ["a"]
