"""The ``wide`` pose mode (poses and shapes people take in scans) and the closed mouth and eye sockets.

The draws are checked without anny; the posed bodies on the tiny coarse topology and the closed cavities
on the full template (built once per module) need the bodies extra and are skipped without it.
"""

import importlib.util

import numpy as np
import pytest
import trimesh

from zernet.data.bodies import BodyGenerator, generate_bodies
from zernet.data.bodies.pose import (
    ARM_STYLES,
    JOINTS,
    LEG_STYLES,
    WIDE_PHENOTYPE_RANGES,
    WIDE_TRUNK_RANGES,
    draw_phenotype,
    draw_pose,
)
from zernet.data.bodies.topology import boundary_loops, close_openings
from zernet.geometry import Surface, validate_surface

COARSE = "coarse-369"


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    if importlib.util.find_spec("anny") is None:
        pytest.skip("needs the bodies extra (anny)")
    return tmp_path_factory.mktemp("wide-cache")


def _group(key: str) -> str:
    return key.split("|")[0]


def test_older_modes_draw_what_they_drew_before_wide_existed():
    """Body 3 of seed 0's stream, values recorded from the generator before the wide mode was added."""
    rng = np.random.default_rng(np.random.SeedSequence([0, 0, 3]))
    phenotype, pose = draw_phenotype(rng), draw_pose(rng, "varied")
    assert phenotype["weight"] == pytest.approx(0.8732588329974255, abs=1e-15)
    assert phenotype["proportions"] == pytest.approx(0.6954699790177852, abs=1e-15)
    assert len(pose) == 23  # the 13 groups of varied, 10 of them on both sides; none of wide's own joints
    assert pose["shoulder raise|upperarm01.L"] == pytest.approx(22.84979996703475, abs=1e-12)
    assert pose["knee|lowerleg01.R"] == pytest.approx(54.537771612280686, abs=1e-12)
    assert pose["ankle|foot.R"] == pytest.approx(11.260400051888968, abs=1e-12)


def test_wide_angles_lie_in_their_ranges_and_reach_the_new_poses():
    rng = np.random.default_rng(0)
    poses = [draw_pose(rng, "wide") for _ in range(400)]
    every_joint = {joint.key(side) for joint in JOINTS for side in joint.sides()}
    arm_low = {g: min(s[1][g][0] for s in ARM_STYLES.values() if g in s[1]) for g in ("shoulder raise", "elbow")}
    arm_high = {g: max(s[1][g][1] for s in ARM_STYLES.values() if g in s[1]) for g in ("shoulder raise", "elbow")}
    leg_high = max(style[1]["knee"][1] for style in LEG_STYLES.values())
    for pose in poses:
        assert set(pose) == every_joint
        for key, angle in pose.items():
            if _group(key) in WIDE_TRUNK_RANGES:
                low, high = WIDE_TRUNK_RANGES[_group(key)]
                assert low <= angle <= high, key
            if _group(key) in arm_low:
                assert arm_low[_group(key)] <= angle <= arm_high[_group(key)], key
            if _group(key) == "knee":
                assert 0.0 <= angle <= leg_high
    raises = np.array([pose["shoulder raise|upperarm01.L"] for pose in poses])
    knees = np.array([[pose["knee|lowerleg01.L"], pose["knee|lowerleg01.R"]] for pose in poses])
    # Arms overhead (beyond the 45 degrees of varied) in about a quarter of the arms, deep knee bends in
    # every bent or one-leg pose, and one-leg stands: one knee bent far, the other nearly straight.
    assert 0.15 < np.mean(raises > 70.0) < 0.35
    assert np.mean(knees.max(1) > 100.0) > 0.1
    assert np.any((knees.max(1) > 100.0) & (knees.min(1) < 20.0))
    # Crossed arms and hands behind the back turn the upper arm in; overhead turns it out.
    twists = np.array([pose["shoulder twist|upperarm01.R"] for pose in poses])
    assert twists.max() > 60.0 and twists.min() < -60.0


def test_wide_shapes_reach_the_model_limits_of_weight_and_muscle():
    rng = np.random.default_rng(1)
    drawn = [draw_phenotype(rng, WIDE_PHENOTYPE_RANGES) for _ in range(300)]
    for key in ("weight", "muscle"):
        values = np.array([phenotype[key] for phenotype in drawn])
        assert values.min() < 0.03 and values.max() > 0.97 and (values >= 0).all() and (values <= 1).all()


