"""Human bodies with ground truth, generated offline by the parametric body model ``anny``.

``anny`` (Apache-2.0 code, CC0 MakeHuman assets) is an optional dependency, imported lazily by this module
only: ``pip install 'zernet[bodies]'``. Every body of a data set shares one connectivity, so the
correspondence class of a vertex is its index (as for FAUST), and each vertex carries one of the 8 part
labels of the human-segmentation benchmark (Maron et al. 2017).

Topologies (``topology=``)
    ==============  ========  =================================================================
    name            vertices  made from
    ==============  ========  =================================================================
    ``faust``       6,890     the full body decimated once (quadric decimation, fast-simplification)
                              to FAUST's count (6,890 vertices, 13,776 faces); every kept vertex is
                              a point of the full template in barycentric coordinates of one of its
                              triangles, carried through every posed body
    ``full``        13,348    anny's template without its interior parts (eyes, tongue)
    ``coarse-1229`` 1,229     anny's shipped ``notoes_collapse10pc`` topology
    ``coarse-615``  615       anny's shipped ``notoes_collapse5pc`` topology
    ``coarse-369``  369       anny's shipped ``notoes_collapse3pc`` topology
    ==============  ========  =================================================================

Interior components are removed by keeping the largest connected component of the template; the kept
vertices are renumbered in their template order, the same way for every body.

Parts (labels 0-7, in :data:`zernet.data.segmentation.HUMAN_PART_NAMES` order, left and right merged):
a vertex's part is the part whose bones carry the largest sum of its skinning weights.

    ==========  =============================================================================
    part        bones
    ==========  =============================================================================
    head        neck01-03, head, eye.L/R
    torso       root, pelvis.L/R, spine01-05, clavicle.L/R, shoulder01.L/R
    upper arm   upperarm01-02.L/R
    lower arm   lowerarm01-02.L/R
    hand        wrist.L/R, metacarpal*, finger*
    upper leg   upperleg01-02.L/R
    lower leg   lowerleg01-02.L/R
    foot        foot.L/R, toe*
    ==========  =============================================================================

Phenotypes, drawn uniformly: gender 0-1 (male-female), age 0.5-0.95 (adults; anny's 2/3 is "young",
1 "old"), muscle 0.1-0.9, weight 0.1-0.9, height 0.1-0.9, proportions 0.2-0.8.

Poses (``poses=``): ``rest`` (anny's A-pose), ``varied`` (each joint rotation drawn uniformly in the
ranges below, left and right independently), ``mild`` (the same ranges halved). Directions are in
anny's frame: forward is -y, up is +z, the body's left is +x (written bodies are then turned to FAUST's
frame: y up, facing +z). A rotation "toward D" turns the bone so that its
far end moves toward direction D; the ranges keep limbs off the body for every phenotype above.

    ===================  =====================  ==================================  =============
    joint group          bones                  rotation                            range (deg)
    ===================  =====================  ==================================  =============
    spine bend           spine03, spine01       about x (positive: bend forward)    -8 .. +15
    spine side bend      spine03, spine01       about y                             -8 .. +8
    spine twist          spine03                about z                             -20 .. +20
    head nod             neck01                 about x (positive: chin down)       -10 .. +20
    head turn            head                   about z                             -35 .. +35
    shoulder raise       upperarm01.L/R         toward up (negative: arm lowered)   -10 .. +45
    shoulder swing       upperarm01.L/R         toward forward (negative: back)     -25 .. +40
    elbow                lowerarm01.L/R         toward forward (flexion)            0 .. +75
    wrist                wrist.L/R              toward forward                      -25 .. +25
    hip swing            upperleg01.L/R         toward forward (negative: back)     -15 .. +50
    hip spread           upperleg01.L/R         toward the body's side (outward)    -3 .. +20
    knee                 lowerleg01.L/R         toward back (flexion)               0 .. +80
    ankle                foot.L/R               about x                             -15 .. +15
    ===================  =====================  ==================================  =============

Train and test bodies: body ``i`` of split ``s`` is drawn from its own random stream
``numpy.random.SeedSequence([seed, s, i])`` (s = 0 for train, 1 for test), so the test bodies' phenotypes
and poses are independent draws from a stream the training bodies never use (none is shared), and body i
does not change with ``count``.

Cache: the topology of each name and every generated body are stored under ``<cache_dir>/bodies/``, keyed
by the generator version, the anny version, the topology, the pose mode, the seed, the split and the
index, and written atomically. The anny model (whose first build takes a minute or more: it builds its
own cache and compiles kernels) is built only when something is missing from that cache.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import io
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

from zernet.data.dataset import DatasetError
from zernet.data.segmentation import HUMAN_PART_NAMES
from zernet.io_utils import atomic_write_bytes
from zernet.geometry import Surface, validate_surface

__all__ = [
    "GENERATOR_VERSION",
    "TOPOLOGIES",
    "POSE_MODES",
    "PART_BONES",
    "MISSING_EXTRA_MESSAGE",
    "Body",
    "BodyTopology",
    "BodiesLayout",
    "BodyGenerator",
    "part_of_bone",
    "generate_bodies",
    "write_bodies",
]

#: Bumped whenever a change alters generated bodies, so cached bodies of older versions are not reused.
GENERATOR_VERSION = 1
#: Topology name -> anny topology it is built on (see the module docstring).
TOPOLOGIES = {
    "faust": "anny",
    "full": "anny",
    "coarse-1229": "notoes_collapse10pc",
    "coarse-615": "notoes_collapse5pc",
    "coarse-369": "notoes_collapse3pc",
}
POSE_MODES = {"rest": 0.0, "mild": 0.5, "varied": 1.0}
FAUST_FACES = 13776  # 6890 vertices on a closed genus-0 surface
MISSING_EXTRA_MESSAGE = "human bodies need the optional dependency anny: pip install 'zernet[bodies]'"

#: Part (index into HUMAN_PART_NAMES) -> bone name prefixes (a bone belongs to the first part it matches).
PART_BONES = {
    0: ("neck", "head", "eye"),
    1: ("root", "pelvis", "spine", "clavicle", "shoulder"),
    2: ("upperarm",),
    3: ("lowerarm",),
    4: ("wrist", "metacarpal", "finger"),
    5: ("upperleg",),
    6: ("lowerleg",),
    7: ("foot", "toe"),
}

_FORWARD, _BACK, _UP = (0.0, -1.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
_OUTWARD = "outward"
# Rotation by -90 degrees about x: (x, y, z) -> (x, z, -y).
_Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
# (name, bone, tip bone or None, axis or "toward" direction, low, high): the table of the docstring. With a
# tip bone, the rotation turns the segment bone -> tip toward the direction; without, it is about the axis.
_JOINTS = (
    ("spine bend", "spine03", None, (1.0, 0.0, 0.0), -8.0, 15.0),
    ("spine bend", "spine01", None, (1.0, 0.0, 0.0), -8.0, 15.0),
    ("spine side bend", "spine03", None, (0.0, 1.0, 0.0), -8.0, 8.0),
    ("spine side bend", "spine01", None, (0.0, 1.0, 0.0), -8.0, 8.0),
    ("spine twist", "spine03", None, (0.0, 0.0, 1.0), -20.0, 20.0),
    ("head nod", "neck01", None, (1.0, 0.0, 0.0), -10.0, 20.0),
    ("head turn", "head", None, (0.0, 0.0, 1.0), -35.0, 35.0),
    ("shoulder raise", "upperarm01.{side}", "lowerarm01.{side}", _UP, -10.0, 45.0),
    ("shoulder swing", "upperarm01.{side}", "lowerarm01.{side}", _FORWARD, -25.0, 40.0),
    ("elbow", "lowerarm01.{side}", "wrist.{side}", _FORWARD, 0.0, 75.0),
    ("wrist", "wrist.{side}", "finger3-1.{side}", _FORWARD, -25.0, 25.0),
    ("hip swing", "upperleg01.{side}", "lowerleg01.{side}", _FORWARD, -15.0, 50.0),
    ("hip spread", "upperleg01.{side}", "lowerleg01.{side}", _OUTWARD, -3.0, 20.0),
    ("knee", "lowerleg01.{side}", "foot.{side}", _BACK, 0.0, 80.0),
    ("ankle", "foot.{side}", None, (1.0, 0.0, 0.0), -15.0, 15.0),
)
# Phenotype -> (low, high) of its uniform draw.
_PHENOTYPE_RANGES = {"gender": (0.0, 1.0), "age": (0.5, 0.95), "muscle": (0.1, 0.9), "weight": (0.1, 0.9),
                     "height": (0.1, 0.9), "proportions": (0.2, 0.8)}
_SPLIT_CODES = {"train": 0, "test": 1}
_TOPOLOGY_ARRAYS = ("corners", "weights", "faces", "parts", "sides")


def part_of_bone(bone: str) -> int:
    """The part (0-7, HUMAN_PART_NAMES order) of an anny bone name; ValueError for an unknown bone."""
    for part, prefixes in PART_BONES.items():
        if bone.startswith(prefixes):
            return part
    raise ValueError(f"anny bone {bone!r} belongs to no part of PART_BONES")


def _side_of_bone(bone: str) -> int:
    """+1 for the body's left (.L), -1 for its right (.R), 0 for the midline."""
    return 1 if bone.endswith(".L") else -1 if bone.endswith(".R") else 0


