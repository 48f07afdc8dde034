"""Surviving faults: kill -9 mid-epoch and resume, damaged checkpoints and caches, a full disk, crafted
checkpoints, and preprocessing that goes on past a broken mesh, a crashing worker and a damaged cache file.

Training uses six 200-vertex creatures and a small model (an epoch takes well under a second); the
preprocessing tests use 162-vertex icospheres. The only subprocess is the training run that gets killed.
"""

from __future__ import annotations

import errno
import io
import os
import pickle
import signal
import subprocess
import sys
import time
import warnings
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
import yaml
from tiny_configs import faults_config

from zernet import io_utils
from zernet.cli import main
from zernet.data import PreprocessError, ShapeSource, SkippedShapesWarning, build_dataset
from zernet.data.preprocess import WORKER_DIED, file_key, preprocess_shapes
from zernet.geometry import load_surface
from zernet.inference import load_checkpoint
from zernet.io_utils import atomic_save_torch, atomic_write_bytes
from zernet.operators import PatchConfig
from zernet.training import train

pytestmark = pytest.mark.timeout(240)

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """A complete 3-epoch run (also fills the shared cache): the reference for every resume below."""
    root = tmp_path_factory.mktemp("faults")
    config = faults_config(root / "cache")
    train(config, root / "full", progress=False, workers=0)
    return root, config, load_checkpoint(root / "full" / "last.pt")


def assert_same_weights(checkpoint: dict, reference: dict) -> None:
    assert checkpoint["state"]["epoch"] == reference["state"]["epoch"]
    for key, value in reference["model"].items():
        torch.testing.assert_close(checkpoint["model"][key], value, rtol=1e-6, atol=1e-7, msg=key)


# ------------------------------------------------------------------------------- kill -9 mid-epoch
# Runs the real CLI in a child process. After every optimiser step it looks for last.pt: the first step
# taken after a checkpoint exists (= step 1 of epoch 2, of 3 steps) writes a marker and then blocks, so
# the SIGKILL below always lands in the middle of epoch 2, with in-memory progress that is lost.
KILL_SCRIPT = r"""
import sys, time
from pathlib import Path
import torch
run_dir, marker = Path(sys.argv[1]), Path(sys.argv[2])
original = torch.optim.Adam.step
def step(self, *args, **kwargs):
    result = original(self, *args, **kwargs)
    if (run_dir / "last.pt").exists() and not marker.exists():
        marker.write_text("mid-epoch 2")
        time.sleep(600)
    return result
torch.optim.Adam.step = step
from zernet.cli import main
sys.exit(main(sys.argv[3:]))
"""


def test_sigkill_mid_epoch_then_resume_equals_uninterrupted(uninterrupted, tmp_path):
    root, config, reference = uninterrupted
    config_path = tmp_path / "config.yaml"
    config_path.write_text(yaml.safe_dump(config))
    run_dir, marker = tmp_path / "run", tmp_path / "marker"
    script = tmp_path / "killable.py"
    script.write_text(KILL_SCRIPT)
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    child = subprocess.Popen(
        [
            sys.executable,
            str(script),
            str(run_dir),
            str(marker),
            "train",
            str(config_path),
            "--run-dir",
            str(run_dir),
            "--no-progress",
            "--workers",
            "0",
        ],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        deadline = time.monotonic() + 180
        while not marker.exists():
            assert child.poll() is None, child.stdout.read().decode()[-3000:]
            assert time.monotonic() < deadline, "the child never reached epoch 2"
            time.sleep(0.1)
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=30)
    finally:
        if child.poll() is None:
            child.kill()
        child.stdout.close()
    assert child.returncode == -signal.SIGKILL
    assert load_checkpoint(run_dir / "last.pt")["state"]["epoch"] == 1  # epoch 2 never finished
    assert not list(run_dir.glob(".*.tmp"))

    assert main(["train", "--resume", "--run-dir", str(run_dir), "--no-progress", "--workers", "0"]) == 0
    assert_same_weights(load_checkpoint(run_dir / "last.pt"), reference)


# ------------------------------------------------------------------------ damaged checkpoints
def _cut_run(root, config, run_dir) -> None:
    """The reference run stopped after 2 of its 3 epochs (last.pt = epoch 2, previous.pt = epoch 1)."""
    train({**config, "train": {**config["train"], "epochs": 2}}, run_dir, progress=False, workers=0)


