"""Generated human bodies (zernet.data.bodies): shared topology, part labels, seeds, layouts the loaders read.

Tiny coarse bodies (369 vertices) keep this to seconds once anny's own model cache exists. Tests that need
anny are skipped without it; the message naming the extra is tested either way.
"""

import importlib.util
import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

from zernet.cli import main
from zernet.data import DatasetError
from zernet.data.bodies import (
    MISSING_EXTRA_MESSAGE,
    BodyGenerator,
    generate_bodies,
    part_of_bone,
    write_bodies,
)
from zernet.data.bodies.pose import JOINTS, bone_rotations, rotation_matrix
from zernet.data.faust import load_faust
from zernet.data.options import LoaderOptions
from zernet.data.segmentation import HUMAN_PART_NAMES, load_segmentation, read_labels
from zernet.geometry import Surface, load_surface, validate_surface
from zernet.operators import PatchConfig

COARSE = "coarse-369"
CONFIGS = [PatchConfig(r0=20.0, n_samples=800, patch_size=20, n_max=2)]


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    if importlib.util.find_spec("anny") is None:
        pytest.skip("needs the bodies extra (anny)")
    return tmp_path_factory.mktemp("bodies-cache")


@pytest.fixture(scope="module")
def varied(cache):
    return generate_bodies(count=6, seed=0, topology=COARSE, poses="varied", n_test=2, cache_dir=cache)


def test_bodies_share_one_topology_and_correspondence_is_the_vertex_index(varied):
    assert [body.split for body in varied] == ["train"] * 4 + ["test"] * 2
    for body in varied:
        assert body.vertices.shape == (369, 3)
        np.testing.assert_array_equal(body.faces, varied[0].faces)
        np.testing.assert_array_equal(body.correspondence, np.arange(369))
        assert np.isfinite(body.vertices).all()
    # Same connectivity, different geometry: the poses and phenotypes do move the vertices.
    assert np.abs(varied[0].vertices - varied[1].vertices).max() > 0.05


def test_every_body_has_all_eight_parts(varied):
    for body in varied:
        assert set(np.unique(body.parts)) == set(range(len(HUMAN_PART_NAMES))), body.name


def test_parts_sit_where_they_belong(varied):
    """Head on top, feet at the bottom (y up), whatever the pose."""
    for body in varied:
        height = {part: body.vertices[body.parts == part, 1].mean() for part in range(8)}
        assert height[0] == max(height.values()) and height[7] == min(height.values()), body.name
        assert height[5] > height[6] > height[7]  # upper leg above lower leg above foot


def test_left_and_right_have_equal_counts_on_the_rest_pose(cache):
    generator = BodyGenerator(COARSE, "rest", seed=0, cache_dir=cache)
    topology = generator.topology()
    body = generator.body(0)
    for part in range(2, 8):  # the limb parts
        left = int(((topology.parts == part) & (topology.sides == 1)).sum())
        right = int(((topology.parts == part) & (topology.sides == -1)).sum())
        assert left > 0 and abs(left - right) <= 0.05 * max(left, right), (HUMAN_PART_NAMES[part], left, right)
    # The left side (+x) mirrors the right one: mean x of each side's limb vertices are opposite.
    limbs = topology.parts >= 2
    left_x = body.vertices[limbs & (topology.sides == 1), 0].mean()
    right_x = body.vertices[limbs & (topology.sides == -1), 0].mean()
    assert left_x > 0.1 and right_x == pytest.approx(-left_x, rel=0.05)


