"""The global correspondence refinement (a flipped region repaired by the spectral map, a perfect map kept),
its configuration, its choice on the validation split only, and what runs and checkpoints record."""

import warnings

import numpy as np
import pytest
import torch
from meshes import ellipsoid
from tiny_configs import faust_run_config

from zernet.data import LoaderOptions, load_faust
from zernet.geometry import Surface
from zernet.inference import load_checkpoint, predict
from zernet.inference.spectral_refine import SpectralRefiner, check_radii
from zernet.metrics import GeodesicErrors
from zernet.operators import PatchConfig
from zernet.operators.spectral import fmap_from_pointmap, pointmap_from_fmap
from zernet.training import train
from zernet.training.config import ConfigError, EvalSection
from zernet.training.evaluation import evaluate_members, select_refinement, summary_line


def mirror_indices(surface: Surface) -> np.ndarray:
    """The vertex at the mirror image (x -> -x) of each vertex: the icosphere is symmetric, so exact."""
    mirrored = surface.vertices * np.array([-1.0, 1.0, 1.0])
    return np.array([np.argmin(np.linalg.norm(surface.vertices - p, axis=1)) for p in mirrored])


def flipped_scores(surface: Surface, flipped: np.ndarray, second: float = 0.0) -> torch.Tensor:
    """Probabilities of the identity map, except that the ``flipped`` vertices point at their mirror images
    (the other side of the body), with ``second`` left on the truth."""
    n = surface.n_vertices
    mirror = mirror_indices(surface)
    scores = np.full((n, n), 1e-7)
    scores[np.arange(n), np.arange(n)] = 0.9
    rows = np.flatnonzero(flipped)
    scores[rows] = 1e-7
    scores[rows, mirror[rows]] = 0.6
    if second:
        scores[rows, rows] = second
    return torch.from_numpy((scores / scores.sum(axis=1, keepdims=True)).astype(np.float32))


@pytest.fixture(scope="module")
def refiner():
    template = ellipsoid()
    return SpectralRefiner(template.vertices, template.faces)


@pytest.mark.parametrize("threshold, second", [(0.9, 0.0), (0.8, 0.0), (0.7, 0.3)])
def test_a_mirrored_region_is_repaired_to_the_identity(refiner, threshold, second):
    """A cap of 5-16 % of the vertices sent to the other side comes back exactly: with no probability left on
    the truth (the spectral map's own vertex) or with some (the network's second choice there)."""
    shape = ellipsoid()
    flipped = shape.vertices[:, 0] > threshold
    assert 0.05 < flipped.mean() < 0.16
    scores = flipped_scores(shape, flipped, second)
    errors = GeodesicErrors(shape)
    before = errors(scores.argmax(dim=1).numpy(), np.arange(shape.n_vertices))
    assert np.all(before[flipped] > 0.3) and np.all(before[~flipped] == 0)  # the flip lands across the shape
    np.testing.assert_array_equal(refiner.refine(scores, shape, 0.2), np.arange(shape.n_vertices))


def test_one_projection_of_the_map_keeps_part_of_the_flip(refiner):
    """Why the refinement goes up the spectrum in rounds: one functional map of the flipped map, at any size,
    still sends part of the cap across."""
    shape = ellipsoid()
    flipped = shape.vertices[:, 0] > 0.8
    scores = flipped_scores(shape, flipped)
    confidence, predicted = scores.max(dim=1)
    basis = refiner.shape_basis(shape)
    for k in (20, 80):
        fmap = fmap_from_pointmap(predicted.numpy(), refiner.basis, basis, k, k, weights=confidence.double().numpy())
        wrong = pointmap_from_fmap(fmap, refiner.basis, basis) != np.arange(shape.n_vertices)
        assert wrong[flipped].mean() > 0.2


