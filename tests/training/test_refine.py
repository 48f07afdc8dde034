"""Refinement of a correspondence and of a segmentation: the rings, what the neighbours' agreement does to
a map, what averaging the unsure vertices does to parts, and how evaluation scores, reports and chooses it."""

import json

import numpy as np
import pytest
import torch
import trimesh
from meshes import icosphere, write_faust_layout
from tiny_configs import faust_run_config

from zernet.cli import main
from zernet.data import LoaderOptions, load_faust
from zernet.inference import load_checkpoint, predict
from zernet.inference.refine import (
    AGREEMENT_FLOOR,
    SEGMENTATION_CONFIDENCE,
    refine_correspondence,
    refine_segmentation,
    ring_average,
    ring_reach,
)
from zernet.operators import PatchConfig
from zernet.training import evaluate, train
from zernet.training.config import ConfigError, EvalSection
from zernet.training.evaluation import evaluate_members, select_refine_rings, select_refinement, summary_line


def test_ring_average_is_the_mean_over_the_vertices_within_so_many_edges(tetrahedron_surface, sphere_surface):
    # On a tetrahedron every vertex neighbours every other: one ring averages all four equally.
    np.testing.assert_allclose(ring_average(tetrahedron_surface.faces, 4, 1).toarray(), np.full((4, 4), 0.25))
    np.testing.assert_array_equal(ring_average(tetrahedron_surface.faces, 4, 0).toarray(), np.eye(4))
    # On the icosphere (valence 5 or 6) one ring holds the vertex and its v neighbours; two rings add the
    # vertices two edges away: 1 + 5 + 10 around a valence-5 vertex, 1 + 6 + 12 around most valence-6 ones.
    faces, n = sphere_surface.faces, sphere_surface.n_vertices
    valence = np.bincount(faces.ravel(), minlength=n)  # a closed mesh has as many faces as edges at a vertex
    assert set(np.unique(valence)) == {5, 6}
    for rings, expected in ((1, valence + 1), (2, None)):
        average = ring_average(faces, n, rings)
        np.testing.assert_allclose(np.asarray(average.sum(axis=1)).ravel(), 1.0, rtol=1e-6)
        np.testing.assert_allclose(1.0 / average.diagonal(), average.getnnz(axis=1), rtol=1e-5)  # equal weights
        if expected is not None:
            np.testing.assert_array_equal(average.getnnz(axis=1), expected)
    two_rings = ring_average(faces, n, 2).getnnz(axis=1)
    assert set(two_rings[valence == 5]) == {16} and np.median(two_rings[valence == 6]) == 19


def test_ring_average_refuses_bad_faces_and_radii(tetrahedron_surface):
    with pytest.raises(ValueError, match="outside"):
        ring_average(tetrahedron_surface.faces, 3, 1)
    with pytest.raises(ValueError, match="rings"):
        ring_average(tetrahedron_surface.faces, 4, -1)


def _rings_by_search(faces: np.ndarray, n: int, rings: int) -> list[set[int]]:
    """The vertices at most ``rings`` edges from each vertex, by breadth-first search (not by matrices)."""
    neighbours = [set() for _ in range(n)]
    for a, b, c in faces:
        neighbours[a] |= {b, c}
        neighbours[b] |= {a, c}
        neighbours[c] |= {a, b}
    reached = []
    for start in range(n):
        seen, frontier = {start}, {start}
        for _ in range(rings):
            frontier = {w for v in frontier for w in neighbours[v]} - seen
            seen |= frontier
        reached.append(seen)
    return reached