def _mirror_partner(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """(index of each vertex's mirror image x -> -x, largest distance to it relative to the body's height)."""
    distance, partner = cKDTree(vertices).query(vertices * [-1.0, 1.0, 1.0])
    return partner, float(distance.max() / np.ptp(vertices[:, 1]))


def test_a_mirror_symmetric_pose_gives_a_mirror_symmetric_body_with_mirrored_labels(cache):
    """Same angles on both sides (and none on the midline): the body is its own mirror image, and each
    vertex's mirror partner has the same part on the other side — the pose code turns left and right alike
    (the twist of the upper arm included)."""
    generator = BodyGenerator(COARSE, "varied", seed=0, cache_dir=cache)
    topology = generator.topology()
    symmetric = {}
    for joint in JOINTS:  # the wide mode's own joints (no varied range) turned by 30 degrees
        if joint.sides() == ("L", "R"):
            low, high = joint.varied or (0.0, 30.0 / 0.7)
            symmetric.update({joint.key(side): low + 0.7 * (high - low) for side in ("L", "R")})
    phenotype, _ = generator.draws(0)
    posed = topology.place(generator.pose_model(phenotype, symmetric))  # anny's frame: left is +x
    rest = topology.place(generator.pose_model(phenotype, {}))
    assert np.abs(posed - rest).max() > 0.05  # the pose does move the limbs
    partner, gap = _mirror_partner(posed)
    assert gap < 1e-3
    np.testing.assert_array_equal(partner[partner], np.arange(len(partner)))  # an involution
    np.testing.assert_array_equal(topology.parts[partner], topology.parts)
    np.testing.assert_array_equal(topology.sides[partner], -topology.sides)
    # An asymmetric pose (one elbow only) breaks the symmetry: the test can fail.
    one_elbow = {key: value for key, value in symmetric.items() if key != "elbow|lowerarm01.R"}
    assert _mirror_partner(topology.place(generator.pose_model(phenotype, one_elbow)))[1] > 0.01


def test_toward_rotations_move_the_far_end_toward_the_direction():
    """Analytic: a segment along +x (the left upper arm) raised by 30 degrees toward up (+z)."""
    bones = ["upperarm01.L", "lowerarm01.L", "upperarm01.R", "lowerarm01.R"]
    heads = np.array([[0.2, 0.0, 1.4], [0.5, 0.0, 1.4], [-0.2, 0.0, 1.4], [-0.5, 0.0, 1.4]])
    deltas = bone_rotations(
        bones,
        heads,
        {"shoulder raise|upperarm01.L": 30.0, "shoulder raise|upperarm01.R": 30.0, "hip spread|upperleg01.L": 0.0},
    )
    assert set(deltas) == {"upperarm01.L", "upperarm01.R"}
    for bone, sign in (("upperarm01.L", 1.0), ("upperarm01.R", -1.0)):
        turned = deltas[bone][:3, :3] @ np.array([sign, 0.0, 0.0])
        np.testing.assert_allclose(turned, [sign * np.cos(np.radians(30)), 0.0, np.sin(np.radians(30))], atol=1e-12)
    rotation = rotation_matrix(np.array([0.0, 0.0, 1.0]), 90.0)
    np.testing.assert_allclose(rotation[:3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(rotation[:3, :3] @ rotation[:3, :3].T, np.eye(3), atol=1e-12)


def test_same_seed_same_bodies_other_seed_other_bodies(cache, tmp_path, varied):
    again = generate_bodies(count=6, seed=0, topology=COARSE, poses="varied", n_test=2, cache_dir=tmp_path)
    for first, second in zip(varied, again):  # a fresh cache: generated again, identically
        np.testing.assert_allclose(first.vertices, second.vertices, atol=1e-12)
        assert first.phenotype == second.phenotype and first.pose == second.pose
    other = generate_bodies(count=6, seed=1, topology=COARSE, poses="varied", n_test=2, cache_dir=cache)
    for first, second in zip(varied, other):
        assert np.abs(first.vertices - second.vertices).max() > 0.01
        assert first.phenotype != second.phenotype


def test_test_bodies_are_not_training_bodies(cache):
    generator = BodyGenerator(COARSE, "varied", seed=0, cache_dir=cache)
    train = [generator.draws(i, "train") for i in range(30)]
    test = [generator.draws(i, "test") for i in range(10)]
    for phenotype, pose in test:
        assert all(phenotype != p and pose != q for p, q in train)
    # Body i does not depend on how many bodies are asked for.
    np.testing.assert_array_equal(
        generate_bodies(3, 0, COARSE, "varied", 1, cache)[1].vertices,
        generate_bodies(6, 0, COARSE, "varied", 2, cache)[1].vertices,
    )


def test_missing_anny_names_the_extra(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "anny", None)  # "import anny" now raises ImportError
    generator = BodyGenerator(COARSE, "varied", seed=0, cache_dir=tmp_path)  # empty cache: needs the model
    with pytest.raises(DatasetError, match=r"optional dependency anny: pip install 'zernet\[bodies\]'"):
        generator.body(0)
    assert "zernet[bodies]" in MISSING_EXTRA_MESSAGE


def test_missing_anny_is_one_line_naming_the_extra_from_the_command(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "anny", None)
    assert (
        main(
            [
                "bodies",
                str(tmp_path / "out"),
                "--count",
                "2",
                "--n-test",
                "1",
                "--topology",
                COARSE,
                "--cache-dir",
                str(tmp_path / "cache"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "pip install 'zernet[bodies]'" in err and "Traceback" not in err


def test_bad_arguments_are_named(cache):
    with pytest.raises(DatasetError, match="unknown body topology 'faust2'"):
        BodyGenerator("faust2")
    with pytest.raises(DatasetError, match="unknown pose mode"):
        BodyGenerator(COARSE, poses="dance")
    with pytest.raises(DatasetError, match="n_test"):
        generate_bodies(count=3, n_test=3, topology=COARSE, cache_dir=cache)
    with pytest.raises(ValueError, match="tail"):
        part_of_bone("tail")


def test_faust_topology_is_a_valid_faust_sized_surface(cache):
    generator = BodyGenerator("faust", "varied", seed=0, cache_dir=cache)
    topology = generator.topology()
    assert topology.n_vertices == 6890 and topology.faces.shape == (13776, 3)
    np.testing.assert_allclose(topology.weights.sum(1), 1.0)
    assert (topology.weights >= 0).all()
    body = generator.body(0)
    surface = validate_surface(Surface(body.vertices, body.faces))
    # A closed surface: every edge has exactly two faces.
    edges = np.sort(body.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all() and surface.n_vertices == 6890
    assert set(np.unique(body.parts)) == set(range(8))


def test_written_bodies_load_with_the_existing_loaders(cache, tmp_path):
    layout = write_bodies(
        tmp_path / "bodies", count=6, seed=0, topology=COARSE, n_test=2, cache_dir=cache, progress=False
    )
    assert layout.readme.is_file() and layout.n_vertices == 369
    assert layout.class_names.read_text().split("\n")[:8] == list(HUMAN_PART_NAMES)
    body = generate_bodies(count=6, seed=0, topology=COARSE, n_test=2, cache_dir=cache)[4]
    mesh = load_surface(layout.meshes / "test" / "body_004.ply")
    np.testing.assert_allclose(mesh.vertices, body.vertices, atol=1e-6)
    np.testing.assert_array_equal(read_labels(layout.labels / "test" / "body_004.txt"), body.parts)

    options = LoaderOptions(patch_configs=CONFIGS, cache_dir=tmp_path / "cache", workers=0, progress=False, n_val=1)
    segmentation = load_segmentation(layout.meshes, layout.labels, options=options)
    assert segmentation.num_classes == 8 and len(segmentation) == 6
    assert sorted(segmentation.names[i] for i in segmentation.splits["test"]) == ["test/body_004", "test/body_005"]
    index = segmentation.names.index("test/body_004")
    np.testing.assert_array_equal(segmentation[index].target, body.parts)

    correspondence = load_faust(
        layout.registrations.parent.parent, n_vertices=369, train_indices=range(4), test_indices=[4, 5], options=options
    )
    assert correspondence.correspondence and correspondence.num_classes == 369
    np.testing.assert_array_equal(correspondence[5].target, np.arange(369))
