"""Scoring a trained model or an ensemble on a split: metrics, baselines, the refinement of a
correspondence or a segmentation chosen on validation, and the one-line summary.

A correspondence is refined on the run's device: the agreement of each vertex's rings (torch sparse products,
:mod:`zernet.inference.refine`), then optionally the global step (:mod:`zernet.inference.spectral_refine`:
the prediction kept within reach of a spectral map, which repairs flipped regions), both chosen on the
validation split. The geodesic errors of a test shape are measured once for the unrefined, the
ring-refined and the refined map together (:class:`zernet.metrics.GeodesicErrors`: the diameter once, each
distinct vertex pair once). A segmentation is refined by the ring average of its unsure vertices
(:func:`zernet.inference.refine.refine_segmentation`), the ring count chosen on the validation split too."""

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
from zernet.geometry.cloud_mesh import mesh_from_cloud
from zernet.inference.model_file import checkpoint_path, load_checkpoint
from zernet.inference.predict import model_from_checkpoint, predict_record
from zernet.inference.refine import refine_correspondence, refine_segmentation
from zernet.inference.runtime import resolve_device
from zernet.inference.spectral_refine import check_radii, spectral_refiner, template_of
from zernet.inference.targets import unstandardise
from zernet.training.build import build_dataset
from zernet.training.config import ConfigError

__all__ = [
    "evaluate",
    "evaluate_members",
    "select_refinement",
    "select_refine_rings",
    "global_refinement_unavailable",
    "check_ensemble",
    "summary_line",
]


def _kind(checkpoint: dict) -> str:
    """correspondence | segmentation | regression: what a checkpoint's model predicts."""
    if checkpoint["task"] != "classification":
        return "regression"
    return "correspondence" if checkpoint.get("correspondence", False) else "segmentation"


def _ring_scores(probabilities: torch.Tensor, record, rings: int, kind: str, passes: int = 1) -> torch.Tensor:
    """The probabilities refined over ``rings`` rings, where they are (the run's device). Correspondence by
    vertex index (refined by the neighbours' agreement, ``passes`` times): every shape has the template's
    connectivity, so the record's faces serve for both the shape and the template. Segmentation: only the
    unsure vertices are averaged, over the shape's rings (a point cloud's: its triangulation's), once."""
    if not rings:
        return probabilities
    faces = record.surface.faces
    if kind == "segmentation":
        if faces is None:  # a cloud prepared for a backend that needs no triangles
            faces = mesh_from_cloud(record.surface).faces
        return refine_segmentation(probabilities, faces, rings)
    if faces is None:
        raise ValueError(f"shape {record.name}: refining a correspondence needs a triangle mesh")
    return refine_correspondence(probabilities, faces, faces, rings, passes)


def _refined(probabilities: torch.Tensor, record, rings: int, kind: str) -> np.ndarray:
    """The prediction refined over ``rings`` rings (:func:`_ring_scores`, one pass)."""
    return _ring_scores(probabilities, record, rings, kind).argmax(dim=1).cpu().numpy()


def global_refinement_unavailable(checkpoint: dict) -> str | None:
    """Why a checkpoint cannot be refined globally (:mod:`zernet.inference.spectral_refine`), or None if it
    can: it must be a correspondence model that stores its template's geometry."""
    if _kind(checkpoint) != "correspondence":
        return None  # nothing to refine globally: the radii are ignored
    if template_of(checkpoint) is None:
        return (
            "the checkpoint stores no template geometry (template_vertices: written before the global "
            "refinement existed), so eval.refine_spectral is unavailable and left off; train the run again to use it"
        )
    return None


