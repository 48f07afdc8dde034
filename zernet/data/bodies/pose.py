"""Phenotypes and poses of generated bodies: the seeded draws and the bone rotations they become.

The ranges are documented in :mod:`zernet.data.bodies` (module docstring) and ``docs/BODIES.md``; this module
holds them as data (:data:`JOINTS`, :data:`PHENOTYPE_RANGES`, :data:`ARM_STYLES`, ...) and turns a pose (joint
name -> degrees) into the per-bone 4x4 deltas of anny's "local-ref" pose parameterisation. Plain numpy: no
anny import here.

Pose modes (:data:`POSE_MODES`): ``rest`` is anny's A-pose; ``varied`` draws every joint of :data:`JOINTS`
uniformly in its ``varied`` range, ``mild`` draws the same and halves it. ``wide`` covers what people do in
scans (arms overhead, crossed, behind the back, reaching forward; squats, sitting, one-leg stands; deep torso
bends and twists) and the full phenotype ranges: each arm draws a style of :data:`ARM_STYLES`, the legs one
of :data:`LEG_STYLES`, and each style its own joint ranges, so that extreme angles come only in the
combinations a person takes (a fully bent elbow with the upper arm raised or turned in, not into the chest).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "POSE_MODES",
    "POSE_SCALES",
    "PHENOTYPE_RANGES",
    "WIDE_PHENOTYPE_RANGES",
    "JOINTS",
    "WIDE_TRUNK_RANGES",
    "ARM_STYLES",
    "LEG_STYLES",
    "STANDING_LEG",
    "FORWARD",
    "BACK",
    "UP",
    "OUTWARD",
    "ALONG",
    "Joint",
    "phenotype_ranges",
    "draw_phenotype",
    "spread_phenotypes",
    "draw_pose",
    "rotation_matrix",
    "bone_rotations",
]

#: Pose mode -> scale of every drawn ``varied`` joint angle (0: anny's rest A-pose).
POSE_SCALES = {"rest": 0.0, "mild": 0.5, "varied": 1.0}
#: Every pose mode: the scaled ones and ``wide`` (module docstring).
POSE_MODES = (*POSE_SCALES, "wide")

#: Directions in anny's frame: forward is -y, up is +z, the body's left is +x.
FORWARD, BACK, UP = (0.0, -1.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
#: "Toward the body's side": +x for a left bone, -x for a right one.
OUTWARD = "outward"
#: About the segment bone -> tip itself (a twist); positive turns its front toward the midline.
ALONG = "along"


@dataclass(frozen=True)
class Joint:
    """One rotation of one bone (``{side}`` in a name: one joint per side, L and R).

    With a ``tip`` bone, the rotation turns the segment bone -> tip toward ``direction`` (a direction,
    :data:`OUTWARD`) or about itself (:data:`ALONG`); without, it is about ``direction`` as an axis.
    ``varied``: the range (degrees) of the ``varied`` mode; None for joints only ``wide`` turns.
    """

    group: str
    bone: str
    tip: str | None
    direction: tuple[float, float, float] | str
    varied: tuple[float, float] | None

    def sides(self) -> tuple[str, ...]:
        return ("L", "R") if "{side}" in self.bone else ("",)

    def key(self, side: str) -> str:
        """The pose's name of this joint on ``side``: ``"<group>|<bone>"``."""
        return f"{self.group}|{self.bone.format(side=side)}"


#: The joints, in the order their rotations compose on a bone (the table of the module docstring). The
#: ``varied`` draws follow this order: joints only ``wide`` turns come last, so older modes draw as before.
JOINTS = (
    Joint("spine bend", "spine03", None, (1.0, 0.0, 0.0), (-8.0, 15.0)),
    Joint("spine bend", "spine01", None, (1.0, 0.0, 0.0), (-8.0, 15.0)),
    Joint("spine side bend", "spine03", None, (0.0, 1.0, 0.0), (-8.0, 8.0)),
    Joint("spine side bend", "spine01", None, (0.0, 1.0, 0.0), (-8.0, 8.0)),
    Joint("spine twist", "spine03", None, (0.0, 0.0, 1.0), (-20.0, 20.0)),
    Joint("head nod", "neck01", None, (1.0, 0.0, 0.0), (-10.0, 20.0)),
    Joint("head turn", "head", None, (0.0, 0.0, 1.0), (-35.0, 35.0)),
    Joint("shoulder raise", "upperarm01.{side}", "lowerarm01.{side}", UP, (-10.0, 45.0)),
    Joint("shoulder swing", "upperarm01.{side}", "lowerarm01.{side}", FORWARD, (-25.0, 40.0)),
    Joint("elbow", "lowerarm01.{side}", "wrist.{side}", FORWARD, (0.0, 75.0)),
    Joint("wrist", "wrist.{side}", "finger3-1.{side}", FORWARD, (-25.0, 25.0)),
    Joint("hip swing", "upperleg01.{side}", "lowerleg01.{side}", FORWARD, (-15.0, 50.0)),
    Joint("hip spread", "upperleg01.{side}", "lowerleg01.{side}", OUTWARD, (-3.0, 20.0)),
    Joint("knee", "lowerleg01.{side}", "foot.{side}", BACK, (0.0, 80.0)),
    Joint("ankle", "foot.{side}", None, (1.0, 0.0, 0.0), (-15.0, 15.0)),
    # Turned by ``wide`` only. The twist is last on its bone, so it turns the arm about its own rest axis
    # before the raise and swing orient it.
    Joint("shoulder twist", "upperarm01.{side}", "lowerarm01.{side}", ALONG, None),
    Joint("shoulder girdle raise", "clavicle.{side}", "upperarm01.{side}", UP, None),
)

