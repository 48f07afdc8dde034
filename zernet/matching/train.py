"""Training the descriptor model on generated bodies, supervised by their exact ground-truth maps.

Each step draws a random pair of training bodies, each in its own form (:mod:`zernet.matching.bodies`:
remeshed independently, a noisy point cloud, or a one-sided partial scan, which keeps its whole body's
scale and is always the source of its pair), runs the descriptor model on both in one block-diagonal
batch, solves the functional map ``C_ts`` (target functions to the source) with the differentiable layer,
and takes the loss (``train.loss``):

- ``fmap``: ``‖C_ts - C_gt‖²`` summed over the entries, ``C_gt = Φ_sᵀ M_s Φ_t[T_gt]`` the functional map of
  the true point map (GeomFmaps' loss);
- ``fmap+point``: that plus ``point_weight`` times the mean distance, in units of the square root of the
  area, between the true target point of each source vertex and its expected position under a soft point
  map (a softmax over target vertices of the negative squared spectral-embedding distance ``‖Φ_s C_ts -
  Φ_t‖²``, temperature the mean nearest distance, not differentiated): it scores the point map the
  matcher actually reads off ``C``, where ``‖C - C_gt‖`` weighs every frequency alike.

Validation: fixed pairs of other bodies (same split, indices after the training ones), scored by the mean
Euclidean distance between the predicted and the true target point (x100, over the square root of the
target's area) of the point map read off the layer's ``C`` (no ZoomOut, so it measures the descriptors);
the weights of the best validation score are kept (``best.pt``).

Run: ``python -m zernet.matching.train CONFIG --out RUN_DIR [--set KEY=VALUE ...]`` (see
``configs/matching/bodies.yaml``); the run folder gets ``config.yaml``, ``train.log``, ``history.json``,
``best.pt`` / ``last.pt`` (matching model files, :func:`zernet.matching.model.save_matching_model`).
"""

from __future__ import annotations

import argparse
import copy
import json
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yaml

from zernet.data.features import feature_channels
from zernet.geometry import FixedScale, Surface
from zernet.io_utils import atomic_write_bytes, plain, write_json
from zernet.matching.bodies import LocatedForm, body_forms, ground_truth_map
from zernet.matching.fmap import fmap_from_pointmap, pointmap_from_fmap
from zernet.matching.match import descriptor_fmap
from zernet.matching.model import DescriptorModel, MatchingSpec, save_matching_model
from zernet.matching.shapes import MatchShape, prepare_shape, rotating_columns
from zernet.operators import Geometry
from zernet.training.augment import random_rotation
from zernet.training.config import ConfigError, apply_overrides, load_config

__all__ = ["TrainingPair", "prepare_bodies", "pair_loss", "validation_error", "train", "read_config", "main"]


@dataclass
class TrainingPair:
    """A source and a target shape with the true target vertex of every source vertex."""

    source: MatchShape
    target: MatchShape
    truth: np.ndarray  # (N_source,) int64


#: The sections of a matching training config (``configs/matching/``).
SECTIONS = ("data", "spec", "train")


def read_config(path: str | Path, overrides: Sequence[str] = ()) -> dict:
    """The YAML config with dotted ``KEY=VALUE`` overrides, read and applied as ``zernet train --set`` does
    (:func:`zernet.training.config.apply_overrides`: ``train.steps=100``, ``spec.patch.0.r0=4.5``)."""
    config = apply_overrides(load_config(path), overrides)
    unknown = sorted(set(config) - set(SECTIONS))
    if unknown:
        raise ConfigError(
            f"{path}: unknown section(s) {', '.join(unknown)}; a matching config has {', '.join(SECTIONS)}"
        )
    return config


def make_spec(config: dict, feature_mean=None, feature_std=None) -> MatchingSpec:
    """The :class:`MatchingSpec` of the config's ``spec`` section."""
    values = dict(config["spec"])
    patch = tuple(dict(p) for p in values.pop("patch"))
    n_max = int(patch[0].get("n_max", 5))
    in_channels = feature_channels(values["feature_kind"], n_max)
    return MatchingSpec(
        patch_configs=patch, in_channels=in_channels, feature_mean=feature_mean, feature_std=feature_std, **values
    )