def _refiner(checkpoint: dict):
    """The checkpoint's :class:`~zernet.inference.spectral_refine.SpectralRefiner`; ConfigError without a
    template geometry."""
    reason = global_refinement_unavailable(checkpoint)
    if reason is not None:
        raise ConfigError(reason)
    return spectral_refiner(*template_of(checkpoint))


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
    refine_spectral: float = 0.0,
    refine_passes: int = 1,
) -> tuple[dict, list[dict]]:
    """Metrics of the model (or ensemble) ``members`` (a list of ``(model, checkpoint)``, see
    :func:`~zernet.inference.predict.predict_record`) on the shapes at ``indices`` and the predictions of
    the first ``keep``. A correspondence is scored after refinement over ``refine_rings`` rings, repeated
    ``refine_passes`` times (:mod:`zernet.inference.refine`), and then, if ``refine_spectral`` > 0, by the global step within that
    radius (:mod:`zernet.inference.spectral_refine`); a segmentation after the rings alone; regression ignores
    both. The unrefined scores are kept beside (``unrefined_summary``), and with both steps the ring-refined
    ones (``ring_refined_summary``)."""
    checkpoint = members[0][1]
    task, kind = checkpoint["task"], _kind(checkpoint)
    refine_rings = refine_rings if kind != "regression" else 0
    refine_spectral = check_radii(refine_spectral)[0] if kind == "correspondence" else 0.0
    refiner = _refiner(checkpoint) if refine_spectral else None
    n_classes = None if checkpoint.get("num_classes") is None else int(checkpoint["num_classes"])
    per_shape: dict[str, dict] = {}
    kept: list[dict] = []
    errors_all, unrefined_errors, ring_errors, confusion, label_counts = [], [], [], None, None
    unrefined_confusion = None
    for position, i in enumerate(tqdm(indices, desc="evaluating", unit="shape", leave=False, disable=not progress)):
        record = dataset[i]
        if record.target is None:
            raise ValueError(f"shape {record.name} has no ground truth to evaluate against")
        pred, probabilities = predict_record(members, record, device)
        target = np.asarray(record.target)
        geodesics = zmetrics.GeodesicErrors(record.surface) if kind == "correspondence" else None
        if refine_rings and kind == "segmentation":
            shape_confusion = zmetrics.confusion_matrix(pred, target, n_classes)
            unrefined_confusion = (
                shape_confusion if unrefined_confusion is None else unrefined_confusion + shape_confusion
            )
            pred = _refined(torch.from_numpy(probabilities).to(device), record, refine_rings, kind)
        elif refine_rings or refine_spectral:
            unrefined_errors.append(geodesics(pred, target))
            scores = _ring_scores(torch.from_numpy(probabilities).to(device), record, refine_rings, kind, refine_passes)
            pred = scores.argmax(dim=1).cpu().numpy()
            if refine_spectral:
                if refine_rings:
                    ring_errors.append(geodesics(pred, target))
                pred = refiner.refine(scores, record.surface, refine_spectral)
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
        result["refine_passes"] = refine_passes if refine_rings else 1
        result["refine_spectral"] = refine_spectral
        for key, stage in (("unrefined_summary", unrefined_errors), ("ring_refined_summary", ring_errors)):
            if stage:  # what the refinement changed, on the same split
                scores = zmetrics.correspondence_scores(stage)
                result[key] = {k: v for k, v in scores.items() if not k.startswith("curve_")}
    elif kind == "segmentation":
        result["summary"] = zmetrics.segmentation_scores(confusion=confusion)
        result["refine_rings"] = refine_rings
        if unrefined_confusion is not None:  # what the refinement changed, on the same split
            result["unrefined_summary"] = zmetrics.segmentation_scores(confusion=unrefined_confusion)
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
    """:func:`select_refinement` over ring counts alone (no global step): ``(rings, choice)``."""
    rings, _, _, choice = select_refinement(members, dataset, candidates, [0.0], device, progress)
    return rings, choice


