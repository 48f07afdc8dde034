"""What a run reports about itself, from the user's side (issue 18): each numbered problem of the issue.

1. bad shapes: stop before training listing every failure (exit 2), or --skip-bad with the skipped shapes
   in train.log, metrics.json and the banner; the same policy in preprocess and evaluate;
2. scores, banner and pictures labelled with the split they were computed on;
5. errors that advise only what the command can do (--skip-bad), config errors before
   any data, label files by file and line;
6. class names from the data, never guessed;
7. strict JSON, one warning for classes no shape has, one-line warnings, resume rules, file modes.

The meshes are 42-vertex spheres, so a whole run takes a few seconds.
"""

from __future__ import annotations

import json
import os
import stat
import warnings

import numpy as np
import pytest
import torch
import trimesh
import yaml
from meshes import icosphere, majority_fraction, write_labelled_sphere, write_labelled_spheres
from tiny_configs import sphere_config

from zernet.cli import main
from zernet.geometry import Surface
from zernet.inference.predict import predict

N_GOOD = 6


def _nan_vertex(text: str) -> str:
    lines = text.splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("v "))
    lines[first + 5] = "v nan 0.0 0.0"
    return "\n".join(lines) + "\n"


def _face_out_of_range(text: str) -> str:
    lines = text.splitlines()
    face = [i for i, line in enumerate(lines) if line.startswith("f ")][3]
    lines[face] = "f 1 2 653"
    return "\n".join(lines) + "\n"


def make_data(root, bad: dict[str, str] | None = None, test: tuple[str, ...] = ("shape5",)):
    """meshes/train/shape0..5 (those named in ``test`` under meshes/test/) plus ``bad``: {name: problem}."""
    write_labelled_spheres(root, N_GOOD, test)
    for name, problem in (bad or {}).items():
        folder = root / ("test" if name in test else "train")
        text, values = write_labelled_sphere(folder, name, seed=50)
        if problem == "nan":
            (folder / f"{name}.obj").write_text(_nan_vertex(text))
        elif problem == "face":
            (folder / f"{name}.obj").write_text(_face_out_of_range(text))
        elif problem == "text label":
            lines = values.splitlines()
            lines[20] = "abc"
            (folder / f"{name}.txt").write_text("\n".join(lines) + "\n")
    return root


def config_file(tmp_path, meshes, cache, **data) -> str:
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(sphere_config(meshes, cache, **data)))
    return str(path)


def strict_json(path):
    def refuse(constant):
        raise ValueError(f"{path} holds {constant}, which is not JSON")

    return json.loads(path.read_text(), parse_constant=refuse)


@pytest.fixture(scope="module")
def skipped_run(tmp_path_factory):
    """A run trained with --skip-bad on six good meshes and one with a NaN vertex."""
    tmp = tmp_path_factory.mktemp("skipped")
    meshes = make_data(tmp / "meshes", {"badnan": "nan"})
    path = config_file(tmp, meshes, tmp / "cache")
    run_dir = tmp / "run"
    code = main(["train", path, "--run-dir", str(run_dir), "--no-progress", "--workers", "0", "--skip-bad"])
    return {"code": code, "run": run_dir, "config": path, "meshes": meshes, "tmp": tmp}