def test_the_refined_score_is_the_neighbours_agreement_written_out():
    """S(i, j) = log(P(i, j) + ε) + Σ_{k ∈ ring(i), k ≠ i} log(Σ_{l ∈ ring(j)} P(k, l) + ε), softmax over j,
    computed vertex by vertex from rings found by breadth-first search; the shape and the template differ in
    size (a new surface against a run's template)."""
    shape, template = icosphere(1, noise=0.05, seed=1), icosphere(2)
    n, m = shape.n_vertices, template.n_vertices
    probabilities = np.random.default_rng(2).dirichlet(np.full(m, 0.2), size=n)
    floor = AGREEMENT_FLOOR / m
    for rings in (1, 2):
        shape_rings, template_rings = (
            _rings_by_search(shape.faces, n, rings),
            _rings_by_search(template.faces, m, rings),
        )
        np.testing.assert_array_equal(
            ring_reach(shape.faces, n, rings).toarray(),
            np.array([[j in shape_rings[i] for j in range(n)] for i in range(n)], dtype=np.float32),
        )
        expected = np.empty((n, m))
        for i in range(n):
            for j in range(m):
                columns = sorted(template_rings[j])
                expected[i, j] = np.log(probabilities[i, j] + floor) + sum(
                    np.log(probabilities[k, columns].sum() + floor) for k in shape_rings[i] - {i}
                )
        expected = np.exp(expected - expected.max(axis=1, keepdims=True))
        expected /= expected.sum(axis=1, keepdims=True)
        refined = refine_correspondence(probabilities.astype(np.float32), shape.faces, template.faces, rings)
        np.testing.assert_allclose(refined, expected, rtol=2e-4, atol=1e-7)


def test_a_true_map_stays_and_a_wrong_vertex_takes_its_neighbourhood_answer(sphere_surface):
    faces, n = sphere_surface.faces, sphere_surface.n_vertices
    identity = np.eye(n, dtype=np.float32)
    # The identity map is its own refinement: every neighbour of i gives the ring of i all its mass, and any
    # other j at least one neighbour short of it.
    for rings in (1, 2, 3):
        np.testing.assert_array_equal(refine_correspondence(identity, faces, faces, rings).argmax(1), np.arange(n))
    # One vertex sent to the far side of the sphere comes back; every other vertex stays.
    wrong = identity.copy()
    far = int(np.argmin(sphere_surface.vertices @ sphere_surface.vertices[7]))
    wrong[7] = 0.0
    wrong[7, far] = 1.0
    np.testing.assert_array_equal(wrong.argmax(1)[7], far)
    np.testing.assert_array_equal(refine_correspondence(wrong, faces, faces, 1).argmax(1), np.arange(n))


def _blob_sent_far(surface, centre: int) -> tuple[np.ndarray, list[int]]:
    """The identity map (one-hot rows) but ``centre`` and its ring, each sent to its own vertex on the far
    side, at least three edges from the others (so no vertex is near two wrong answers: they never agree).
    The centre is sure of its wrong answer; its neighbours keep 1 % on their truth (a tie-breaker among the
    vertices next to it, no more)."""
    faces, n = surface.faces, surface.n_vertices
    blob = sorted(_rings_by_search(faces, n, 1)[centre])
    reach = ring_reach(faces, n, 2).toarray() > 0
    far, taken = [], np.zeros(n, dtype=bool)
    for v in np.argsort(surface.vertices @ surface.vertices[centre]):
        if not taken[v]:
            far.append(int(v))
            taken |= reach[v]
    probabilities = np.eye(n, dtype=np.float32)
    for i, target in zip(blob, far):
        probabilities[i] = 0.0
        probabilities[i, target] = 1.0 if i == centre else 0.99
        probabilities[i, i] = 0.0 if i == centre else 0.01
    return probabilities, blob


