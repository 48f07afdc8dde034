"""Predictions of a trained model (or an ensemble) on one record or on a new surface."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from zernet.data import prepare_record
from zernet.geometry import Surface, mesh_from_cloud, read_surface, repair_surface
from zernet.inference.batch import Batch, model_basis_orders, model_directional_order
from zernet.inference.model_file import checkpoint_path, load_checkpoint
from zernet.inference.refine import refine_correspondence, refine_segmentation
from zernet.inference.runtime import resolve_device
from zernet.inference.spec import build_model_from_spec
from zernet.inference.spectral_refine import check_radii, spectral_refiner, template_of
from zernet.inference.targets import destandardise, untransform
from zernet.operators import PatchConfig

__all__ = ["predict_record", "model_from_checkpoint", "predict"]


@torch.no_grad()
def predict_record(members: Sequence[tuple], record, device) -> tuple[np.ndarray, np.ndarray | None]:
    """(prediction, probabilities) for one record: class index and softmax per vertex, or the value.

    ``members`` is a list of ``(model, checkpoint)``. With several (an ensemble) the prediction is made from
    the mean of their softmax probabilities (classification), or of their outputs in the transformed target
    units (regression; with ``target_transform: log`` a geometric mean of the values), which for one member
    is that member's own prediction.
    """
    task = members[0][1]["task"]
    outputs = []
    for model, checkpoint in members:
        model.eval()
        batch = Batch(
            [record],
            device,
            None,
            checkpoint.get("feature_stats"),
            model_directional_order(model),
            model_basis_orders(model),
        )
        output = model(batch.features, batch.geometry).float()
        if task == "classification":
            outputs.append(torch.softmax(output, dim=1))
        else:
            outputs.append(destandardise(output.reshape(-1), checkpoint["target_stats"]))
    mean = outputs[0] if len(outputs) == 1 else torch.stack(outputs).mean(dim=0)
    if task == "classification":
        return mean.argmax(dim=1).cpu().numpy(), mean.cpu().numpy()
    return untransform(mean, members[0][1]["target_stats"]).cpu().numpy(), None


def model_from_checkpoint(checkpoint: dict, device: torch.device) -> torch.nn.Module:
    """The trained model of ``checkpoint`` on ``device``."""
    model = build_model_from_spec(checkpoint["model_spec"]).to(device)
    model.load_state_dict(checkpoint["model"])
    return model


def predict(
    checkpoint: str | Path,
    surface,
    probabilities: bool = False,
    device: str | None = None,
    cache_dir: str | Path | None = None,
    progress: bool = False,
    refine_rings: int | None = None,
    backend: str | None = None,
    scale: float | None = None,
    refine_spectral: float | None = None,
    refine_passes: int | None = None,
):
    """Per-vertex predictions of a trained model on a new surface: a mesh or a point cloud, whatever the
    training shapes were.

    Args:
        checkpoint: a run folder (its ``best.pt``) or a checkpoint file.
        surface: a :class:`~zernet.geometry.surface.Surface` or a path to a mesh / point-cloud file. It is
            repaired where it can be (:func:`~zernet.geometry.validate.repair_surface`: duplicate vertices
            merged, degenerate faces dropped; non-manifold edges, holes and several components are used as
            they are) and preprocessed like the training shapes (area normalisation, features, patch
            operators; a point cloud is triangulated through its own points for the front backend).
        probabilities: classification only — also return the (N, C) softmax probabilities.
        progress: print what was repaired (duplicate vertices merged, degenerate faces dropped).
        refine_rings: correspondence: refine the probabilities by the agreement of this many rings of mesh
            neighbours on the surface and on the template; segmentation: average them over this many rings of the
            surface (a cloud: of its triangulation) where the network is unsure (:mod:`zernet.inference.refine`);
            None: the number the run chose on its validation split (0 for runs that chose none).
        refine_spectral: correspondence only: after the rings, keep the prediction within this radius (a
            fraction of the template's geodesic diameter) of a spectral map read from it
            (:mod:`zernet.inference.spectral_refine`; it repairs flipped regions); 0: off; None: what the run
            chose on its validation split. The probabilities returned stay the ring-refined ones.
        refine_passes: correspondence: how many times the refinement by rings is repeated; None: what the run
            chose on its validation split (1 for runs that chose none).
        backend: polar-coordinate backend for this surface (``"front"``, ``"fast"``, ``"accurate"``); None:
            the run's own (every backend reads meshes and clouds alike).
        scale: None (default): scale the surface as the training shapes were (to the training area, or by
            the run's ``patch.scale``); a number: multiply its coordinates by this instead — for a partial
            scan, whose area is not the whole shape's (e.g. the factor that takes the training shapes'
            units to the training area).

    Returns:
        (N,) int64 class indices or (N,) float32 values, one per vertex of the *input* surface (a merged
        duplicate gets its kept copy's value; regression: in the surface's own units — the model predicts at
        the training area, and a target of area exponent e is divided by ``scale ** (2 e)``); with
        ``probabilities=True`` a tuple (prediction, probabilities).
    """
    checkpoint = load_checkpoint(checkpoint_path(checkpoint))
    config, spec = checkpoint["config"], checkpoint["preprocess"]
    if not hasattr(surface, "vertices"):
        surface = read_surface(surface)  # validated and repaired below, with the map back to its vertices
    repaired = repair_surface(surface)
    if progress and repaired.describe():
        print(f"{surface.name}: {repaired.describe()} (predictions are given back per vertex of the file)")
    patch_configs = [PatchConfig(**c) for c in spec["patch_configs"]]
    if backend is not None:
        patch_configs = [dataclasses.replace(c, backend=backend) for c in patch_configs]
    surface = repaired.surface
    if scale is None and spec.get("unit_scale"):  # trained at a fixed scale (patch.scale): the same factor
        scale = float(spec["unit_scale"])
    if scale is not None:
        if not scale > 0:
            raise ValueError(f"scale must be positive, got {scale}")
        surface = Surface(surface.vertices * scale, surface.faces, surface.normals, surface.fields, surface.name)
    record = prepare_record(
        surface,
        patch_configs,
        cache_dir=config["cache_dir"] if cache_dir is None else cache_dir,
        target_area=spec["area"] if scale is None else None,
        feature_kind=spec["feature_kind"],
    )
    record_scale = record.scale if scale is None else scale
    device = resolve_device(device or config["train"]["device"])
    model = model_from_checkpoint(checkpoint, device)
    pred, probs = predict_record([(model, checkpoint)], record, device)
    rings = checkpoint.get("refine_rings", 0) if refine_rings is None else refine_rings
    radius = checkpoint.get("refine_spectral", 0.0) if refine_spectral is None else refine_spectral
    passes = checkpoint.get("refine_passes", 1) if refine_passes is None else refine_passes
    if rings:
        probs = _refined_probabilities(checkpoint, record, probs, rings, passes)
        pred = probs.argmax(axis=1)
    if radius:
        pred = _globally_refined(checkpoint, record, probs, radius, device)
    if checkpoint["task"] == "classification":
        pred = pred.astype(np.int64)
    else:
        exponent = float(checkpoint.get("target_exponent", 0.0))  # older checkpoints: area-normalised
        pred = (pred / record_scale ** (2 * exponent)).astype(np.float32)
    pred = pred[repaired.vertex_map]
    if probabilities:
        if probs is None:
            raise ValueError("probabilities exist only for classification models")
        return pred, probs[repaired.vertex_map].astype(np.float32)
    return pred


def _refined_probabilities(checkpoint: dict, record, probabilities: np.ndarray, rings: int, passes: int) -> np.ndarray:
    """Refinement of a new surface's probabilities: a correspondence against the template the run stored
    (``passes`` times), a segmentation on the surface alone (once)."""
    if checkpoint["task"] != "classification":
        raise ValueError("refine_rings applies to classification models only; this one predicts values")
    if not checkpoint.get("correspondence"):  # segmentation: the shape's own rings, where the network is unsure
        faces = record.surface.faces
        return refine_segmentation(
            probabilities, mesh_from_cloud(record.surface).faces if faces is None else faces, rings
        )
    template = checkpoint.get("template_faces")
    if template is None:
        raise ValueError(
            "this checkpoint stores no template mesh (it was written before zernet refined "
            "correspondences): predict with refine_rings=0, or train the run again"
        )
    if record.surface.faces is None:
        raise ValueError(f"{record.name}: refining a correspondence needs a triangle mesh, not a point cloud")
    return refine_correspondence(probabilities, record.surface.faces, np.asarray(template), rings, passes)


def _globally_refined(checkpoint: dict, record, probabilities: np.ndarray, radius: float, device) -> np.ndarray:
    """The global refinement (:mod:`zernet.inference.spectral_refine`) of a new surface's (ring-refined)
    probabilities, against the template geometry the run stored, on ``device``."""
    if not checkpoint.get("correspondence"):
        raise ValueError(
            "refine_spectral applies to correspondence models only; this one predicts "
            + ("values" if checkpoint["task"] == "regression" else "segmentation classes")
        )
    radius = check_radii(radius)[0]
    template = template_of(checkpoint)
    if template is None:
        raise ValueError(
            "this checkpoint stores no template geometry (template_vertices: it was written before zernet "
            "refined correspondences globally): predict with refine_spectral=0, or train the run again"
        )
    refiner = spectral_refiner(*template)
    scores = torch.from_numpy(np.ascontiguousarray(probabilities, dtype=np.float32)).to(device)
    return refiner.refine(scores, record.surface, radius)
