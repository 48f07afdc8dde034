"""The benchmarks' shared harness: result files and the generated-bodies folder it keeps."""

import json
import subprocess
from pathlib import Path

import pytest

from benchmarks import harness


def test_markdown_table_aligns_the_first_column_left_and_figures_right():
    lines = harness.markdown_table(["model", "accuracy"], [["zernet", "97.8 %"], ["feastnet", "95.1 %"]])
    assert lines == [
        "| model | accuracy |",
        "| --- | ---: |",
        "| zernet | 97.8 % |",
        "| feastnet | 95.1 % |",
    ]


def test_markdown_table_takes_an_alignment_per_column():
    assert harness.markdown_table(["a", "b", "c"], [[1, 2, 3]], align="rlr")[1] == "| ---: | --- | ---: |"


def test_result_file_keeps_the_dots_of_a_stem():
    stem = Path("results") / "few_people_more_people_lr2.5e-3"
    assert harness.result_file(stem, ".json") == Path("results/few_people_more_people_lr2.5e-3.json")


def test_write_json_puts_commit_machine_and_command_before_the_result(tmp_path, monkeypatch):
    monkeypatch.setattr(harness, "commit", lambda checkout=harness.REPO: "abc123")
    monkeypatch.setattr("sys.argv", [str(harness.REPO / "benchmarks" / "speed" / "bench_startup.py"), "--repeats", "2"])
    path = harness.write_json(tmp_path / "out" / "bench.json", {"median_s": 1.5})
    stored = json.loads(path.read_text())
    assert list(stored)[:3] == ["commit", "machine", "command"]
    assert stored["commit"] == "abc123"
    assert stored["command"] == "python -m benchmarks.speed.bench_startup --repeats 2"
    assert stored["median_s"] == 1.5
    assert stored["machine"]["cpus"] >= 1 and stored["machine"]["torch"]


def test_write_markdown_ends_with_the_command_and_commit(tmp_path, monkeypatch):
    monkeypatch.setattr(harness, "commit", lambda checkout=harness.REPO: "abc123")
    monkeypatch.setattr("sys.argv", [str(harness.REPO / "benchmarks" / "experiments" / "scans.py")])
    text = harness.write_markdown(tmp_path / "scans.md", ["# scans", "", "body"]).read_text()
    assert text == "# scans\n\nbody\n\nMade by `python -m benchmarks.experiments.scans` at commit `abc123`.\n"


def test_commit_names_the_checkout_head_and_marks_changed_tracked_files(tmp_path):
    def git(*arguments):
        return subprocess.run(["git", "-C", str(tmp_path), *arguments], capture_output=True, text=True, check=True)

    git("init", "-q")
    (tmp_path / "a.txt").write_text("one")
    git("add", "a.txt")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "first")
    head = git("rev-parse", "HEAD").stdout.strip()
    (tmp_path / "untracked.txt").write_text("ignored")
    assert harness.commit(tmp_path) == head
    (tmp_path / "a.txt").write_text("two")
    assert harness.commit(tmp_path) == head + "-dirty"
    assert harness.commit(tmp_path / "no-repository-here") == "unknown"


def test_ensure_bodies_writes_once_per_set_of_parameters(tmp_path, monkeypatch):
    calls = []

    def write_bodies(folder, count, seed, topology, poses, n_test, cache_dir, progress, forms, forms_split, people):
        calls.append((count, seed, topology, n_test, forms, people))
        Path(folder).mkdir(parents=True, exist_ok=True)

    monkeypatch.setattr("zernet.data.bodies.write_bodies", write_bodies)
    folder = tmp_path / "bodies"
    assert harness.ensure_bodies(folder, count=10, n_test=2, seed=0, topology="coarse-369") == folder
    harness.ensure_bodies(folder, count=10, n_test=2, seed=0, topology="coarse-369")
    assert calls == [(10, 0, "coarse-369", 2, None, None)]
    harness.ensure_bodies(folder, count=10, n_test=2, seed=1, topology="coarse-369")  # another seed: rewritten
    assert calls[-1] == (10, 1, "coarse-369", 2, None, None) and len(calls) == 2


def test_body_surface_is_the_first_generated_training_body():
    pytest.importorskip("anny")  # the optional bodies extra
    import numpy as np

    from zernet.data.bodies import generate_bodies
    from zernet.data.segmentation import HUMAN_PART_NAMES

    body = generate_bodies(count=2, seed=0, topology="faust", n_test=1, progress=False)[0]
    as_generated, parts = harness.body_surface(seed=0, area=None)
    assert np.array_equal(as_generated.vertices, body.vertices) and np.array_equal(as_generated.faces, body.faces)
    assert list(parts) == [HUMAN_PART_NAMES[part] for part in body.parts]
    scaled, _ = harness.body_surface(seed=0)
    assert scaled.area == pytest.approx(harness.BODY_AREA)


def test_the_command_shows_paths_outside_the_repository_by_their_last_part_only(monkeypatch):
    monkeypatch.setattr(
        harness.sys,
        "argv",
        [
            str(harness.REPO / "benchmarks/speed/bench_operator.py"),
            "--data",
            "/home/me/MPI-FAUST",
            "--set",
            "data.root=/srv/scans",
            "--out",
            str(harness.REPO / "benchmarks/speed/results/x"),
            "--threads",
            "2",
        ],
    )
    assert harness.command() == (
        "python -m benchmarks.speed.bench_operator --data .../MPI-FAUST --set data.root=.../scans "
        "--out benchmarks/speed/results/x --threads 2"
    )