def test_a_second_pass_reaches_a_vertex_whose_whole_ring_is_wrong(sphere_surface):
    # Every neighbour of the centre is wrong, so one pass over one ring keeps it wrong (nobody agrees with
    # its truth) while it brings each neighbour back (their other neighbours agree); the second pass then
    # asks the repaired neighbours.
    faces, n = sphere_surface.faces, sphere_surface.n_vertices
    probabilities, blob = _blob_sent_far(sphere_surface, 0)
    assert len(blob) >= 6 and np.sum(probabilities.argmax(1) != np.arange(n)) == len(blob)
    once = refine_correspondence(probabilities, faces, faces, 1).argmax(1)
    assert once[0] != 0 and np.array_equal(np.flatnonzero(once != np.arange(n)), [0])
    twice = refine_correspondence(probabilities, faces, faces, 1, passes=2)
    np.testing.assert_array_equal(twice.argmax(1), np.arange(n))
    step = refine_correspondence(probabilities, faces, faces, 1)
    np.testing.assert_allclose(twice, refine_correspondence(step, faces, faces, 1), rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(refine_correspondence(probabilities, faces, faces, 0, passes=3), probabilities)
    with pytest.raises(ValueError, match="passes"):
        refine_correspondence(probabilities, faces, faces, 1, passes=0)


def test_every_neighbour_is_asked_where_an_average_lets_the_sure_ones_outvote(sphere_surface):
    """Vertex 0 is unsure between its true vertex and a far one; one neighbour sends all its mass next to the
    far one, the others put a modest share on the truth. The average follows the one sure neighbour; the
    agreement follows the many."""
    faces, vertices, n = sphere_surface.faces, sphere_surface.vertices, sphere_surface.n_vertices
    rings = _rings_by_search(faces, n, 1)
    far = int(np.argmin(vertices @ vertices[0]))
    near_far = sorted(rings[far] - {far})[0]
    probabilities = np.full((n, n), 0.2 / n, dtype=np.float32)
    probabilities[np.arange(n), np.arange(n)] += 0.8
    probabilities[0] = 0.2 / n
    probabilities[0, [0, far]] += [0.4, 0.4]
    loud, *quiet = sorted(rings[0] - {0})
    probabilities[loud] = 0.0
    probabilities[loud, near_far] = 1.0
    for k in quiet:
        probabilities[k] = 0.8 / n
        probabilities[k, k] += 0.2
    average = ring_average(faces, n, 1)
    averaged = (average @ (average @ probabilities).T).T
    assert averaged[0].argmax() == far  # the loud neighbour's whole mass outweighs the quiet ones' shares
    assert refine_correspondence(probabilities, faces, faces, 1).argmax(axis=1)[0] == 0


def test_refinement_keeps_rows_normalised_and_zero_rings_change_nothing(sphere_surface):
    rng = np.random.default_rng(0)
    n = sphere_surface.n_vertices
    probabilities = rng.random((n, n)).astype(np.float32)
    probabilities /= probabilities.sum(axis=1, keepdims=True)
    np.testing.assert_array_equal(
        refine_correspondence(probabilities, sphere_surface.faces, sphere_surface.faces, 0), probabilities
    )
    refined = refine_correspondence(probabilities, sphere_surface.faces, sphere_surface.faces, 3)
    np.testing.assert_allclose(refined.sum(axis=1), 1.0, rtol=1e-5)
    with pytest.raises(ValueError, match="rings"):
        refine_correspondence(probabilities, sphere_surface.faces, sphere_surface.faces, -1)


def test_refinement_follows_a_reindexing_of_either_mesh():
    """Renumbering the shape's vertices permutes the rows; renumbering the template's permutes the columns."""
    shape, template = icosphere(1, noise=0.05, seed=1), icosphere(1)
    n, m = shape.n_vertices, template.n_vertices
    rng = np.random.default_rng(3)
    probabilities = rng.dirichlet(np.full(m, 0.1), size=n).astype(np.float32)
    refined = refine_correspondence(probabilities, shape.faces, template.faces, 2)
    rows, cols = rng.permutation(n), rng.permutation(m)
    rows_inverse, cols_inverse = np.argsort(rows), np.argsort(cols)
    # New vertex a of the shape is old vertex rows[a]: its faces use the inverse permutation.
    renumbered = refine_correspondence(
        probabilities[rows][:, cols], rows_inverse[shape.faces], cols_inverse[template.faces], 2
    )
    np.testing.assert_allclose(renumbered, refined[rows][:, cols], rtol=1e-5, atol=1e-7)


def _hemispheres(surface) -> tuple[np.ndarray, np.ndarray]:
    """(N,) parts of a sphere (0 below the equator, 1 above) and sure (N, 2) probabilities of them."""
    parts = (surface.vertices[:, 2] > 0).astype(np.int64)
    probabilities = np.where(parts[:, None] == np.arange(2), 0.99, 0.01).astype(np.float32)
    return parts, probabilities


def test_segmentation_refinement_corrects_only_the_unsure_vertices(sphere_surface):
    faces = sphere_surface.faces
    parts, probabilities = _hemispheres(sphere_surface)
    # Far from the equator: one vertex wrong and unsure, one wrong and sure.
    top = np.flatnonzero(sphere_surface.vertices[:, 2] > 0.8)
    unsure, sure = int(top[0]), int(top[1])
    probabilities[unsure] = [0.6, 0.4]
    probabilities[sure] = [(1 + SEGMENTATION_CONFIDENCE) / 2, (1 - SEGMENTATION_CONFIDENCE) / 2]
    for rings in (1, 2):
        refined = refine_segmentation(probabilities, faces, rings)
        assert refined.argmax(1)[unsure] == parts[unsure] == 1  # its neighbourhood's answer
        assert refined.argmax(1)[sure] == 0  # a sure answer is the network's, right or wrong
        others = np.setdiff1d(np.arange(len(parts)), [unsure])
        np.testing.assert_array_equal(refined[others], probabilities[others])
        np.testing.assert_allclose(refined.sum(axis=1), 1.0, rtol=1e-5)
    np.testing.assert_array_equal(refine_segmentation(probabilities, faces, 0), probabilities)
    # A tensor is refined where it is, to the same numbers.
    tensor = refine_segmentation(torch.from_numpy(probabilities), faces, 2)
    assert isinstance(tensor, torch.Tensor)
    np.testing.assert_allclose(tensor.numpy(), refine_segmentation(probabilities, faces, 2), rtol=1e-6)
    with pytest.raises(ValueError, match="rings"):
        refine_segmentation(probabilities, faces, -1)


def test_segmentation_refinement_follows_a_reindexing_of_the_vertices():
    shape = icosphere(2, noise=0.05, seed=2)
    rng = np.random.default_rng(4)
    probabilities = rng.dirichlet(np.full(4, 0.5), size=shape.n_vertices).astype(np.float32)
    refined = refine_segmentation(probabilities, shape.faces, 2)
    assert (refined != probabilities).any(axis=1).sum() > 0
    order = rng.permutation(shape.n_vertices)
    renumbered = refine_segmentation(probabilities[order], np.argsort(order)[shape.faces], 2)
    np.testing.assert_allclose(renumbered, refined[order], rtol=1e-5, atol=1e-7)


# ------------------------------------------------------------------------------- evaluation with refinement
class _KnownMap(torch.nn.Module):
    """Predicts the identity map except that a few vertices point at the far side of the sphere."""

    def __init__(self, vertices: np.ndarray, wrong: list[int]):
        super().__init__()
        logits = torch.full((len(vertices), len(vertices)), -10.0)
        logits.fill_diagonal_(10.0)
        for i in wrong:
            logits[i, i] = 0.0
            logits[i, int(np.argmin(vertices @ vertices[i]))] = 10.0
        self.register_buffer("logits", logits)

    def forward(self, features, geometry):
        return self.logits


PATCH = {"r0": 1.2, "n_samples": 1500, "patch_size": 30, "n_max": 2}


@pytest.fixture(scope="module")
def faust_root(tmp_path_factory):
    """Five noisy icospheres sharing one connectivity, in FAUST's layout."""
    root = tmp_path_factory.mktemp("faust")
    write_faust_layout(root, [icosphere(2, noise=0.02, seed=i) for i in range(5)])
    return root


@pytest.fixture(scope="module")
def spheres_in_faust_layout(faust_root):
    """3 train (1 of them validation), 2 test."""
    options = LoaderOptions(
        patch_configs=[PatchConfig(**PATCH)], cache_dir=faust_root / "cache", n_val=1, workers=0, progress=False
    )
    return load_faust(
        faust_root, train_indices=range(3), test_indices=[3, 4], n_vertices=None, area=100.0, options=options
    )


def test_evaluation_scores_the_refined_map_and_keeps_the_unrefined_beside(spheres_in_faust_layout):
    dataset = spheres_in_faust_layout
    vertices = dataset[0].surface.vertices - dataset[0].surface.vertices.mean(axis=0)
    members = [
        (
            _KnownMap(vertices, wrong=[5, 40, 100]),
            {"task": "classification", "correspondence": True, "num_classes": 162},
        )
    ]
    test, device = dataset.splits["test"], torch.device("cpu")
    raw, _ = evaluate_members(members, dataset, test, device, progress=False, keep=0)
    assert raw["refine_rings"] == 0 and "unrefined_summary" not in raw
    assert raw["summary"]["accuracy"] == pytest.approx(1 - 3 / 162)
    refined, _ = evaluate_members(members, dataset, test, device, progress=False, keep=0, refine_rings=1)
    assert refined["summary"]["accuracy"] == 1.0 and refined["summary"]["mean_geodesic_error"] == 0.0
    assert refined["unrefined_summary"] == raw["summary"]
    assert "refined over 1 rings; unrefined accuracy 0.9815" in summary_line(refined)
    # Chosen on the validation split: the fewest rings among the best.
    rings, choice = select_refine_rings(members, dataset, [3, 0, 1], device, progress=False)
    assert rings == 1 and choice["split"] == "val"
    assert choice["accuracy"] == {"0": pytest.approx(1 - 3 / 162), "1": 1.0, "3": 1.0}
    assert select_refine_rings(members, dataset, [2], device, progress=False) == (2, None)
    with pytest.raises(ConfigError, match="integers >= 0"):
        select_refine_rings(members, dataset, [-1], device, progress=False)


class _FixedScores(torch.nn.Module):
    """Predicts the given probabilities (as logits) for every shape."""

    def __init__(self, probabilities: np.ndarray):
        super().__init__()
        self.register_buffer("logits", torch.log(torch.from_numpy(probabilities) + 1e-6))

    def forward(self, features, geometry):
        return self.logits


def test_passes_are_chosen_with_the_rings_and_scored(spheres_in_faust_layout):
    dataset = spheres_in_faust_layout
    probabilities, blob = _blob_sent_far(icosphere(2), 0)
    header = {"task": "classification", "correspondence": True, "num_classes": 162}
    members, device = [(_FixedScores(probabilities), header)], torch.device("cpu")
    rings, passes, radius, choice = select_refinement(members, dataset, [0, 1], [0.0], device, False, [1, 2, 3])
    assert (rings, passes, radius) == (1, 2, 0.0) and choice["passes"] == 2
    assert choice["accuracy"] == {
        "0x1": pytest.approx(1 - len(blob) / 162),
        "1x1": pytest.approx(1 - 1 / 162),
        "1x2": 1.0,
        "1x3": 1.0,
    }
    test = dataset.splits["test"]
    metrics, _ = evaluate_members(members, dataset, test, device, False, keep=0, refine_rings=1, refine_passes=2)
    assert metrics["summary"]["accuracy"] == 1.0 and metrics["refine_passes"] == 2
    assert "refined over 1 rings x 2 passes; unrefined accuracy" in summary_line(metrics)
    # One candidate of each: nothing is chosen, nothing is read.
    assert select_refinement(members, dataset, [1], [0.0], device, False, [2]) == (1, 2, 0.0, None)
    with pytest.raises(ConfigError, match="integers >= 1"):
        select_refinement(members, dataset, [1], [0.0], device, False, [0])


def test_refinement_is_chosen_for_segmentation_ignored_by_regression_and_needs_a_validation_split(
    spheres_in_faust_layout,
):
    dataset = spheres_in_faust_layout
    # Sure answers (every vertex its own class): no ring changes them, so the fewest rings are chosen.
    segmentation = [(_KnownMap(dataset[0].surface.vertices, wrong=[]), {"task": "classification", "num_classes": 162})]
    rings, choice = select_refine_rings(segmentation, dataset, [0, 4], torch.device("cpu"), progress=False)
    assert rings == 0 and choice["split"] == "val" and choice["accuracy"] == {"0": 1.0, "4": 1.0}
    regression = [(segmentation[0][0], {"task": "regression"})]
    assert select_refine_rings(regression, dataset, [0, 4], torch.device("cpu"), progress=False) == (0, None)
    correspondence = [(segmentation[0][0], {"task": "classification", "correspondence": True, "num_classes": 162})]
    no_validation = dataset.subset(dataset.splits["train"] + dataset.splits["test"])
    no_validation.splits.pop("val", None)
    with pytest.raises(ConfigError, match="no validation split"):
        select_refine_rings(correspondence, no_validation, [0, 4], torch.device("cpu"), progress=False)


def test_the_eval_section_takes_a_number_or_candidates():
    assert EvalSection(refine_rings=2).refine_rings == [2]
    assert EvalSection(refine_rings=[0, 1, 2]).refine_rings == [0, 1, 2]
    assert EvalSection().refine_rings == [0]
    assert EvalSection().refine_passes == [1] and EvalSection(refine_passes=3).refine_passes == [3]
    for bad in ([], [0], "two"):
        with pytest.raises(ConfigError, match="eval.refine_passes"):
            EvalSection(refine_passes=bad)
    for bad in ([], [-1], "two"):
        with pytest.raises(ConfigError, match="eval.refine_rings"):
            EvalSection(refine_rings=bad)


def test_a_trained_run_stores_its_template_and_choice_and_predict_applies_them(faust_root, tmp_path):
    config = faust_run_config(faust_root, 162, PATCH, eval={"refine_rings": [0, 1, 2]})
    metrics = train(config, tmp_path / "run", progress=False)
    best = load_checkpoint(tmp_path / "run" / "best.pt")
    assert best["refine_rings"] == metrics["refine_choice"]["rings"] == metrics["refine_rings"]
    assert sorted(metrics["refine_choice"]["accuracy"]) == ["0", "1", "2"]
    surface = icosphere(2, noise=0.02, seed=3)
    np.testing.assert_array_equal(best["template_faces"].numpy(), surface.faces)
    # predict refines a new surface as the run chose; any other radius on request, 0 turns it off.
    _, raw = predict(tmp_path / "run", surface, probabilities=True, refine_rings=0)
    for rings in (1, 2):
        expected = refine_correspondence(raw, surface.faces, surface.faces, rings).argmax(axis=1)
        np.testing.assert_array_equal(predict(tmp_path / "run", surface, refine_rings=rings), expected)
    expected = refine_correspondence(raw, surface.faces, surface.faces, 1, passes=2).argmax(axis=1)
    np.testing.assert_array_equal(predict(tmp_path / "run", surface, refine_rings=1, refine_passes=2), expected)
    np.testing.assert_array_equal(
        predict(tmp_path / "run", surface), predict(tmp_path / "run", surface, refine_rings=best["refine_rings"])
    )
    # A checkpoint without a template (written before refinement existed) says so.
    torch.save({**best, "template_faces": None}, tmp_path / "changed.pt")
    with pytest.raises(ValueError, match="stores no template mesh"):
        predict(tmp_path / "changed.pt", surface, refine_rings=1)
    # evaluate chooses again on the validation split, with the same outcome as training.
    again = evaluate(tmp_path / "run", progress=False)
    assert again["refine_choice"] == metrics["refine_choice"] and again["summary"] == metrics["summary"]
    # The command line: evaluate and predict take a radius of their own.
    mesh = tmp_path / "new.ply"
    trimesh.Trimesh(surface.vertices, surface.faces, process=False).export(mesh)
    assert (
        main(
            [
                "evaluate",
                str(tmp_path / "run"),
                "--refine-rings",
                "2",
                "--no-progress",
                "--out",
                str(tmp_path / "two.json"),
            ]
        )
        == 0
    )
    two = json.loads((tmp_path / "two.json").read_text())
    assert two["refine_rings"] == 2 and "refine_choice" not in two
    assert two["unrefined_summary"] == again.get("unrefined_summary", again["summary"])
    assert (
        main(["predict", str(tmp_path / "run"), str(mesh), "--refine-rings", "2", "--out", str(tmp_path / "pred")]) == 0
    )
    np.testing.assert_array_equal(
        np.load(tmp_path / "pred.npy"), refine_correspondence(raw, surface.faces, surface.faces, 2).argmax(axis=1)
    )