def prepare_bodies(
    config: dict, spec: MatchingSpec, indices, split: str = "train", forms: dict | None = None
) -> tuple[list[LocatedForm], list[MatchShape], dict, np.ndarray]:
    """The located forms of bodies ``indices`` and their prepared shapes."""
    data = config["data"]
    located, body_vertices, faces = body_forms(
        indices,
        split,
        forms or data["forms"],
        data["form_seed"],
        data["topology"],
        data["poses"],
        data["body_seed"],
        data["cache_dir"],
    )
    shapes = [
        prepare_shape(
            form.surface,
            spec.patch_config_objects(),
            _form_scale(form, spec.area, body_vertices, faces),
            spec.feature_kind,
            spec.n_eigen,
            cache_dir=data["cache_dir"],
            name=form.name,
            descriptor_vertices=spec.descriptor_vertices,
        )
        for form in located
    ]
    return located, shapes, body_vertices, faces


def _form_scale(form: LocatedForm, area: float, body_vertices: dict, faces: np.ndarray) -> float | FixedScale:
    """How a form is scaled: to ``area``, but a partial scan by the factor of its whole body (as
    ``zernet match --same-scale`` scales it), so it keeps its size."""
    if form.form != "partial":
        return area
    return FixedScale(float(np.sqrt(area / Surface(body_vertices[form.body], faces).area)))


def oriented_pair(forms: list[LocatedForm], a: int, b: int) -> tuple[int, int] | None:
    """(source, target) positions of a pair with a partial scan as the source, never the target (the map of
    a part into a whole is defined, the reverse is not); None for two partial scans."""
    partial_a, partial_b = forms[a].form == "partial", forms[b].form == "partial"
    if partial_a and partial_b:
        return None
    return (b, a) if partial_b else (a, b)


def small_rotation(rng: np.random.Generator, max_degrees: float) -> np.ndarray:
    """A rotation about a uniformly random axis by an angle uniform in [0, max_degrees] (Rodrigues)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(0.0, max_degrees))
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def pair_rotations(rng: np.random.Generator, mode: str, jitter_degrees: float) -> tuple[np.ndarray, np.ndarray]:
    """The rotations of a training pair's rotating feature columns.

    ``mode``: ``none``; ``any`` (each shape its own uniform rotation: descriptors must not depend on the
    pose); ``pair`` (one uniform rotation for both, each then turned by up to ``jitter_degrees``: the
    matcher aligns the target to the source first, :func:`zernet.matching.match.candidate_alignments`, so
    descriptors need only agree between two shapes in nearly the same frame, whatever that frame is).
    """
    if mode == "pair":
        common = random_rotation(rng, "any")
        return tuple(common @ small_rotation(rng, jitter_degrees) for _ in range(2))
    return random_rotation(rng, mode), random_rotation(rng, mode)


def feature_statistics(shapes: list[MatchShape], rotating: list[slice]) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel mean and standard deviation over the shapes' vertices; rotating parts get mean 0 and one
    common deviation per part, so a rotated input is standardised like an unrotated one."""
    stacked = np.concatenate([shape.features for shape in shapes]).astype(np.float64)
    mean, std = stacked.mean(axis=0), stacked.std(axis=0)
    for columns in rotating:
        mean[columns] = 0.0
        std[columns] = np.sqrt((stacked[:, columns] ** 2).mean())
    return mean, np.maximum(std, 1e-6)


