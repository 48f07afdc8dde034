"""Scoring a trained model or an ensemble on a split: metrics, baselines, the correspondence refinement
chosen on validation, and the one-line summary.

A correspondence is refined on the run's device (torch sparse products, :mod:`zernet.training.refine`),
and its geodesic errors are measured once per test shape for the unrefined and the refined map together
(:class:`zernet.metrics.GeodesicErrors`: the diameter once, each distinct vertex pair once)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from zernet import metrics as zmetrics
from zernet.data import SkippedShapesWarning
from zernet.training.build import build_dataset
from zernet.training.checkpoint import checkpoint_path, load_checkpoint
from zernet.training.config import ConfigError
from zernet.training.predict import model_from_checkpoint, predict_record
from zernet.training.refine import refine_correspondence
from zernet.training.runtime import resolve_device
from zernet.training.targets import unstandardise

__all__ = ["evaluate", "evaluate_members", "select_refine_rings", "check_ensemble", "summary_line"]


def _kind(checkpoint: dict) -> str:
    """correspondence | segmentation | regression: what a checkpoint's model predicts."""
    if checkpoint["task"] != "classification":
        return "regression"
    return "correspondence" if checkpoint.get("correspondence", False) else "segmentation"


def _refined(probabilities: torch.Tensor, record, rings: int) -> np.ndarray:
    """The refined map, computed where ``probabilities`` are (the run's device). Correspondence by vertex
    index: every shape has the template's connectivity, so the record's faces serve for both the shape and
    the template."""
    faces = record.surface.faces
    if faces is None:
        raise ValueError(f"shape {record.name}: refining a correspondence needs a triangle mesh")
    return refine_correspondence(probabilities, faces, faces, rings).argmax(dim=1).cpu().numpy()


def _score_shape(kind: str, record, pred: np.ndarray, target: np.ndarray, n_classes: int | None, geodesic_errors=None):
    """(per-shape scores, per-vertex error) of one shape; segmentation also returns its confusion matrix.
    ``geodesic_errors``: the shape's :class:`~zernet.metrics.GeodesicErrors` (correspondence)."""
    if kind == "correspondence":
        errors = geodesic_errors(pred, target)
        scores = zmetrics.correspondence_scores(errors)
        return {k: v for k, v in scores.items() if not k.startswith("curve_")}, errors, None
    if kind == "segmentation":
        confusion = zmetrics.confusion_matrix(pred, target, n_classes)
        return {"accuracy": zmetrics.accuracy(pred, target)}, (pred != target).astype(np.float64), confusion
    with np.errstate(divide="ignore", invalid="ignore"):
        errors = np.abs(pred - target) / np.abs(target)
    return zmetrics.regression_scores(pred, target), errors, None


def evaluate_members(
    members: Sequence[tuple],
    dataset,
    indices: Sequence[int],
    device,
    progress: bool,
    keep: int = 3,
    refine_rings: int = 0,
) -> tuple[dict, list[dict]]:
    """Metrics of the model (or ensemble) ``members`` (a list of ``(model, checkpoint)``, see
    :func:`~zernet.training.predict.predict_record`) on the shapes at ``indices`` and the predictions of
    the first ``keep``. A correspondence is scored after refinement over ``refine_rings`` rings
    (:mod:`zernet.training.refine`; other tasks ignore it), and its unrefined scores are kept beside."""
    checkpoint = members[0][1]
    task, kind = checkpoint["task"], _kind(checkpoint)
    refine_rings = refine_rings if kind == "correspondence" else 0
    n_classes = None if checkpoint.get("num_classes") is None else int(checkpoint["num_classes"])
    per_shape: dict[str, dict] = {}
    kept: list[dict] = []
    errors_all, unrefined_errors, confusion, label_counts = [], [], None, None
    for position, i in enumerate(tqdm(indices, desc="evaluating", unit="shape", leave=False, disable=not progress)):
        record = dataset[i]
        if record.target is None:
            raise ValueError(f"shape {record.name} has no ground truth to evaluate against")
        pred, probabilities = predict_record(members, record, device)
        target = np.asarray(record.target)
        geodesics = zmetrics.GeodesicErrors(record.surface) if kind == "correspondence" else None
        if refine_rings:
            unrefined_errors.append(geodesics(pred, target))
            pred = _refined(torch.from_numpy(probabilities).to(device), record, refine_rings)
        per_shape[record.name], errors, shape_confusion = _score_shape(kind, record, pred, target, n_classes, geodesics)
        if kind == "correspondence":
            errors_all.append(errors)
        elif kind == "segmentation":
            confusion = shape_confusion if confusion is None else confusion + shape_confusion
            counts = np.bincount(target, minlength=n_classes)
            label_counts = counts if label_counts is None else label_counts + counts
        if position < keep:
            kept.append(
                {"name": record.name, "surface": record.surface, "prediction": pred, "target": target, "error": errors}
            )

    result: dict[str, Any] = {"task": task, "kind": kind, "n_shapes": len(indices)}
    if kind == "correspondence":
        scores = zmetrics.correspondence_scores(errors_all)
        result["summary"] = {k: v for k, v in scores.items() if not k.startswith("curve_")}
        result["error_curve"] = {"radii": scores["curve_radii"], "fractions": scores["curve_fractions"]}
        result["baseline"] = {"chance_accuracy": 1.0 / float(checkpoint["num_classes"])}
        result["refine_rings"] = refine_rings
        if refine_rings:  # what the refinement changed, on the same split
            unrefined = zmetrics.correspondence_scores(unrefined_errors)
            result["unrefined_summary"] = {k: v for k, v in unrefined.items() if not k.startswith("curve_")}
    elif kind == "segmentation":
        result["summary"] = zmetrics.segmentation_scores(confusion=confusion)
        result["baseline"] = {"majority_class_accuracy": float(label_counts.max() / label_counts.sum())}
    else:
        aggregated = zmetrics.aggregate_scores(per_shape)
        result["summary"] = aggregated["mean"]
        result["summary_std"] = aggregated["std"]
        stats = checkpoint.get("target_stats")
        if stats is not None:
            result["baseline"] = _training_mean_baseline(stats, dataset, indices)
    result["per_shape"] = per_shape
    return result, kept