#: ``wide``: the range of each trunk, head, wrist and ankle joint group (every bone of the group).
WIDE_TRUNK_RANGES = {
    "spine bend": (-10.0, 30.0),
    "spine side bend": (-15.0, 15.0),
    "spine twist": (-40.0, 40.0),
    "head nod": (-20.0, 30.0),
    "head turn": (-45.0, 45.0),
    "wrist": (-40.0, 40.0),
    "ankle": (-25.0, 25.0),
}

# The arm's rest (anny's A-pose) hangs about 48 degrees below the horizontal: a raise of 138 degrees holds it
# straight up, 90 degrees of swing straight forward.
#: ``wide``: arm style -> (probability, joint group -> range in degrees). Each arm draws its style (the right
#: one copies the left's style half of the time, as in two-armed poses), then each joint in that style's range.
ARM_STYLES = {
    "down": (
        0.3,
        {
            "shoulder raise": (-30.0, 45.0),
            "shoulder swing": (-25.0, 40.0),
            "elbow": (0.0, 75.0),
            "shoulder twist": (-20.0, 20.0),
        },
    ),
    "overhead": (
        0.25,
        {
            "shoulder raise": (70.0, 130.0),
            "shoulder swing": (-15.0, 40.0),
            "elbow": (0.0, 110.0),
            "shoulder twist": (-90.0, 20.0),
            "shoulder girdle raise": (5.0, 25.0),
        },
    ),
    "forward": (
        0.15,
        {
            "shoulder raise": (-10.0, 30.0),
            "shoulder swing": (50.0, 100.0),
            "elbow": (0.0, 90.0),
            "shoulder twist": (-30.0, 60.0),
        },
    ),
    "crossed": (
        0.15,
        {
            "shoulder raise": (-15.0, 15.0),
            "shoulder swing": (20.0, 60.0),
            "elbow": (70.0, 110.0),
            "shoulder twist": (30.0, 75.0),
        },
    ),
    "behind": (
        0.15,
        {
            "shoulder raise": (-10.0, 20.0),
            "shoulder swing": (-45.0, -20.0),
            "elbow": (40.0, 90.0),
            "shoulder twist": (20.0, 80.0),
        },
    ),
}

#: ``wide``: leg style -> (probability, joint group -> range of each leg; for ``one-leg`` the lifted leg's, the
#: other standing, :data:`STANDING_LEG`). ``step`` holds the ``varied`` ranges (walking, lunging).
LEG_STYLES = {
    "stand": (0.35, {"hip swing": (-10.0, 15.0), "hip spread": (-3.0, 15.0), "knee": (0.0, 20.0)}),
    "step": (0.2, {"hip swing": (-15.0, 50.0), "hip spread": (-3.0, 20.0), "knee": (0.0, 80.0)}),
    "bent": (0.2, {"hip swing": (50.0, 100.0), "hip spread": (-3.0, 30.0), "knee": (50.0, 120.0)}),
    "one-leg": (0.25, {"hip swing": (20.0, 100.0), "hip spread": (-3.0, 50.0), "knee": (30.0, 120.0)}),
}
#: ``one-leg``: the ranges of the leg stood on.
STANDING_LEG = LEG_STYLES["stand"][1]

#: Phenotype -> (low, high) of its uniform draw (modes rest, mild, varied).
PHENOTYPE_RANGES = {
    "gender": (0.0, 1.0),
    "age": (0.5, 0.95),
    "muscle": (0.1, 0.9),
    "weight": (0.1, 0.9),
    "height": (0.1, 0.9),
    "proportions": (0.2, 0.8),
}
#: Mode ``wide``: muscle and weight over the model's whole range (the thinnest, heaviest and most muscular).
WIDE_PHENOTYPE_RANGES = {**PHENOTYPE_RANGES, "muscle": (0.0, 1.0), "weight": (0.0, 1.0)}


def phenotype_ranges(mode: str) -> dict[str, tuple[float, float]]:
    """The phenotype ranges of a pose mode: :data:`WIDE_PHENOTYPE_RANGES` for ``wide``, else the older ones."""
    return WIDE_PHENOTYPE_RANGES if mode == "wide" else PHENOTYPE_RANGES


def draw_phenotype(rng: np.random.Generator, ranges: dict[str, tuple[float, float]] = PHENOTYPE_RANGES) -> dict:
    """One phenotype: every value of ``ranges`` drawn uniformly, in its order."""
    return {key: float(rng.uniform(low, high)) for key, (low, high) in ranges.items()}