def pair_loss(
    model: DescriptorModel,
    pair: TrainingPair,
    loss: str,
    point_weight: float,
    rotations: tuple[np.ndarray, np.ndarray] | None,
    rotating: list[slice],
) -> torch.Tensor:
    """The training loss of one pair (module docstring); ``rotations``: one 3x3 per shape for the rotating
    feature columns (None: none)."""
    features = []
    for index, shape in enumerate((pair.source, pair.target)):
        x = shape.features.copy()
        if rotations is not None:
            for columns in rotating:
                x[:, columns] = x[:, columns] @ rotations[index].T.astype(np.float32)
        features.append(torch.as_tensor(x))
    geometry = Geometry.concatenate([pair.source.geometry, pair.target.geometry])
    descriptors = model(torch.cat(features), geometry)
    n_source = pair.source.n_vertices
    descriptors_s, descriptors_t = descriptors[:n_source], descriptors[n_source:]
    fmap = descriptor_fmap(model, descriptors_t, descriptors_s, pair.target, pair.source)  # C_ts (k_s, k_t)
    k = model.spec.n_fmap
    truth_fmap = torch.as_tensor(
        fmap_from_pointmap(pair.truth, pair.target.basis, pair.source.basis, k, k), dtype=fmap.dtype
    )
    value = ((fmap - truth_fmap) ** 2).sum()
    if loss == "fmap+point":
        vectors_s, _, _ = pair.source.basis_tensors(k)
        vectors_t, _, _ = pair.target.basis_tensors(k)
        distances = torch.cdist(vectors_s @ fmap, vectors_t) ** 2  # (N_s, N_t)
        temperature = distances.min(dim=1).values.mean().detach().clamp_min(1e-12)
        soft_map = torch.softmax(-distances / temperature, dim=1)
        positions = torch.as_tensor(pair.target.surface.vertices, dtype=torch.float32)
        error = torch.linalg.norm(soft_map @ positions - positions[pair.truth], dim=1)
        value = value + point_weight * error.mean() / float(np.sqrt(model.spec.area))
    elif loss != "fmap":
        raise ValueError(f"train.loss must be 'fmap' or 'fmap+point', got {loss!r}")
    return value


@torch.no_grad()
def validation_error(model: DescriptorModel, pairs: list[TrainingPair]) -> float:
    """Mean over the pairs of the mean Euclidean error x100 / sqrt(area) of the layer's point map."""
    model.eval()
    errors = []
    for pair in pairs:
        descriptors_s = model(torch.as_tensor(pair.source.features), pair.source.geometry)
        descriptors_t = model(torch.as_tensor(pair.target.features), pair.target.geometry)
        fmap = descriptor_fmap(model, descriptors_t, descriptors_s, pair.target, pair.source).double().numpy()
        predicted = pointmap_from_fmap(fmap, pair.target.basis, pair.source.basis)
        vertices = pair.target.surface.vertices
        distance = np.linalg.norm(vertices[predicted] - vertices[pair.truth], axis=1)
        errors.append(100 * distance.mean() / np.sqrt(pair.target.surface.area))
    return float(np.mean(errors))


def make_pairs(
    forms: list[LocatedForm], shapes: list[MatchShape], body_vertices: dict, faces: np.ndarray, index_pairs
) -> list[TrainingPair]:
    """Training pairs of the given (source, target) positions in ``forms``."""
    return [
        TrainingPair(shapes[a], shapes[b], ground_truth_map(forms[a], forms[b], body_vertices[forms[b].body], faces))
        for a, b in index_pairs
    ]