def _import_anny():
    """anny, or a DatasetError naming the extra (the only place anny is imported)."""
    try:
        import anny
    except ImportError as error:
        raise DatasetError(MISSING_EXTRA_MESSAGE) from error
    return anny


def _package_version(name: str) -> str:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True)
class BodyTopology:
    """One connectivity shared by every body of a data set.

    Vertex ``v`` is ``sum_k weights[v, k] * model_vertices[corners[v, k]]`` of a posed anny body: a template
    vertex itself (weights (1, 0, 0)) or a point of one of its triangles. ``parts`` (N,) holds the part
    labels (0-7), ``sides`` (N,) +1 / -1 / 0 for left / right / midline (the side whose bones carry more of
    the vertex's skinning weight).
    """

    name: str
    corners: np.ndarray
    weights: np.ndarray
    faces: np.ndarray
    parts: np.ndarray
    sides: np.ndarray

    @property
    def n_vertices(self) -> int:
        return len(self.corners)

    def place(self, model_vertices: np.ndarray) -> np.ndarray:
        """This topology's vertices (N, 3) from the anny model's (V, 3)."""
        return np.einsum("nk,nkd->nd", self.weights, model_vertices[self.corners])


@dataclass(frozen=True)
class Body:
    """A generated body: vertices (N, 3) in metres (y up, facing +z), shared faces, per-vertex parts,
    its phenotype and pose (joint angles in degrees)."""

    name: str
    split: str
    vertices: np.ndarray
    faces: np.ndarray
    parts: np.ndarray
    phenotype: dict = field(default_factory=dict)
    pose: dict = field(default_factory=dict)

    @property
    def correspondence(self) -> np.ndarray:
        """The class of each vertex: its template index."""
        return np.arange(len(self.vertices), dtype=np.int64)

    def surface(self) -> Surface:
        return Surface(self.vertices, self.faces, name=self.name)