def test_overhead_arms_put_the_hands_above_the_head_and_a_twist_turns_the_forearm_in(cache):
    generator = BodyGenerator(COARSE, "wide", seed=0, cache_dir=cache)
    topology = generator.topology()
    phenotype, _ = generator.draws(0)
    hands, head = topology.parts == 4, topology.parts == 0
    low, high = ARM_STYLES["overhead"][1]["shoulder raise"]
    for raise_by, above in ((high, True), (0.0, False)):
        pose = {f"shoulder raise|upperarm01.{side}": raise_by for side in "LR"}
        vertices = topology.place(generator.pose_model(phenotype, pose))  # anny's frame: z up
        assert (vertices[hands, 2].max() > vertices[head, 2].max()) == above, raise_by
    # Elbows bent in front: a positive twist (crossed arms) brings the left hand toward the midline (x = 0).
    bent = {
        f"{group}|{bone}.{side}": angle
        for side in "LR"
        for group, bone, angle in (("shoulder swing", "upperarm01", 40.0), ("elbow", "lowerarm01", 100.0))
    }
    left_hand = hands & (topology.sides == 1)
    straight = topology.place(generator.pose_model(phenotype, bent))[left_hand, 0].mean()
    twisted = {**bent, **{f"shoulder twist|upperarm01.{side}": 60.0 for side in "LR"}}
    turned = topology.place(generator.pose_model(phenotype, twisted))[left_hand, 0].mean()
    assert turned < straight - 0.04


def test_wide_bodies_are_valid_and_reproducible(cache, tmp_path):
    bodies = generate_bodies(count=4, seed=0, topology=COARSE, poses="wide", n_test=1, cache_dir=cache)
    again = generate_bodies(count=4, seed=0, topology=COARSE, poses="wide", n_test=1, cache_dir=tmp_path)
    varied = generate_bodies(count=4, seed=0, topology=COARSE, poses="varied", n_test=1, cache_dir=cache)
    for body, same, other in zip(bodies, again, varied):
        assert np.isfinite(body.vertices).all()
        validate_surface(Surface(body.vertices, body.faces))
        np.testing.assert_allclose(body.vertices, same.vertices, atol=1e-12)
        assert body.pose == same.pose and body.pose != other.pose
        assert all(low <= body.phenotype[key] <= high for key, (low, high) in WIDE_PHENOTYPE_RANGES.items())


def test_closing_an_opening_leaves_a_closed_consistently_oriented_surface():
    """A sphere with a cap cut off: the hole is zipped shut with no new vertex, the cap's inner vertices
    left unreferenced, every edge between two faces that run it in opposite directions."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    vertices, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    cap = vertices[faces].mean(1)[:, 2] > 0.8
    assert len(boundary_loops(faces)) == 0 and len(boundary_loops(faces[~cap])) == 1
    closed = close_openings(vertices, faces, cap)
    loop = boundary_loops(faces[~cap])[0]
    assert len(closed) == (~cap).sum() + len(loop) - 2
    half_edges = closed[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    assert len(np.unique(half_edges, axis=0)) == len(half_edges)  # one orientation
    assert len(np.unique(np.sort(half_edges, axis=1), axis=0)) * 2 == len(half_edges)  # every edge twice
    used = np.unique(closed)
    assert len(used) - len(half_edges) // 2 + len(closed) == 2  # a sphere again (Euler characteristic 2)
    cap_only = np.setdiff1d(np.unique(faces[cap]), np.unique(faces[~cap]))
    assert len(cap_only) > 0 and not np.isin(cap_only, used).any()
    outward = trimesh.Trimesh(vertices, closed, process=False)
    assert outward.is_winding_consistent and outward.volume > 0  # faces still facing out


def test_the_full_template_has_no_mouth_or_eye_socket_left(cache):
    from zernet.data.bodies.topology import cavity_faces

    generator = BodyGenerator("full", "rest", seed=0, cache_dir=cache)
    topology = generator.topology()
    model = generator.model
    template = model.template_vertices.numpy()
    faces = model.get_triangular_faces().numpy()
    cavity = cavity_faces(model)
    inner = np.setdiff1d(np.unique(faces[cavity]), np.unique(faces[~cavity]))
    assert cavity.sum() == 796 + 2 * 586 and len(inner) == 380 + 2 * 280  # mouth, two eye sockets
    assert not np.isin(topology.corners, inner).any()
    assert topology.n_vertices == 12408
    mesh = trimesh.Trimesh(topology.place(template), topology.faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.euler_number == 2
    # Closed at the lips and eyelids: the only faces not of the template join vertices of those openings,
    # as many as close a loop of 38 (the lips) and two of 28 (the eyelids) without a new vertex.
    openings = np.intersect1d(np.unique(faces[cavity]), np.unique(faces[~cavity]))
    assert len(openings) == 38 + 2 * 28
    template_faces = topology.corners[topology.faces, 0]  # the full topology's vertices are template vertices
    original = {tuple(sorted(face)) for face in faces.tolist()}
    added = np.array([face for face in template_faces.tolist() if tuple(sorted(face)) not in original])
    assert len(added) == (38 - 2) + 2 * (28 - 2) and np.isin(added, openings).all()