def spread_phenotypes(
    rng: np.random.Generator, count: int, ranges: dict[str, tuple[float, float]] = PHENOTYPE_RANGES
) -> list[dict[str, float]]:
    """``count`` phenotypes spread over every range of ``ranges`` (a Latin hypercube): each value's range is
    cut into ``count`` equal strata and every stratum is used once, in an order drawn independently per
    value. A few people then differ as much as the ranges allow (both sexes, the youngest and oldest
    adults, thin and heavy, short and tall), where independent draws often bunch up."""
    if count < 1:
        raise ValueError(f"need at least one person, got {count}")
    columns = {}
    for key, (low, high) in ranges.items():
        strata = (rng.permutation(count) + rng.uniform(size=count)) / count
        columns[key] = low + (high - low) * strata
    return [{key: float(values[person]) for key, values in columns.items()} for person in range(count)]


def draw_pose(rng: np.random.Generator, mode: str) -> dict[str, float]:
    """Joint name ("<group>|<bone>") -> angle in degrees, for a pose mode of :data:`POSE_MODES`: every
    ``varied`` joint (sides included) drawn uniformly in its range and scaled, or a ``wide`` pose."""
    if mode == "wide":
        return _draw_wide_pose(rng)
    scale = POSE_SCALES[mode]
    return {
        joint.key(side): float(rng.uniform(*joint.varied)) * scale
        for joint in JOINTS
        if joint.varied is not None
        for side in joint.sides()
    }


def _choose(rng: np.random.Generator, styles: dict) -> str:
    names = list(styles)
    return names[rng.choice(len(names), p=[styles[name][0] for name in names])]


def _draw_wide_pose(rng: np.random.Generator) -> dict[str, float]:
    """A ``wide`` pose (module docstring): the trunk's ranges, an arm style per side, a leg style."""
    left_arm = _choose(rng, ARM_STYLES)
    right_arm = left_arm if rng.uniform() < 0.5 else _choose(rng, ARM_STYLES)
    legs = _choose(rng, LEG_STYLES)
    lifted = "L" if rng.uniform() < 0.5 else "R"
    ranges = {
        "L": {**ARM_STYLES[left_arm][1], **LEG_STYLES[legs][1]},
        "R": {**ARM_STYLES[right_arm][1], **LEG_STYLES[legs][1]},
    }
    if legs == "one-leg":
        ranges["R" if lifted == "L" else "L"].update(STANDING_LEG)
    angles = {}
    for joint in JOINTS:
        for side in joint.sides():
            low, high = WIDE_TRUNK_RANGES.get(joint.group) or ranges[side].get(joint.group, (0.0, 0.0))
            angles[joint.key(side)] = float(rng.uniform(low, high))
    return angles


def rotation_matrix(axis: np.ndarray, degrees: float) -> np.ndarray:
    """4x4 homogeneous rotation by ``degrees`` about a unit axis (Rodrigues)."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    angle = np.radians(degrees)
    matrix = np.eye(4)
    matrix[:3, :3] = np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)
    return matrix


def _joint_axis(joint: Joint, side: str, bones: dict[str, int], heads: np.ndarray) -> np.ndarray:
    """The unit rotation axis of one joint: its fixed axis, the segment bone -> tip itself, or the axis that
    turns the segment toward a direction."""
    if joint.tip is None:
        axis = np.asarray(joint.direction, dtype=np.float64)
    else:
        segment = heads[bones[joint.tip.format(side=side)]] - heads[bones[joint.bone.format(side=side)]]
        outward = (1.0 if side == "L" else -1.0, 0.0, 0.0)
        if joint.direction == ALONG:
            # About the segment, signed per side so that a positive twist turns the bone's front (-y)
            # toward the midline on both sides (a mirror image).
            axis = segment * (1.0 if side == "L" else -1.0)
        else:
            toward = np.asarray(outward if joint.direction == OUTWARD else joint.direction)
            # Turning the segment u about u x d moves its far end toward d.
            axis = np.cross(segment, toward)
    return axis / np.linalg.norm(axis)


def bone_rotations(bones: list[str], heads: np.ndarray, pose: dict[str, float]) -> dict[str, np.ndarray]:
    """Bone -> composed 4x4 delta (world-aligned axes, anny's "local-ref" pose parameterisation).

    ``bones`` are the model's bone names, ``heads`` (B, 3) their rest heads for the body's phenotype; joints
    with angle 0 (or missing from ``pose``) leave their bone out.
    """
    index = {bone: i for i, bone in enumerate(bones)}
    rotations: dict[str, np.ndarray] = {}
    for joint in JOINTS:
        for side in joint.sides():
            degrees = pose.get(joint.key(side), 0.0)
            if degrees == 0.0:
                continue
            bone = joint.bone.format(side=side)
            axis = _joint_axis(joint, side, index, heads)
            rotations[bone] = rotations.get(bone, np.eye(4)) @ rotation_matrix(axis, degrees)
    return rotations