@dataclass(frozen=True)
class BodiesLayout:
    """Where :func:`write_bodies` put things (see the README.txt it writes)."""

    root: Path
    meshes: Path
    labels: Path
    class_names: Path
    registrations: Path
    readme: Path
    topology: str
    n_vertices: int
    n_train: int
    n_test: int


def _npz_bytes(**arrays) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def _largest_component(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """(kept template vertices in template order, faces renumbered onto them) of the largest component."""
    mesh = trimesh.Trimesh(np.zeros((n_vertices, 3)), faces, process=False)
    components = trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(len(faces)), min_len=1)
    kept_faces = faces[np.sort(max(components, key=len))]
    kept = np.unique(kept_faces)
    renumber = np.full(n_vertices, -1, dtype=np.int64)
    renumber[kept] = np.arange(len(kept))
    return kept, renumber[kept_faces]


def _closest_barycentric(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray,
                         neighbours: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """For each point, (the triangle of the mesh closest to it, its barycentric coordinates there).

    Candidates are the triangles around the ``neighbours`` nearest mesh vertices, exact among those.
    """
    _, nearest = cKDTree(vertices).query(points, k=neighbours)
    vertex_faces = trimesh.Trimesh(vertices, faces, process=False).vertex_faces  # (V, max degree), -1 padded
    candidates = vertex_faces[nearest].reshape(len(points), -1)
    point_ids = np.repeat(np.arange(len(points)), candidates.shape[1])
    face_ids = candidates.reshape(-1)
    valid = face_ids >= 0
    point_ids, face_ids = point_ids[valid], face_ids[valid]
    closest = trimesh.triangles.closest_point(vertices[faces[face_ids]], points[point_ids])
    distance = np.linalg.norm(closest - points[point_ids], axis=1)
    order = np.lexsort((distance, point_ids))
    best = order[np.r_[0, np.flatnonzero(np.diff(point_ids[order])) + 1]]
    barycentric = trimesh.triangles.points_to_barycentric(vertices[faces[face_ids[best]]], closest[best])
    return face_ids[best], np.clip(barycentric, 0.0, 1.0) / np.clip(barycentric, 0.0, 1.0).sum(1, keepdims=True)


def _decimate_to_faust(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(corners (6890, 3) into ``vertices``, barycentric weights, faces (13776, 3)) of the decimated body."""
    try:
        import fast_simplification  # optional, part of the bodies extra
    except ImportError as error:
        raise DatasetError(MISSING_EXTRA_MESSAGE + " (the 'faust' topology also needs fast-simplification)") from error
    # agg=3: fewer sliver triangles than the default 7, and it still reaches the target count.
    points, reduced_faces = fast_simplification.simplify(vertices, faces.astype(np.int32), target_count=FAUST_FACES,
                                                         agg=3.0)
    triangles, barycentric = _closest_barycentric(vertices, faces, points)
    return faces[triangles], barycentric, reduced_faces.astype(np.int64)


def _labels_from_weights(model, corners: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(parts, sides) per topology vertex from the model's skinning weights, interpolated like positions."""
    bones = list(model.bone_labels)
    bone_weights = model.vertex_bone_weights.detach().cpu().numpy().astype(np.float64)
    bone_ids = model.vertex_bone_indices.detach().cpu().numpy().astype(np.int64)
    bone_part = np.array([part_of_bone(bone) for bone in bones])
    bone_side = np.array([_side_of_bone(bone) for bone in bones], dtype=np.float64)
    per_part = np.zeros((len(bone_weights), len(HUMAN_PART_NAMES)))
    np.add.at(per_part, (np.arange(len(bone_weights))[:, None].repeat(bone_ids.shape[1], 1), bone_part[bone_ids]),
              bone_weights)
    side_weight = (bone_weights * bone_side[bone_ids]).sum(1)
    parts = np.einsum("nk,nkp->np", weights, per_part[corners]).argmax(1).astype(np.int64)
    side = np.einsum("nk,nk->n", weights, side_weight[corners])
    sides = np.where(side > 0.5, 1, np.where(side < -0.5, -1, 0)).astype(np.int64)
    return parts, sides


def _build_topology(name: str, model) -> BodyTopology:
    """The topology ``name`` of the module docstring, built on ``model`` (an anny model of its base)."""
    template = model.template_vertices.detach().cpu().numpy().astype(np.float64)
    all_faces = model.get_triangular_faces().detach().cpu().numpy().astype(np.int64)
    kept, faces = _largest_component(all_faces, len(template))
    if name == "faust":
        local_corners, weights, faces = _decimate_to_faust(template[kept], faces)
        corners = kept[local_corners]
    else:
        corners = np.repeat(kept[:, None], 3, axis=1)
        weights = np.tile([1.0, 0.0, 0.0], (len(kept), 1))
    parts, sides = _labels_from_weights(model, corners, weights)
    topology = BodyTopology(name, corners, weights, faces, parts, sides)
    validate_surface(Surface(topology.place(template), faces, name=f"body topology {name!r}"))
    return topology


def _draw_phenotype(rng: np.random.Generator) -> dict[str, float]:
    return {key: float(rng.uniform(low, high)) for key, (low, high) in _PHENOTYPE_RANGES.items()}


def _draw_pose(rng: np.random.Generator, scale: float) -> dict[str, float]:
    """Joint name ("<group>|<bone>") -> angle in degrees, for every joint of the table (sides included)."""
    angles = {}
    for group, bone, _, _, low, high in _JOINTS:
        for side in (("L", "R") if "{side}" in bone else ("",)):
            angles[f"{group}|{bone.format(side=side)}"] = float(rng.uniform(low, high)) * scale
    return angles


class BodyGenerator:
    """Seeded bodies of one topology and pose mode, cached under ``<cache_dir>/bodies``.

    ``generator.body(index, split)`` returns the same :class:`Body` for the same arguments on any machine
    with the same anny version; the anny model is built on the first cache miss only.
    """

    def __init__(self, topology: str = "faust", poses: str = "varied", seed: int = 0,
                 cache_dir: str | os.PathLike = ".zernet-cache"):
        if topology not in TOPOLOGIES:
            raise DatasetError(f"unknown body topology {topology!r}; choose one of {', '.join(TOPOLOGIES)}")
        if poses not in POSE_MODES:
            raise DatasetError(f"unknown pose mode {poses!r}; choose one of {', '.join(POSE_MODES)}")
        self.topology_name, self.poses, self.seed = topology, poses, int(seed)
        self.cache = Path(os.path.expanduser(os.fspath(cache_dir))) / "bodies"
        self._model = None
        self._topology = None
        self._version = f"g{GENERATOR_VERSION}-anny{_package_version('anny')}"
        if topology == "faust":
            self._version += f"-fs{_package_version('fast-simplification')}"

    @property
    def model(self):
        """The anny model of this topology's base (built on first use; slow the very first time)."""
        if self._model is None:
            anny = _import_anny()
            self._model = anny.Anny(topology=TOPOLOGIES[self.topology_name])
        return self._model

    def topology(self) -> BodyTopology:
        if self._topology is None:
            path = self.cache / f"topology-{self.topology_name}-{self._version}.npz"
            if path.is_file():
                with np.load(path) as stored:
                    self._topology = BodyTopology(self.topology_name, *(stored[key] for key in _TOPOLOGY_ARRAYS))
            else:
                self._topology = _build_topology(self.topology_name, self.model)
                atomic_write_bytes(path, _npz_bytes(**{key: getattr(self._topology, key) for key in _TOPOLOGY_ARRAYS}))
        return self._topology

    def draws(self, index: int, split: str = "train") -> tuple[dict[str, float], dict[str, float]]:
        """(phenotype, pose in degrees) of body ``index`` of ``split``: its own random stream."""
        if split not in _SPLIT_CODES:
            raise DatasetError(f"body split must be 'train' or 'test', got {split!r}")
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, _SPLIT_CODES[split], int(index)]))
        return _draw_phenotype(rng), _draw_pose(rng, POSE_MODES[self.poses])

    def body(self, index: int, split: str = "train", name: str | None = None) -> Body:
        phenotype, pose = self.draws(index, split)
        topology = self.topology()
        name = name or f"{split}_{index:03d}"
        key = f"{self.topology_name}-{self.poses}-seed{self.seed}-{split}{index}-{self._version}"
        path = self.cache / self.topology_name / (hashlib.sha256(key.encode()).hexdigest()[:24] + ".npz")
        if path.is_file():
            with np.load(path) as stored:
                vertices = stored["vertices"]
        else:
            # anny is z-up facing -y; FAUST's scans (and zernet.viz's default) are y-up facing +z.
            vertices = topology.place(self._pose_model(phenotype, pose)) @ _Z_UP_TO_Y_UP.T
            atomic_write_bytes(path, _npz_bytes(vertices=vertices))
        return Body(name, split, vertices, topology.faces, topology.parts, phenotype, pose)

    def _pose_model(self, phenotype: dict[str, float], pose: dict[str, float]) -> np.ndarray:
        """The model's posed vertices (V, 3) for a phenotype and joint angles in degrees."""
        model = self.model
        with torch.no_grad():
            rest = model(phenotype_kwargs=phenotype)
            heads = rest["rest_bone_heads"][0].detach().cpu().numpy().astype(np.float64)
            deltas = {bone: torch.as_tensor(matrix, dtype=model.dtype, device=model.device)[None]
                      for bone, matrix in _bone_rotations(list(model.bone_labels), heads, pose).items()}
            posed = model(pose_parameters=deltas or None, phenotype_kwargs=phenotype)
        return posed["vertices"][0].detach().cpu().numpy().astype(np.float64)