def select_refine_rings(
    members: Sequence[tuple], dataset, candidates: Sequence[int], device, progress: bool
) -> tuple[int, dict | None]:
    """The refinement rings to use and how they were chosen: the only candidate, or (correspondence) the one
    whose exact accuracy on the ``val`` split is highest, the fewest rings on a tie.

    Returns ``(rings, choice)`` with ``choice`` None when nothing was chosen, else
    ``{"split": "val", "accuracy": {rings: exact accuracy}, "rings": chosen}`` for ``metrics.json``.
    """
    candidates = sorted(set(int(c) for c in candidates))
    if not candidates or candidates[0] < 0:
        raise ConfigError(f"refine rings must be one or more integers >= 0, got {candidates}")
    if _kind(members[0][1]) != "correspondence":
        return 0, None
    if len(candidates) == 1:
        return candidates[0], None
    indices = dataset.splits.get("val", [])
    if not indices:
        raise ConfigError(
            f"eval.refine_rings lists several candidates ({candidates}) but the data set has no "
            "validation split to choose among them: give one number"
        )
    hits = {rings: 0 for rings in candidates}
    total = 0
    for i in tqdm(indices, desc="choosing refine rings", unit="shape", leave=False, disable=not progress):
        record = dataset[i]
        pred, probabilities = predict_record(members, record, device)
        target = np.asarray(record.target)
        total += len(target)
        probabilities = torch.from_numpy(probabilities).to(device)  # refined there, once per candidate
        for rings in candidates:
            refined = pred if rings == 0 else _refined(probabilities, record, rings)
            hits[rings] += int(np.sum(refined == target))
    accuracy = {rings: hits[rings] / total for rings in candidates}
    chosen = max(candidates, key=lambda rings: (accuracy[rings], -rings))
    return chosen, {"split": "val", "accuracy": {str(k): v for k, v in accuracy.items()}, "rings": chosen}


def _training_mean_baseline(stats: dict, dataset, indices: Sequence[int]) -> dict:
    """The honest reference: predicting the training mean (of the trained units) everywhere."""
    mean = float(unstandardise(torch.zeros(1), stats))
    constant = [zmetrics.regression_scores(np.full(len(dataset.target(i)), mean), dataset.target(i)) for i in indices]
    return {
        "training_mean_MAPE": float(np.mean([c["MAPE"] for c in constant])),
        "training_mean_RRMSE": float(np.mean([c["RRMSE"] for c in constant])),
    }


def summary_line(metrics: dict) -> str:
    """The headline scores of a metrics dictionary and its baselines, on one line."""
    summary = metrics.get("summary", {})
    keys = {
        "correspondence": ("accuracy", "within_0.025", "within_0.05", "mean_geodesic_error"),
        "segmentation": ("accuracy", "mean_class_accuracy", "mean_iou"),
        "regression": ("MAPE", "RRMSE", "PCC", "HR10", "HR20", "HR30"),
    }.get(metrics.get("kind"), ())
    parts = [f"{key} {summary[key]:.4f}" for key in keys if key in summary]
    if "unrefined_summary" in metrics:
        parts.append(
            f"(refined over {metrics['refine_rings']} rings; unrefined accuracy "
            f"{metrics['unrefined_summary']['accuracy']:.4f})"
        )
    for key, value in metrics.get("baseline", {}).items():
        parts.append(f"(baseline {key} {value:.4f})")
    return ", ".join(parts)