# ------------------------------------------------------------------------------------------ 1. bad shapes
def test_a_bad_shape_stops_training_before_it_starts_listing_every_failure(tmp_path, capsys):
    meshes = make_data(tmp_path / "meshes", {"badnan": "nan", "badface": "face"})
    run_dir = tmp_path / "run"
    code = main(
        [
            "train",
            config_file(tmp_path, meshes, tmp_path / "cache"),
            "--run-dir",
            str(run_dir),
            "--no-progress",
            "--workers",
            "0",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert "2 of 8 shapes failed to load or preprocess" in err
    assert "train/badnan: " in err and "badnan.obj: vertex 5 has a non-finite coordinate" in err
    assert "train/badface: " in err and "badface.obj: face 3 (line" in err and "refers to vertex 653" in err
    assert "rerun with --skip-bad" in err and "on_error='skip'" not in err
    assert not (run_dir / "last.pt").exists()
    log = (run_dir / "train.log").read_text()
    assert "stopped before training" in log and "train/badnan" in log and "train/badface" in log


def test_skip_bad_trains_without_them_and_says_so_everywhere(skipped_run, capsys):
    assert skipped_run["code"] == 0
    run_dir = skipped_run["run"]
    log = (run_dir / "train.log").read_text()
    assert "skipped shape train/badnan (data.on_error: skip): " in log and "non-finite coordinate" in log
    metrics = strict_json(run_dir / "metrics.json")
    assert [item["name"] for item in metrics["skipped"]] == ["train/badnan"]
    assert "badnan.obj: vertex 5 has a non-finite coordinate" in metrics["skipped"][0]["reason"]
    assert "on_error: skip" in (run_dir / "config.yaml").read_text()


def test_the_banner_counts_the_skipped_shapes(tmp_path, capsys):
    meshes = make_data(tmp_path / "meshes", {"badnan": "nan"})
    path = config_file(tmp_path, meshes, tmp_path / "cache")
    assert (
        main(
            [
                "train",
                path,
                "--run-dir",
                str(tmp_path / "run"),
                "--no-progress",
                "--workers",
                "0",
                "--set",
                "data.on_error=skip",
                "train.epochs=1",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "test metrics (1 shapes, model of epoch 1 chosen on validation, 1 shapes skipped)" in out
    assert "skipped train/badnan: " in out


def test_preprocess_follows_the_same_policy(tmp_path, capsys):
    meshes = make_data(tmp_path / "meshes", {"badnan": "nan"})
    path = config_file(tmp_path, meshes, tmp_path / "cache")
    assert main(["preprocess", path, "--workers", "0"]) == 2
    err = capsys.readouterr().err
    assert "1 of 7 shapes failed" in err and "train/badnan" in err and "--skip-bad" in err
    assert main(["preprocess", path, "--workers", "0", "--skip-bad"]) == 0
    err = capsys.readouterr().err
    assert "1 shapes skipped" in err and "skipped train/badnan: " in err


def test_evaluate_follows_the_same_policy(skipped_run, capsys):
    run_dir, meshes = skipped_run["run"], skipped_run["meshes"]
    label_file = meshes / "test" / "shape5.txt"
    good = label_file.read_text()
    try:
        label_file.write_text(good.replace("\n", "\nxyz\n", 1))  # now a text value on line 2
        assert main(["evaluate", str(run_dir), "--no-progress", "--out", str(run_dir / "e.json")]) == 2
        err = capsys.readouterr().err
        assert "test/shape5: " in err and "shape5.txt: line 2: 'xyz' is not a number" in err
        assert "--skip-bad" in err
        assert (
            main(
                [
                    "evaluate",
                    str(run_dir),
                    "--split",
                    "val",
                    "--no-progress",
                    "--skip-bad",
                    "--out",
                    str(run_dir / "e.json"),
                ]
            )
            == 0
        )
        skipped = strict_json(run_dir / "e.json")["skipped"]
        assert {item["name"] for item in skipped} == {"train/badnan", "test/shape5"}
    finally:
        label_file.write_text(good)


def test_a_label_file_with_text_is_one_bad_shape_named_by_file_and_line(tmp_path, capsys):
    meshes = make_data(tmp_path / "meshes", {"badlabel": "text label"})
    path = config_file(tmp_path, meshes, tmp_path / "cache")
    assert main(["train", path, "--run-dir", str(tmp_path / "run"), "--no-progress", "--workers", "0"]) == 2
    err = capsys.readouterr().err
    assert "badlabel.txt: line 21: 'abc' is not a number" in err and "row 20" not in err
    assert (
        main(
            [
                "train",
                path,
                "--run-dir",
                str(tmp_path / "run"),
                "--no-progress",
                "--workers",
                "0",
                "--skip-bad",
                "--set",
                "train.epochs=1",
            ]
        )
        == 0
    )
    assert "badlabel.txt: line 21" in strict_json(tmp_path / "run" / "metrics.json")["skipped"][0]["reason"]


# -------------------------------------------------------------------------------------------- 2. splits
def test_pictures_of_test_shapes_are_named_once_by_their_split(skipped_run):
    plots = sorted(p.name for p in (skipped_run["run"] / "plots").glob("*.png"))
    assert plots == ["test_shape5.png", "training_curves.png"]


def test_a_run_whose_only_test_shape_is_dropped_reports_validation_scores_as_such(tmp_path, capsys):
    meshes = make_data(tmp_path / "meshes", {"badnan": "nan"}, test=("badnan",))
    path = config_file(tmp_path, meshes, tmp_path / "cache")
    run_dir = tmp_path / "run"
    assert main(["train", path, "--run-dir", str(run_dir), "--no-progress", "--workers", "0", "--skip-bad"]) == 0
    out = capsys.readouterr().out
    assert "val metrics (1 shapes, model of epoch" in out and "test metrics" not in out
    assert "no test shapes" in out
    assert strict_json(run_dir / "metrics.json")["split"] == "val"
    pictures = [p.name for p in (run_dir / "plots").glob("*_shape*.png")]
    assert len(pictures) == 1 and pictures[0].startswith("val_train_shape")
    assert "no test shapes" in (run_dir / "train.log").read_text()


# ----------------------------------------------------------------------------- 5. advice the user can take
def test_predict_repairs_a_mesh_and_answers_every_input_vertex(skipped_run, tmp_path, capsys):
    sphere = icosphere(subdivisions=1, noise=0.05, seed=3)
    vertices = np.vstack([sphere.vertices, sphere.vertices[:1]])
    faces = sphere.faces.copy()
    faces[0, 0] = len(vertices) - 1  # a duplicate of vertex 0 that a face uses
    mesh = tmp_path / "dup.obj"
    mesh.write_text(trimesh.Trimesh(vertices, faces, process=False).export(file_type="obj"))
    prefix = tmp_path / "out" / "dup"
    assert main(["predict", str(skipped_run["run"]), str(mesh), "--out", str(prefix)]) == 0
    assert "merged 1 duplicate vertices" in capsys.readouterr().out
    prediction = np.load(tmp_path / "out" / "dup.npy")
    assert prediction.shape == (len(vertices),) and prediction[-1] == prediction[0]


def test_predict_answers_a_scan_with_a_hole_a_second_piece_a_fin_and_half_the_body(skipped_run, tmp_path):
    """The forms a scanner or a mesh tool leaves: each predicted without an error, one value per vertex."""
    mesh = trimesh.load(skipped_run["meshes"] / "test" / "shape5.obj", process=False)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    extra = np.vstack([vertices, vertices[faces[0, :2]].mean(axis=0) + [0.0, 0.0, 0.3]])
    fin = np.array([[faces[0, 0], faces[0, 1], len(vertices)]])  # a third face on an edge
    piece = icosphere(1, radius=0.3).vertices + [4.0, 0.0, 0.0]  # a separate component
    forms = {
        "hole": (vertices, faces[5:]),
        "fin": (extra, np.vstack([faces, fin])),
        "pieces": (np.vstack([vertices, piece]), np.vstack([faces, icosphere(1).faces + len(vertices)])),
        "half": (vertices, faces[vertices[faces].mean(axis=1)[:, 2] > 0]),  # one side, vertices kept
    }
    for name, (form_vertices, form_faces) in forms.items():
        path = tmp_path / f"{name}.ply"
        path.write_bytes(trimesh.Trimesh(form_vertices, form_faces, process=False).export(file_type="ply"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the non-manifold edge and the unused vertices are reported
            # Half the body: scaled like the whole one (the config's patch.area is 100), not to its own area.
            scale = np.sqrt(100.0 / mesh.area) if name == "half" else None
            prediction = predict(skipped_run["run"], path, scale=scale)
        assert prediction.shape == (len(form_vertices),), name
        assert set(np.unique(prediction)) <= {0, 1}, name


def _test_sphere_and_majority(spheres):
    """The test sphere's file, its true labels and the fraction of its vertices in the larger class."""
    labels = np.loadtxt(spheres / "test" / "shape5.txt", dtype=np.int64)
    return spheres / "test" / "shape5.obj", labels, majority_fraction(labels)


def test_a_run_trained_on_meshes_predicts_on_the_cloud_of_a_mesh(learnt_sphere_run, labelled_spheres, tmp_path):
    run_dir, _ = learnt_sphere_run
    mesh, truth, majority = _test_sphere_and_majority(labelled_spheres)
    vertices = trimesh.load(mesh, process=False).vertices
    cloud = tmp_path / "cloud.ply"
    cloud.write_bytes(trimesh.PointCloud(vertices).export(file_type="ply"))
    for name, path in (("mesh", mesh), ("cloud", cloud)):
        assert main(["predict", str(run_dir), str(path), "--out", str(tmp_path / name)]) == 0
    on_mesh, on_cloud = np.load(tmp_path / "mesh.npy"), np.load(tmp_path / "cloud.npy")
    assert on_cloud.shape == on_mesh.shape == truth.shape
    # The run has learnt the labelling (measured: every vertex right, against 60 % for the majority class).
    assert (on_mesh == truth).mean() > majority + 0.3
    # The cloud is triangulated through its points and read by the same front: the same right answers
    # (measured: every point right).
    assert (on_cloud == truth).mean() > majority + 0.3
    assert (on_cloud == on_mesh).mean() >= 0.9


def test_a_segmentation_run_chooses_its_refinement_on_validation_and_predict_applies_it_to_a_cloud(
    learnt_sphere_run, labelled_spheres
):
    from zernet.inference import load_checkpoint
    from zernet.inference.refine import SEGMENTATION_CONFIDENCE

    run_dir, metrics = learnt_sphere_run  # trained with eval.refine_rings [0, 1, 2]
    choice = metrics["refine_choice"]
    assert choice["split"] == "val" and sorted(choice["accuracy"]) == ["0", "1", "2"]
    assert load_checkpoint(run_dir / "best.pt")["refine_rings"] == choice["rings"] == metrics["refine_rings"]
    assert ("unrefined_summary" in metrics) == (choice["rings"] > 0)  # the test split before refinement
    # On a cloud: the sure points keep the network's answer, the unsure ones take their rings' average.
    mesh, truth, majority = _test_sphere_and_majority(labelled_spheres)
    cloud = Surface(trimesh.load(mesh, process=False).vertices, None)
    raw, probabilities = predict(run_dir, cloud, probabilities=True, refine_rings=0)
    refined = predict(run_dir, cloud, refine_rings=2)
    assert refined.shape == raw.shape == truth.shape
    sure = probabilities.max(axis=1) >= SEGMENTATION_CONFIDENCE
    assert sure.any() and not sure.all()  # measured: 20 of the 42 points sure
    np.testing.assert_array_equal(refined[sure], raw[sure])
    # The average over two rings keeps most answers right (measured: 39 of 42 points, all 42 unrefined; the
    # majority class is 25 of them).
    assert (raw == truth).mean() > majority + 0.3 and (refined == truth).mean() > majority + 0.2
    np.testing.assert_array_equal(predict(run_dir, cloud), predict(run_dir, cloud, refine_rings=choice["rings"]))


def test_predict_with_an_explicit_scale_equals_the_area_normalised_prediction(skipped_run):
    from zernet.geometry import load_surface

    surface = load_surface(skipped_run["meshes"] / "test" / "shape5.obj")
    run = skipped_run["run"]
    _, probabilities = predict(run, surface, probabilities=True)
    factor = np.sqrt(100.0 / surface.area)  # the config's patch.area is 100
    _, scaled = predict(run, surface, probabilities=True, scale=factor)
    np.testing.assert_allclose(scaled, probabilities, atol=1e-5)


@pytest.mark.parametrize(
    "override, expected",
    [
        ("data.num_classes=two", "data.num_classes must be an integer >= 1, got 'two'"),
        ("model.widths=abc", "model.widths must be a list of integers, got 'abc'"),
        ("model.widths=[8,-1]", "model 'zernet' cannot be built from its options (model.widths=[8, -1]"),
        ("data.colour=red", "unknown key data.colour for data kind 'segmentation'"),
        ("train.device=gpu7", "train.device: 'gpu7' is not a device"),
    ],
)
def test_config_errors_name_the_key_before_any_data_is_read(tmp_path, capsys, override, expected):
    path = config_file(tmp_path, tmp_path / "no-such-folder", tmp_path / "cache")
    assert main(["train", path, "--run-dir", str(tmp_path / "run"), "--set", override]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "internal error" not in err
    assert expected in err and "no-such-folder" not in err


# ------------------------------------------------------------------------------------------ 6. class names
def test_class_names_come_from_a_names_file_beside_the_labels(tmp_path, capsys):
    meshes = make_data(tmp_path / "meshes")
    path = config_file(tmp_path, meshes, tmp_path / "cache", labels=str(meshes))
    (meshes / "class_names.txt").write_text("lower half\nupper half\n")
    assert (
        main(
            [
                "train",
                path,
                "--run-dir",
                str(tmp_path / "run"),
                "--no-progress",
                "--workers",
                "0",
                "--set",
                "train.epochs=1",
            ]
        )
        == 0
    )
    best = torch.load(tmp_path / "run" / "best.pt", weights_only=True)
    assert best["preprocess"]["class_names"] == ["lower half", "upper half"]
    (meshes / "class_names.txt").write_text("only one\n")
    assert main(["preprocess", path, "--workers", "0"]) == 2
    assert "class_names.txt: 1 class names for 2 classes" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------- 7. smaller
def test_classes_no_shape_has_give_one_warning_and_null_scores(tmp_path, capsys):
    meshes = make_data(tmp_path / "meshes")
    path = config_file(tmp_path, meshes, tmp_path / "cache", num_classes=4)
    run_dir = tmp_path / "run"
    assert (
        main(["train", path, "--run-dir", str(run_dir), "--no-progress", "--workers", "0", "--set", "train.epochs=1"])
        == 0
    )
    log = (run_dir / "train.log").read_text()
    assert log.count("data.num_classes is 4 but no shape has a vertex of class 2, 3") == 1
    summary = strict_json(run_dir / "metrics.json")["summary"]
    assert summary["per_class_accuracy"][2:] == [None, None] and summary["per_class_iou"][2:] == [None, None]


def test_warnings_are_one_line_without_source(skipped_run, capsys):
    assert main(["preprocess", skipped_run["config"], "--workers", "0", "--set", "data.strict=false"]) == 0
    err = capsys.readouterr().err
    assert "zernet preprocess: warning: data.strict is deprecated: use data.on_error: skip" in err
    assert "warnings.warn" not in err and ".py:" not in err


def test_a_corrupt_cache_entry_is_reported_once(skipped_run, capsys):
    cache_files = sorted((skipped_run["tmp"] / "cache" / "shapes").glob("train_shape0-*.npz"))
    cache_files[0].write_bytes(cache_files[0].read_bytes()[:50])
    assert main(["preprocess", skipped_run["config"], "--workers", "0", "--skip-bad"]) == 0
    err = capsys.readouterr().err
    assert err.count("shape cache file is unreadable") == 1 and ".py:" not in err


def test_resume_may_change_threads_and_never_lowers_the_recorded_epochs(skipped_run, tmp_path, capsys):
    run_dir = skipped_run["run"]
    assert (
        main(
            [
                "train",
                "--resume",
                "--run-dir",
                str(run_dir),
                "--no-progress",
                "--workers",
                "0",
                "--set",
                "train.threads=2",
                "train.epochs=1",
            ]
        )
        == 0
    )
    stored = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert stored["train"]["epochs"] == 2 and stored["train"]["threads"] == 2
    assert main(["train", "--resume", "--run-dir", str(run_dir), "--set", "model.dropout=0.5"]) == 2
    err = capsys.readouterr().err
    assert "--resume --set cannot change model.dropout" in err and "train.threads" in err


def test_run_files_are_readable_by_others_like_any_file(skipped_run):
    mask = os.umask(0o022)
    os.umask(mask)
    for name in ("metrics.json", "best.pt", "last.pt", "config.yaml"):
        mode = stat.S_IMODE((skipped_run["run"] / name).stat().st_mode)
        assert mode == 0o666 & ~mask, (name, oct(mode))