def test_a_perfect_map_stays_perfect_on_another_shape(refiner):
    shape = ellipsoid(noise=0.03, seed=4)  # another geometry, the template's connectivity: the identity is true
    n = shape.n_vertices
    scores = torch.full((n, n), 1e-6)
    scores[torch.arange(n), torch.arange(n)] = 0.5
    scores /= scores.sum(dim=1, keepdim=True)
    for radius in (0.05, 0.1, 0.3):
        np.testing.assert_array_equal(refiner.refine(scores, shape, radius), np.arange(n))
    # Radius 0: the argmax as it is.
    flipped = flipped_scores(shape, shape.vertices[:, 0] > 0.8)
    np.testing.assert_array_equal(refiner.refine(flipped, shape, 0.0), flipped.argmax(dim=1).numpy())


def test_the_refinement_refuses_what_it_cannot_read(refiner):
    shape = ellipsoid()
    with pytest.raises(ValueError, match="expected"):
        refiner.refine(torch.ones(shape.n_vertices, 10), shape, 0.1)
    with pytest.raises(ValueError, match="triangle mesh"):
        refiner.refine(torch.ones(shape.n_vertices, shape.n_vertices), Surface(shape.vertices, None), 0.1)


def test_the_eval_section_takes_a_radius_or_candidates_in_0_1():
    assert EvalSection().refine_spectral == [0.0]
    assert EvalSection(refine_spectral=0.1).refine_spectral == [0.1]
    assert EvalSection(refine_spectral=[0, 0.1, 1]).refine_spectral == [0.0, 0.1, 1.0]
    for bad in ([], [-0.1], [1.5], "wide", [True], [float("nan")], [None]):
        with pytest.raises(ConfigError, match="eval.refine_spectral"):
            EvalSection(refine_spectral=bad)
    assert check_radii(0.2) == [0.2]
    with pytest.raises(ValueError, match="radii"):
        check_radii([0.1, 2])


# ------------------------------------------------------------------------------ choice and evaluation
class _FlippedMap(torch.nn.Module):
    """Predicts the identity map except that the vertices with x > 0.8 point at their mirror images."""

    def __init__(self, template: Surface):
        super().__init__()
        n = template.n_vertices
        flipped = np.flatnonzero(template.vertices[:, 0] > 0.8 * template.vertices[:, 0].max())
        target = np.arange(n)
        target[flipped] = mirror_indices(template)[flipped]
        logits = torch.full((n, n), -10.0)
        logits[torch.arange(n), torch.from_numpy(target)] = 10.0
        self.register_buffer("logits", logits)
        self.n_flipped = len(flipped)

    def forward(self, features, geometry):
        return self.logits


PATCH = {"r0": 1.2, "n_samples": 1500, "patch_size": 30, "n_max": 2}


@pytest.fixture(scope="module")
def ellipsoids(ellipsoid_faust_root):
    """3 train (1 of them validation), 2 test."""
    options = LoaderOptions(
        patch_configs=[PatchConfig(**PATCH)],
        cache_dir=ellipsoid_faust_root / "cache",
        n_val=1,
        workers=0,
        progress=False,
    )
    return load_faust(
        ellipsoid_faust_root, train_indices=range(3), test_indices=[3, 4], n_vertices=None, area=100.0, options=options
    )


class _Logged:
    """A data set that remembers which shapes were read."""

    def __init__(self, dataset):
        self.dataset, self.splits, self.read = dataset, dataset.splits, []

    def __getitem__(self, i):
        self.read.append(i)
        return self.dataset[i]


def _members(dataset, template_vertices=True):
    template = dataset[dataset.splits["train"][0]].surface
    checkpoint = {
        "task": "classification",
        "correspondence": True,
        "num_classes": template.n_vertices,
        "template_faces": torch.as_tensor(template.faces),
    }
    if template_vertices:
        checkpoint["template_vertices"] = torch.as_tensor(template.vertices, dtype=torch.float32)
    return [(_FlippedMap(ellipsoid()), checkpoint)]


