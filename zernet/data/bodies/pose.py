"""Phenotypes and poses of generated bodies: the seeded draws and the bone rotations they become.

The ranges are documented in :mod:`zernet.data.bodies` (module docstring) and ``docs/BODIES.md``; this module
holds them as data (:data:`JOINTS`, :data:`PHENOTYPE_RANGES`, :data:`POSE_MODES`) and turns a pose (joint
name -> degrees) into the per-bone 4x4 deltas of anny's "local-ref" pose parameterisation. Plain numpy: no
anny import here.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "POSE_MODES",
    "PHENOTYPE_RANGES",
    "JOINTS",
    "FORWARD",
    "BACK",
    "UP",
    "OUTWARD",
    "draw_phenotype",
    "spread_phenotypes",
    "draw_pose",
    "rotation_matrix",
    "bone_rotations",
]

#: Pose mode -> scale of every drawn joint angle (0: anny's rest A-pose).
POSE_MODES = {"rest": 0.0, "mild": 0.5, "varied": 1.0}

#: Directions in anny's frame: forward is -y, up is +z, the body's left is +x.
FORWARD, BACK, UP = (0.0, -1.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
#: "Toward the body's side": +x for a left bone, -x for a right one.
OUTWARD = "outward"

#: (name, bone, tip bone or None, axis or "toward" direction, low, high): the table of the docstring. With a
#: tip bone, the rotation turns the segment bone -> tip toward the direction; without, it is about the axis.
JOINTS = (
    ("spine bend", "spine03", None, (1.0, 0.0, 0.0), -8.0, 15.0),
    ("spine bend", "spine01", None, (1.0, 0.0, 0.0), -8.0, 15.0),
    ("spine side bend", "spine03", None, (0.0, 1.0, 0.0), -8.0, 8.0),
    ("spine side bend", "spine01", None, (0.0, 1.0, 0.0), -8.0, 8.0),
    ("spine twist", "spine03", None, (0.0, 0.0, 1.0), -20.0, 20.0),
    ("head nod", "neck01", None, (1.0, 0.0, 0.0), -10.0, 20.0),
    ("head turn", "head", None, (0.0, 0.0, 1.0), -35.0, 35.0),
    ("shoulder raise", "upperarm01.{side}", "lowerarm01.{side}", UP, -10.0, 45.0),
    ("shoulder swing", "upperarm01.{side}", "lowerarm01.{side}", FORWARD, -25.0, 40.0),
    ("elbow", "lowerarm01.{side}", "wrist.{side}", FORWARD, 0.0, 75.0),
    ("wrist", "wrist.{side}", "finger3-1.{side}", FORWARD, -25.0, 25.0),
    ("hip swing", "upperleg01.{side}", "lowerleg01.{side}", FORWARD, -15.0, 50.0),
    ("hip spread", "upperleg01.{side}", "lowerleg01.{side}", OUTWARD, -3.0, 20.0),
    ("knee", "lowerleg01.{side}", "foot.{side}", BACK, 0.0, 80.0),
    ("ankle", "foot.{side}", None, (1.0, 0.0, 0.0), -15.0, 15.0),
)

#: Phenotype -> (low, high) of its uniform draw.
PHENOTYPE_RANGES = {
    "gender": (0.0, 1.0),
    "age": (0.5, 0.95),
    "muscle": (0.1, 0.9),
    "weight": (0.1, 0.9),
    "height": (0.1, 0.9),
    "proportions": (0.2, 0.8),
}


def _sides(bone_pattern: str) -> tuple[str, ...]:
    return ("L", "R") if "{side}" in bone_pattern else ("",)


def draw_phenotype(rng: np.random.Generator) -> dict[str, float]:
    """One phenotype: every value of :data:`PHENOTYPE_RANGES` drawn uniformly, in its order."""
    return {key: float(rng.uniform(low, high)) for key, (low, high) in PHENOTYPE_RANGES.items()}


def spread_phenotypes(rng: np.random.Generator, count: int) -> list[dict[str, float]]:
    """``count`` phenotypes spread over every range of :data:`PHENOTYPE_RANGES` (a Latin hypercube): each
    value's range is cut into ``count`` equal strata and every stratum is used once, in an order drawn
    independently per value. A few people then differ as much as the ranges allow (both sexes, the youngest
    and oldest adults, thin and heavy, short and tall), where independent draws often bunch up."""
    if count < 1:
        raise ValueError(f"need at least one person, got {count}")
    columns = {}
    for key, (low, high) in PHENOTYPE_RANGES.items():
        strata = (rng.permutation(count) + rng.uniform(size=count)) / count
        columns[key] = low + (high - low) * strata
    return [{key: float(values[person]) for key, values in columns.items()} for person in range(count)]


def draw_pose(rng: np.random.Generator, scale: float) -> dict[str, float]:
    """Joint name ("<group>|<bone>") -> angle in degrees, for every joint of :data:`JOINTS` (sides included),
    each drawn uniformly in its range and multiplied by ``scale`` (a :data:`POSE_MODES` value)."""
    angles = {}
    for group, bone, _, _, low, high in JOINTS:
        for side in _sides(bone):
            angles[f"{group}|{bone.format(side=side)}"] = float(rng.uniform(low, high)) * scale
    return angles


def rotation_matrix(axis: np.ndarray, degrees: float) -> np.ndarray:
    """4x4 homogeneous rotation by ``degrees`` about a unit axis (Rodrigues)."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    angle = np.radians(degrees)
    matrix = np.eye(4)
    matrix[:3, :3] = np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)
    return matrix


def _joint_axis(
    bone: str, side: str, tip_pattern: str | None, direction, bones: dict[str, int], heads: np.ndarray
) -> np.ndarray:
    """The unit rotation axis of one joint: its fixed axis, or the one that turns bone -> tip toward a direction."""
    if tip_pattern is None:
        axis = np.asarray(direction, dtype=np.float64)
    else:
        segment = heads[bones[tip_pattern.format(side=side)]] - heads[bones[bone]]
        outward = (1.0 if side == "L" else -1.0, 0.0, 0.0)
        toward = np.asarray(outward if direction == OUTWARD else direction)
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
    for group, bone_pattern, tip_pattern, direction, _, _ in JOINTS:
        for side in _sides(bone_pattern):
            bone = bone_pattern.format(side=side)
            degrees = pose.get(f"{group}|{bone}", 0.0)
            if degrees == 0.0:
                continue
            axis = _joint_axis(bone, side, tip_pattern, direction, index, heads)
            rotations[bone] = rotations.get(bone, np.eye(4)) @ rotation_matrix(axis, degrees)
    return rotations