def check_ensemble(paths: Sequence[Path], checkpoints: Sequence[dict]) -> None:
    """Ensemble members must predict the same thing from the same inputs: say which one differs and how."""

    def data_section(checkpoint):
        return {k: v for k, v in checkpoint["config"]["data"].items() if k != "root"}

    def short(value) -> str:  # a split of hundreds of indices would bury the message
        text = repr(value)
        return text if len(text) <= 60 else text[:57] + "..."

    def difference(a, b) -> str:
        if isinstance(a, dict) and isinstance(b, dict):
            keys = [k for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
            return "; ".join(f"{k}: {short(a.get(k))} vs {short(b.get(k))}" for k in keys)
        return f"{short(a)} vs {short(b)}"

    first = checkpoints[0]
    for path, checkpoint in zip(paths[1:], checkpoints[1:]):
        for what, value in (
            ("task", lambda c: c["task"]),
            ("number of classes", lambda c: c["num_classes"]),
            ("preprocessing", lambda c: c["preprocess"]),
            ("data section", data_section),
        ):
            if value(checkpoint) != value(first):
                raise ConfigError(
                    f"cannot ensemble {path} with {paths[0]}: their {what} differs "
                    f"({difference(value(checkpoint), value(first))})"
                )


def evaluate(
    run_dir_or_checkpoint,
    dataset=None,
    split: str = "test",
    progress: bool = True,
    device: str | None = None,
    on_error: str | None = None,
    refine_rings: int | Sequence[int] | None = None,
) -> dict:
    """Evaluate a trained model (a run folder's ``best.pt``, or any checkpoint file) on one split; given
    several, evaluate their ensemble.

    Args:
        run_dir_or_checkpoint: a run folder or a ``.pt`` checkpoint, or a list of them: an ensemble whose
            prediction averages the members' probabilities or (regression) their outputs in the transformed
            target units (see :func:`~zernet.training.predict.predict_record`). Members must share the
            task, the classes, the preprocessing and the data section (apart from ``data.root``), e.g. the
            same recipe trained with different ``train.seed``.
        dataset: the :class:`~zernet.data.ShapeDataset` to use; by default it is rebuilt (from the cache)
            from the configuration stored in the (first) checkpoint.
        split: ``"test"``, ``"val"``, ``"train"`` or any split the data set defines.
        device: overrides the configured ``train.device``.
        on_error: overrides the stored ``data.on_error`` when the data set is rebuilt: ``"skip"`` evaluates
            without the shapes that fail to load (listed under ``"skipped"``).
        refine_rings: correspondence refinement (:mod:`zernet.training.refine`): a ring radius, or
            candidates chosen among on the validation split; None: the run's ``eval.refine_rings``.

    Returns:
        The same metrics dictionary that training writes to ``metrics.json`` (for an ensemble,
        ``checkpoint`` lists the members and ``best_epoch``/``epochs_trained`` are per member).
    """
    many = isinstance(run_dir_or_checkpoint, (list, tuple))
    paths = [checkpoint_path(p) for p in (run_dir_or_checkpoint if many else [run_dir_or_checkpoint])]
    if not paths:
        raise ConfigError("evaluate needs at least one run folder or checkpoint")
    checkpoints = [load_checkpoint(path) for path in paths]
    check_ensemble(paths, checkpoints)
    config = checkpoints[0]["config"]
    device = resolve_device(device or config["train"]["device"])
    if dataset is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SkippedShapesWarning)  # listed under "skipped" instead
            dataset = build_dataset(config, progress=progress, on_error=on_error)
    if split not in dataset.splits:
        raise ConfigError(f"the data set has no split {split!r} (it has {', '.join(sorted(dataset.splits))})")
    indices = dataset.splits[split]
    if not indices:
        others = ", ".join(name for name, members in sorted(dataset.splits.items()) if members)
        raise ConfigError(f"split {split!r} of the data set is empty (splits with shapes: {others or 'none'})")
    members = [(model_from_checkpoint(checkpoint, device), checkpoint) for checkpoint in checkpoints]
    if refine_rings is None:
        refine_rings = config.get("eval", {}).get("refine_rings", (0,))  # older runs: no refinement
    rings, choice = select_refine_rings(
        members, dataset, [refine_rings] if isinstance(refine_rings, int) else refine_rings, device, progress
    )
    metrics, _ = evaluate_members(members, dataset, indices, device, progress, keep=0, refine_rings=rings)
    if choice is not None:
        metrics["refine_choice"] = choice
    best_epochs = [c["state"]["best_epoch"] for c in checkpoints]
    epochs = [c["state"]["epoch"] for c in checkpoints]
    metrics.update(
        {
            "split": split,
            "checkpoint": [str(p) for p in paths] if many else str(paths[0]),
            "best_epoch": best_epochs if many else best_epochs[0],
            "epochs_trained": epochs if many else epochs[0],
            "skipped": [{"name": name, "reason": reason} for name, reason in getattr(dataset, "failures", {}).items()],
        }
    )
    return metrics