def test_the_radius_is_chosen_on_the_validation_split_only_and_scored_beside_the_rings(ellipsoids):
    members, device = _members(ellipsoids), torch.device("cpu")
    logged = _Logged(ellipsoids)
    rings, _, radius, choice = select_refinement(members, logged, [0, 1], [0, 0.2, 0.3], device, progress=False)
    assert set(logged.read) == set(ellipsoids.splits["val"])  # never a test shape
    n, flipped = ellipsoids[0].surface.n_vertices, members[0][0].n_flipped
    assert choice["split"] == "val" and choice["rings"] == rings == 0
    assert choice["spectral_accuracy"]["0"] == pytest.approx(1 - flipped / n)
    assert choice["spectral_accuracy"]["0.2"] == 1.0 and choice["spectral_accuracy"]["0.3"] == 1.0
    assert radius == choice["spectral"] == 0.3  # a tie: the widest radius
    # A single candidate pair is taken without reading any shape.
    logged.read.clear()
    assert select_refinement(members, logged, [1], [0.2], device, progress=False) == (1, 1, 0.2, None)
    assert logged.read == []

    test = ellipsoids.splits["test"]
    metrics, _ = evaluate_members(members, ellipsoids, test, device, progress=False, keep=0, refine_spectral=0.2)
    assert metrics["refine_spectral"] == 0.2 and metrics["refine_rings"] == 0
    assert metrics["summary"]["accuracy"] == 1.0 and metrics["summary"]["within_0.1"] == 1.0
    assert metrics["unrefined_summary"]["accuracy"] == pytest.approx(1 - flipped / n)
    assert metrics["unrefined_summary"]["within_0.1"] < 1.0
    assert "ring_refined_summary" not in metrics
    assert "then globally within 0.2 of the diameter" in summary_line(metrics)
    both, _ = evaluate_members(
        members, ellipsoids, test, device, progress=False, keep=0, refine_rings=1, refine_spectral=0.2
    )
    assert both["ring_refined_summary"]["accuracy"] < both["summary"]["accuracy"]
    assert "over the rings only" in summary_line(both)


def test_a_checkpoint_without_template_geometry_leaves_the_global_step_off_and_says_so(ellipsoids):
    members, device = _members(ellipsoids, template_vertices=False), torch.device("cpu")
    with pytest.warns(UserWarning, match="no template geometry"):
        rings, _, radius, choice = select_refinement(members, ellipsoids, [0, 1], [0, 0.2], device, progress=False)
    assert radius == 0.0 and "spectral" not in choice and "no template geometry" in choice["spectral_unavailable"]
    with pytest.raises(ConfigError, match="no template geometry"):
        evaluate_members(members, ellipsoids, [0], device, progress=False, keep=0, refine_spectral=0.2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # radius 0 alone: nothing to warn about
        assert select_refinement(members, ellipsoids, [1], [0], device, progress=False) == (1, 1, 0.0, None)


def test_a_run_stores_its_template_geometry_and_radius_and_predict_applies_them(ellipsoid_faust_root, tmp_path):
    config = faust_run_config(
        ellipsoid_faust_root, 642, PATCH, eval={"refine_rings": [0, 1], "refine_spectral": [0, 0.2]}
    )
    metrics = train(config, tmp_path / "run", progress=False)
    best = load_checkpoint(tmp_path / "run" / "best.pt")
    first = ellipsoid(noise=0.01, seed=0)
    assert best["template_vertices"].dtype == torch.float32 and best["template_vertices"].shape == (642, 3)
    np.testing.assert_array_equal(best["template_faces"].numpy(), first.faces)
    assert sorted(metrics["refine_choice"]["spectral_accuracy"]) == ["0", "0.2"]
    assert best["refine_spectral"] == metrics["refine_choice"]["spectral"] == metrics["refine_spectral"]
    # predict refines globally on request (and as the run chose by default); a checkpoint without the
    # template geometry says why it cannot.
    surface = ellipsoid(noise=0.01, seed=3)
    plain = predict(tmp_path / "run", surface, refine_rings=0, refine_spectral=0)
    refined = predict(tmp_path / "run", surface, refine_rings=0, refine_spectral=0.2)
    assert refined.shape == plain.shape == (642,)
    torch.save({**best, "template_vertices": None}, tmp_path / "old.pt")
    with pytest.raises(ValueError, match="no template geometry"):
        predict(tmp_path / "old.pt", surface, refine_spectral=0.2)