def select_refinement(
    members: Sequence[tuple],
    dataset,
    rings_candidates: Sequence[int],
    spectral_candidates: Sequence[float],
    device,
    progress: bool,
    passes_candidates: Sequence[int] = (1,),
) -> tuple[int, int, float, dict | None]:
    """The refinement to use and how it was chosen, on the ``val`` split (correspondence and segmentation;
    regression gets none): first the ring count, and for a correspondence the number of passes
    (:func:`~zernet.inference.refine.refine_correspondence`; each candidate count of passes is scored on the
    way to the largest), whose exact accuracy is highest (the fewest rings, then passes, on a tie), then, for a correspondence, after those rings, the global step's radius (:mod:`zernet.inference.spectral_refine`; 0: off) whose exact accuracy is
    highest (off on a tie, else the widest radius). A single candidate is taken without a look at the data.
    Without a template geometry (older checkpoints) the global step is left off with a warning
    (:func:`global_refinement_unavailable`).

    Returns ``(rings, passes, radius, choice)`` with ``choice`` None when nothing was chosen, else, for
    ``metrics.json``, ``{"split": "val", "accuracy": {rings: exact accuracy}, "rings": chosen}`` (with
    several pass counts: keys ``"RxP"``, rings x passes, and ``"passes": chosen``) and, when radii were
    candidates, ``"spectral": chosen radius`` and ``"spectral_accuracy": {radius: exact accuracy
    after the chosen rings}`` (radius "0": the rings alone).
    """
    candidates = sorted(set(int(c) for c in rings_candidates))
    if not candidates or candidates[0] < 0:
        raise ConfigError(f"refine rings must be one or more integers >= 0, got {candidates}")
    passes_list = sorted(set(int(c) for c in passes_candidates))
    if not passes_list or passes_list[0] < 1:
        raise ConfigError(f"refine passes must be one or more integers >= 1, got {passes_list}")
    try:
        radii = sorted(set(check_radii(spectral_candidates)))
    except ValueError as error:
        raise ConfigError(str(error)) from None
    kind = _kind(members[0][1])
    if kind == "regression":
        return 0, 1, 0.0, None
    if kind == "segmentation":
        radii = [0.0]  # the global step maps onto a template; a segmentation has none
        passes_list = [1]  # a segmentation averages its unsure vertices once
    unavailable = global_refinement_unavailable(members[0][1]) if any(radii) else None
    if unavailable is not None:
        warnings.warn(unavailable, UserWarning, stacklevel=2)
        radii = [0.0]
    if len(candidates) == 1 and len(radii) == 1 and len(passes_list) == 1:
        return candidates[0], passes_list[0], radii[0], None
    indices = dataset.splits.get("val", [])
    if not indices:
        raise ConfigError(
            f"eval.refine_rings / refine_passes / refine_spectral list several candidates ({candidates} / "
            f"{passes_list} / {radii}) but the data set has no validation split to choose among them: give one "
            "number each"
        )
    # (rings, passes): rings 0 is the prediction itself, whatever the passes
    combos = [(rings, passes) for rings in candidates for passes in (passes_list if rings else [1])]
    hits = {combo: 0 for combo in combos}
    spectral_hits = {radius: 0 for radius in radii}
    total = 0
    for i in tqdm(indices, desc="choosing the refinement", unit="shape", leave=False, disable=not progress):
        record = dataset[i]
        pred, probabilities = predict_record(members, record, device)
        target = np.asarray(record.target)
        total += len(target)
        probabilities = torch.from_numpy(probabilities).to(device)  # refined there, once per candidate
        for rings in candidates:
            if rings == 0:
                hits[0, 1] += int(np.sum(pred == target))
                continue
            scores = probabilities
            for passes in range(1, passes_list[-1] + 1):  # each pass continues the last one
                scores = _ring_scores(scores, record, rings, kind)
                if passes in passes_list:
                    hits[rings, passes] += int(np.sum(scores.argmax(dim=1).cpu().numpy() == target))
            del scores
    accuracy = {combo: hits[combo] / total for combo in combos}
    chosen, chosen_passes = max(combos, key=lambda combo: (accuracy[combo], -combo[0], -combo[1]))
    several_passes = len(passes_list) > 1
    choice: dict[str, Any] = {
        "split": "val",
        "accuracy": {(f"{r}x{p}" if several_passes else str(r)): v for (r, p), v in accuracy.items()},
        "rings": chosen,
    }
    if several_passes:
        choice["passes"] = chosen_passes
    radius = radii[0]
    if len(radii) > 1:
        refiner = _refiner(members[0][1])
        # Predicted again rather than kept: a FAUST-size shape's probabilities take 190 MB.
        for i in tqdm(indices, desc="choosing the global refinement", unit="shape", leave=False, disable=not progress):
            record = dataset[i]
            target = np.asarray(record.target)
            _, probabilities = predict_record(members, record, device)
            scores = _ring_scores(torch.from_numpy(probabilities).to(device), record, chosen, kind, chosen_passes)
            for candidate in radii:
                refined = refiner.refine(scores, record.surface, candidate)
                spectral_hits[candidate] += int(np.sum(refined == target))
        spectral_accuracy = {candidate: spectral_hits[candidate] / total for candidate in radii}
        radius = max(radii, key=lambda r: (spectral_accuracy[r], r == 0, r))
        choice["spectral"] = radius
        choice["spectral_accuracy"] = {f"{k:g}": v for k, v in spectral_accuracy.items()}
    if unavailable is not None:
        choice["spectral_unavailable"] = unavailable
    return chosen, chosen_passes, radius, choice


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
        radius = metrics.get("refine_spectral", 0.0)
        spectral = f" then globally within {radius:g} of the diameter" if radius else ""
        ring_stage = metrics.get("ring_refined_summary")
        passes = f" x {metrics['refine_passes']} passes" if metrics.get("refine_passes", 1) > 1 else ""
        rings_only = f", over the rings only {ring_stage['accuracy']:.4f}" if ring_stage else ""
        parts.append(
            f"(refined over {metrics['refine_rings']} rings{passes}{spectral}; unrefined accuracy "
            f"{metrics['unrefined_summary']['accuracy']:.4f}{rings_only})"
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
    refine_spectral: float | Sequence[float] | None = None,
    refine_passes: int | Sequence[int] | None = None,
) -> dict:
    """Evaluate a trained model (a run folder's ``best.pt``, or any checkpoint file) on one split; given
    several, evaluate their ensemble.

    Args:
        run_dir_or_checkpoint: a run folder or a ``.pt`` checkpoint, or a list of them: an ensemble whose
            prediction averages the members' probabilities or (regression) their outputs in the transformed
            target units (see :func:`~zernet.inference.predict.predict_record`). Members must share the
            task, the classes, the preprocessing and the data section (apart from ``data.root``), e.g. the
            same recipe trained with different ``train.seed``.
        dataset: the :class:`~zernet.data.ShapeDataset` to use; by default it is rebuilt (from the cache)
            from the configuration stored in the (first) checkpoint.
        split: ``"test"``, ``"val"``, ``"train"`` or any split the data set defines.
        device: overrides the configured ``train.device``.
        on_error: overrides the stored ``data.on_error`` when the data set is rebuilt: ``"skip"`` evaluates
            without the shapes that fail to load (listed under ``"skipped"``).
        refine_rings: correspondence refinement (:mod:`zernet.inference.refine`): a ring radius, or
            candidates chosen among on the validation split; None: the run's ``eval.refine_rings``.
        refine_spectral: the global step after the rings (:mod:`zernet.inference.spectral_refine`): a radius
            (fraction of the template's diameter; 0: off) or candidates, chosen together with the rings on the
            validation split; None: the run's ``eval.refine_spectral`` (off for runs made before it existed).
        refine_passes: how many times the correspondence refinement by rings is repeated, or candidates
            chosen with the rings on the validation split; None: the run's ``eval.refine_passes`` (1 for
            runs made before it existed).

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
    if refine_spectral is None:
        refine_spectral = config.get("eval", {}).get("refine_spectral", (0.0,))
    if refine_passes is None:
        refine_passes = config.get("eval", {}).get("refine_passes", (1,))
    rings, passes, radius, choice = select_refinement(
        members,
        dataset,
        [refine_rings] if isinstance(refine_rings, int) else refine_rings,
        [refine_spectral] if isinstance(refine_spectral, (int, float)) else refine_spectral,
        device,
        progress,
        [refine_passes] if isinstance(refine_passes, int) else refine_passes,
    )
    metrics, _ = evaluate_members(
        members,
        dataset,
        indices,
        device,
        progress,
        keep=0,
        refine_rings=rings,
        refine_spectral=radius,
        refine_passes=passes,
    )
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