@pytest.mark.parametrize("damage", ["truncate", "flip"])
def test_damaged_last_checkpoint_is_named_and_resume_falls_back(uninterrupted, tmp_path, damage, caplog):
    root, config, reference = uninterrupted
    run_dir = tmp_path / "run"
    _cut_run(root, config, run_dir)
    last = run_dir / "last.pt"
    data = last.read_bytes()
    if damage == "truncate":
        last.write_bytes(data[: len(data) // 2])
    else:  # flip bytes in the middle of the stored tensors: the zip CRC catches it
        middle = len(data) // 2
        last.write_bytes(data[:middle] + bytes(b ^ 0xFF for b in data[middle : middle + 64]) + data[middle + 64 :])

    with pytest.raises(ValueError, match=r"last\.pt: not a readable zernet checkpoint"):
        load_checkpoint(last)
    assert load_checkpoint(run_dir / "previous.pt")["state"]["epoch"] == 1

    train(config, run_dir, resume=True, progress=False, workers=0)
    log = (run_dir / "train.log").read_text()
    assert "last.pt: not a readable zernet checkpoint" in log and "resuming from" in log
    assert_same_weights(load_checkpoint(run_dir / "last.pt"), reference)


def test_no_usable_checkpoint_lists_every_file(uninterrupted, tmp_path):
    root, config, _ = uninterrupted
    run_dir = tmp_path / "run"
    _cut_run(root, config, run_dir)
    for name in ("last.pt", "previous.pt", "best.pt"):
        (run_dir / name).write_bytes(b"garbage")
    with pytest.raises(ValueError, match="no usable checkpoint") as caught:
        train(None, run_dir, resume=True, progress=False, workers=0)
    for name in ("last.pt", "previous.pt", "best.pt"):
        assert name in str(caught.value)


# ----------------------------------------------------------------------------------- full disk
def _raise_enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


@pytest.mark.parametrize("where", ["fsync", "write"])
def test_full_disk_during_atomic_write_keeps_the_old_file(tmp_path, monkeypatch, where):
    path = tmp_path / "last.pt"
    atomic_save_torch({"weights": torch.arange(5.0)}, path)
    before = path.read_bytes()
    if where == "fsync":
        monkeypatch.setattr(io_utils.os, "fsync", _raise_enospc)
    else:
        real_fdopen = os.fdopen

        class FullDisk(io.BufferedWriter):
            def write(self, data):
                super().write(data[: len(data) // 3])  # part of the bytes reach the temp file, then the disk is full
                raise OSError(errno.ENOSPC, "No space left on device")

        monkeypatch.setattr(io_utils.os, "fdopen", lambda fd, mode: FullDisk(real_fdopen(fd, mode, buffering=0)))
    with pytest.raises(OSError, match="No space left") as caught:
        atomic_save_torch({"weights": torch.zeros(10_000)}, path)
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.pt"]  # no temp file left behind


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc to tell checkpoint writes apart")
def test_full_disk_during_training_keeps_the_previous_checkpoint(uninterrupted, tmp_path, monkeypatch):
    root, config, reference = uninterrupted
    run_dir = tmp_path / "run"
    _cut_run(root, config, run_dir)  # last.pt = epoch 2
    before = {name: (run_dir / name).read_bytes() for name in ("last.pt", "best.pt")}
    real_fsync = os.fsync

    def fsync_fails_for_checkpoints(fd):
        # Small files (config.yaml) still fit; the disk is full when a checkpoint's temp file is flushed.
        if os.readlink(f"/proc/self/fd/{fd}").endswith(".tmp") and ".pt." in os.readlink(f"/proc/self/fd/{fd}"):
            _raise_enospc()
        return real_fsync(fd)

    monkeypatch.setattr(io_utils.os, "fsync", fsync_fails_for_checkpoints)
    with pytest.raises(OSError, match=r"No space left.*\.pt"):
        train(config, run_dir, resume=True, progress=False, workers=0)  # epoch 3's checkpoint cannot be written
    monkeypatch.undo()
    assert {name: (run_dir / name).read_bytes() for name in before} == before
    assert not list(run_dir.glob(".*.tmp"))
    train(config, run_dir, resume=True, progress=False, workers=0)  # disk freed: resume finishes the run
    assert_same_weights(load_checkpoint(run_dir / "last.pt"), reference)


# ---------------------------------------------------------------------------- crafted checkpoint
class _Payload:
    """Unpickling this would call Path.touch(marker): code execution from a data file."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


@pytest.mark.parametrize("container", ["torch-zip", "raw-pickle"])
def test_crafted_checkpoint_cannot_run_code(tmp_path, container):
    marker = tmp_path / "pwned"
    path = tmp_path / "last.pt"
    payload = {"format": "zernet-checkpoint-1", "model": _Payload(marker)}
    if container == "torch-zip":
        torch.save(payload, path)
    else:
        path.write_bytes(pickle.dumps(payload))
    with pytest.raises(ValueError, match=r"last\.pt: not a readable zernet checkpoint") as caught:
        load_checkpoint(path)
    assert "weights" in str(caught.value).lower()  # torch's weights_only refusal is passed on
    assert not marker.exists()
    with pytest.raises(ValueError, match="no usable checkpoint"):
        train(None, tmp_path, resume=True, progress=False, workers=0)
    assert not marker.exists()
    pickle.loads(pickle.dumps(_Payload(marker)))  # the payload is real: plain unpickling does run it
    assert marker.exists()


# ------------------------------------------------------------------------------- preprocessing
AREA = 100.0
CONFIGS = [PatchConfig(r0=1.2, n_samples=1500, patch_size=30, n_max=3)]


def _load_logged(path: str, log: str):
    """ShapeSource loader that records every call (in any worker process) by appending to ``log``."""
    with open(log, "a", encoding="utf-8") as handle:
        handle.write(Path(path).stem + "\n")
    surface = load_surface(path)
    return surface, np.zeros(surface.n_vertices, dtype=np.int64)


def _kill_own_worker(path: str, log: str):
    """Loader that dies the way the out-of-memory killer would kill a worker."""
    os.kill(os.getpid(), signal.SIGKILL)


def _mesh_folder(folder: Path, n_good: int = 3) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n_good):
        mesh = trimesh.creation.icosphere(subdivisions=2)
        vertices = np.asarray(mesh.vertices) * (1 + 0.03 * np.random.default_rng(i).standard_normal((162, 1)))
        path = folder / f"good{i}.ply"
        trimesh.Trimesh(vertices, mesh.faces, process=False).export(path)
        paths.append(path)
    bad = folder / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 nan\nf 1 2 3\n")
    return paths + [bad]


def _sources(paths, log, loader=_load_logged):
    return [ShapeSource(p.stem, partial(loader, str(p), str(log)), key=file_key(p)) for p in paths]


def _calls(log: Path) -> list[str]:
    return sorted(log.read_text().split()) if log.exists() else []


def _cache_state(cache: Path) -> dict[str, int]:
    return {str(p.relative_to(cache)): p.stat().st_mtime_ns for p in cache.rglob("*") if p.suffix in (".npz", ".zop")}


def test_parallel_preprocessing_reports_a_broken_mesh_and_resumes_from_the_cache(tmp_path):
    paths = _mesh_folder(tmp_path / "meshes")
    cache, log = tmp_path / "cache", tmp_path / "calls.log"
    failures = preprocess_shapes(_sources(paths, log), CONFIGS, cache, AREA, workers=2, progress=False)
    assert set(failures) == {"bad"}
    assert "bad.obj" in failures["bad"] and "nan" in failures["bad"].lower()
    assert _calls(log) == ["bad", "good0", "good1", "good2"]
    first = _cache_state(cache)
    assert len(list((cache / "shapes").glob("good*.npz"))) == 3

    # Second run: the three cached shapes are neither loaded nor rewritten; only the failed one is retried.
    log.unlink()
    failures = preprocess_shapes(_sources(paths, log), CONFIGS, cache, AREA, workers=2, progress=False)
    assert set(failures) == {"bad"} and _calls(log) == ["bad"]
    assert _cache_state(cache) == first

    # A damaged cache entry is named, rebuilt, and only its shape is loaded again.
    damaged = next((cache / "shapes").glob("good1-*.npz"))
    damaged.write_bytes(damaged.read_bytes()[:100])
    log.unlink()
    with (
        pytest.warns(RuntimeWarning, match=rf"{damaged.name}: shape cache file is unreadable"),
        pytest.warns(SkippedShapesWarning, match="bad.obj"),
    ):
        dataset = build_dataset(
            _sources(paths, log),
            CONFIGS,
            cache,
            AREA,
            task="classification",
            num_classes=2,
            split_names={"train": ["good0", "good1"], "test": ["good2"]},
            workers=0,
            progress=False,
            on_error="skip",
        )
    assert _calls(log) == ["bad", "good1"]
    assert dataset.names == ["good0", "good1", "good2"] and set(dataset.failures) == {"bad"}
    assert np.isfinite(dataset[1].features).all()


def test_a_worker_killed_mid_shape_is_reported_and_the_others_go_on(tmp_path):
    paths = _mesh_folder(tmp_path / "meshes", n_good=2)[:2]
    log = tmp_path / "calls.log"
    sources = _sources(paths, log) + [ShapeSource("killer", partial(_kill_own_worker, "x", str(log)), key="k")]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        failures = preprocess_shapes(sources, CONFIGS, tmp_path / "cache", AREA, workers=2, progress=False)
    assert failures == {"killer": WORKER_DIED}
    assert len(list((tmp_path / "cache" / "shapes").glob("good*.npz"))) == 2


def test_every_shape_failing_is_an_error_naming_them(tmp_path):
    bad = _mesh_folder(tmp_path / "meshes", n_good=0)
    with pytest.raises(PreprocessError, match="bad.obj"):
        build_dataset(
            _sources(bad, tmp_path / "log"),
            CONFIGS,
            tmp_path / "cache",
            AREA,
            task="classification",
            num_classes=2,
            split_names={"train": ["bad"]},
            workers=0,
            progress=False,
        )


def test_atomic_write_bytes_leaves_no_temp_file_on_interrupt(tmp_path, monkeypatch):
    path = tmp_path / "cache.npz"
    atomic_write_bytes(path, b"old")
    monkeypatch.setattr(io_utils.os, "replace", lambda *a: (_ for _ in ()).throw(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        atomic_write_bytes(path, b"new")
    assert path.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["cache.npz"]