def _rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    """4x4 homogeneous rotation about a unit axis (Rodrigues)."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    angle = np.radians(degrees)
    matrix = np.eye(4)
    matrix[:3, :3] = np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)
    return matrix


def _bone_rotations(bones: list[str], heads: np.ndarray, pose: dict[str, float]) -> dict[str, np.ndarray]:
    """Bone -> composed 4x4 delta (world-aligned axes, anny's "local-ref" pose parameterisation)."""
    index = {bone: i for i, bone in enumerate(bones)}
    rotations: dict[str, np.ndarray] = {}
    for group, bone_pattern, tip_pattern, direction, _, _ in _JOINTS:
        for side in (("L", "R") if "{side}" in bone_pattern else ("",)):
            bone = bone_pattern.format(side=side)
            degrees = pose.get(f"{group}|{bone}", 0.0)
            if degrees == 0.0:
                continue
            if tip_pattern is None:
                axis = np.asarray(direction, dtype=np.float64)
            else:
                segment = heads[index[tip_pattern.format(side=side)]] - heads[index[bone]]
                outward = (1.0 if side == "L" else -1.0, 0.0, 0.0)
                toward = np.asarray(outward if direction == _OUTWARD else direction)
                # Turning the segment u about u x d moves its far end toward d.
                axis = np.cross(segment, toward)
            axis = axis / np.linalg.norm(axis)
            rotations[bone] = rotations.get(bone, np.eye(4)) @ _rotation(axis, degrees)
    return rotations


def generate_bodies(count: int = 100, seed: int = 0, topology: str = "faust", poses: str = "varied",
                    n_test: int = 20, cache_dir: str | os.PathLike = ".zernet-cache",
                    progress: bool = False) -> list[Body]:
    """``count`` bodies named ``body_000`` ...: the first ``count - n_test`` train, the rest test."""
    if count < 1 or not 0 <= n_test < count:
        raise DatasetError(f"bodies: need count >= 1 and 0 <= n_test < count, got count={count}, n_test={n_test}")
    generator = BodyGenerator(topology, poses, seed, cache_dir)
    n_train = count - n_test
    bodies = []
    for number in tqdm(range(count), desc=f"bodies ({topology})", unit="body", disable=not progress):
        split, index = ("train", number) if number < n_train else ("test", number - n_train)
        bodies.append(generator.body(index, split, name=f"body_{number:03d}"))
    return bodies


def _ply_bytes(body: Body) -> bytes:
    return trimesh.Trimesh(body.vertices, body.faces, process=False).export(file_type="ply")


def write_bodies(out_dir: str | os.PathLike, count: int = 100, seed: int = 0, topology: str = "faust",
                 poses: str = "varied", n_test: int = 20, cache_dir: str | os.PathLike = ".zernet-cache",
                 progress: bool = True) -> BodiesLayout:
    """Generate bodies and write them in the layouts the segmentation and FAUST loaders read.

    Layout (also described by the README.txt written into ``out_dir``)::

        out_dir/segmentation/meshes/{train,test}/body_XXX.ply
        out_dir/segmentation/labels/{train,test}/body_XXX.txt   (one 0-based part label per vertex)
        out_dir/segmentation/labels/class_names.txt             (one part name per line, label order)
        out_dir/correspondence/training/registrations/tr_reg_XXX.ply  (the same meshes, FAUST's names)
    """
    root = Path(os.path.expanduser(os.fspath(out_dir)))
    bodies = generate_bodies(count, seed, topology, poses, n_test, cache_dir, progress)
    layout = BodiesLayout(root, root / "segmentation" / "meshes", root / "segmentation" / "labels",
                          root / "segmentation" / "labels" / "class_names.txt",
                          root / "correspondence" / "training" / "registrations", root / "README.txt",
                          topology, len(bodies[0].vertices), count - n_test, n_test)
    for number, body in enumerate(bodies):
        mesh = _ply_bytes(body)
        atomic_write_bytes(layout.meshes / body.split / f"{body.name}.ply", mesh)
        labels = "\n".join(str(int(label)) for label in body.parts) + "\n"
        atomic_write_bytes(layout.labels / body.split / f"{body.name}.txt", labels.encode())
        atomic_write_bytes(layout.registrations / f"tr_reg_{number:03d}.ply", mesh)
    atomic_write_bytes(layout.class_names, ("\n".join(HUMAN_PART_NAMES) + "\n").encode())
    atomic_write_bytes(layout.readme, _readme(layout, seed, poses).encode())
    return layout


def _readme(layout: BodiesLayout, seed: int, poses: str) -> str:
    last = layout.n_train + layout.n_test - 1
    return f"""Human bodies generated by zernet (zernet.data.bodies, generator version {GENERATOR_VERSION}) with the
parametric body model anny {_package_version('anny')}: seed {seed}, poses "{poses}", topology "{layout.topology}"
({layout.n_vertices} vertices, one connectivity shared by every body). Metres, y up, facing +z (as FAUST).
Bodies body_000 ... body_{layout.n_train - 1:03d} are the training set, the rest (up to body_{last:03d}) the test
set; test phenotypes and poses are independent draws from a random stream the training bodies do not use.

segmentation/meshes/train/body_XXX.ply, segmentation/meshes/test/body_XXX.ply
segmentation/labels/train/body_XXX.txt, segmentation/labels/test/body_XXX.txt
    one part label per vertex (0-based), in the order of segmentation/labels/class_names.txt:
    {', '.join(f'{i} {name}' for i, name in enumerate(HUMAN_PART_NAMES))}
    (the 8 parts of the human-segmentation benchmark of Maron et al. 2017, left and right merged).
correspondence/training/registrations/tr_reg_XXX.ply
    the same meshes under FAUST's names (tr_reg_XXX = body_XXX): the correspondence class of a vertex is
    its index. Split: 000-{layout.n_train - 1:03d} train, {layout.n_train:03d}-{last:03d} test.
Read them with zernet's configs bodies_segmentation.yaml and bodies_correspondence.yaml.
"""