def _commit() -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
            cwd=Path(__file__).resolve().parent,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def train(config: dict, run_dir: str | Path, command: str = "") -> dict:
    """Train a descriptor model as ``config`` says, writing the run folder; returns the run's summary."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    settings, data = config["train"], config["data"]
    torch.manual_seed(int(settings["seed"]))
    rng = np.random.default_rng(int(settings["seed"]))
    log_lines = []

    def log(message: str) -> None:
        line = f"[{time.strftime('%H:%M:%S')}] {message}"
        print(line, flush=True)
        log_lines.append(line)
        atomic_write_bytes(run_dir / "train.log", ("\n".join(log_lines) + "\n").encode())

    atomic_write_bytes(run_dir / "config.yaml", yaml.safe_dump(plain(config), sort_keys=False).encode())
    started = time.perf_counter()
    spec = make_spec(config)
    n_train, n_val = int(data["train_bodies"]), int(data["val_bodies"])
    forms, shapes, body_vertices, faces = prepare_bodies(config, spec, range(n_train))
    val_forms, val_shapes, val_vertices, _ = prepare_bodies(config, spec, range(n_train, n_train + n_val))
    log(f"prepared {n_train} training and {n_val} validation bodies in {time.perf_counter() - started:.0f} s")
    n_max = int(spec.patch_configs[0].get("n_max", 5))
    rotating = rotating_columns(spec.feature_kind, n_max)
    rotate = settings.get("rotate", "none")
    mean, std = feature_statistics(shapes, rotating)
    spec = make_spec(config, tuple(mean.tolist()), tuple(std.tolist()))
    model = DescriptorModel(spec)
    optimiser = torch.optim.Adam(model.parameters(), lr=float(settings["lr"]))
    steps = int(settings["steps"])
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimiser, lambda step: 0.5 * (1 + np.cos(np.pi * min(step, steps) / steps))
    )
    val_positions = [oriented_pair(val_forms, i, (i + 1) % n_val) for i in range(n_val)]
    val_pairs = make_pairs(val_forms, val_shapes, val_vertices, faces, [p for p in val_positions if p is not None])
    provenance = {
        "command": command,
        "commit": _commit(),
        "config": plain(config),
        "torch": str(torch.__version__),
        "threads": torch.get_num_threads(),
    }
    best, history, window = float("inf"), [], []
    deadline = started + 60 * float(settings.get("max_minutes", 1e9))
    train_started = time.perf_counter()
    for step in range(1, steps + 1):
        model.train()
        pair_positions = None
        while pair_positions is None:
            pair_positions = oriented_pair(forms, *rng.choice(n_train, size=2, replace=False))
        pair = make_pairs(forms, shapes, body_vertices, faces, [pair_positions])[0]
        rotations = pair_rotations(rng, rotate, float(settings.get("rotate_jitter", 0.0))) if rotating else None
        loss = pair_loss(model, pair, settings["loss"], float(settings.get("point_weight", 1.0)), rotations, rotating)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
        window.append(loss.item())
        last = step == steps or time.perf_counter() > deadline
        if step % int(settings["val_every"]) == 0 or last:
            error = validation_error(model, val_pairs)
            elapsed = time.perf_counter() - train_started
            history.append({"step": step, "loss": float(np.mean(window)), "val_error": error, "seconds": elapsed})
            window = []
            improved = error < best
            if improved:
                best = error
                save_matching_model(model, run_dir / "best.pt", {**provenance, "step": step, "val_error": error})
            save_matching_model(model, run_dir / "last.pt", {**provenance, "step": step, "val_error": error})
            write_json(run_dir / "history.json", {"history": history})
            log(
                f"step {step}: loss {history[-1]['loss']:.4f}, validation error {error:.3f}"
                f"{' (best)' if improved else ''}, {elapsed / step:.2f} s/step"
            )
        if last:
            break
    summary = {
        "best_val_error": best,
        "steps": history[-1]["step"],
        "train_seconds": time.perf_counter() - train_started,
        "total_seconds": time.perf_counter() - started,
    }
    write_json(run_dir / "history.json", {"history": history, "summary": summary})
    log(f"done: {json.dumps(summary)}")
    return summary


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m zernet.matching.train", description=__doc__.split("\n")[0])
    parser.add_argument("config")
    parser.add_argument("--out", required=True, help="run folder")
    parser.add_argument(
        "--set",
        dest="overrides",
        nargs="+",
        action="extend",
        default=[],
        metavar="KEY=VALUE",
        help="override config entries with dotted keys, as zernet train --set, e.g. --set train.steps=100 "
        "spec.patch.0.r0=4.5 (values are read as YAML)",
    )
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    config = read_config(args.config, args.overrides)
    train(copy.deepcopy(config), args.out, command=" ".join(["python -m zernet.matching.train"] + sys.argv[1:]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
