"""The shared connectivity of generated bodies (:class:`BodyTopology`) and its per-vertex part labels.

A topology is built once per name from an anny model (see :mod:`zernet.data.bodies` for the names and the
part table): anny's template with the pockets no scan has (the inside of the mouth, the eye sockets:
:data:`CAVITIES`) cut out and their openings closed, its largest connected component (the eyeballs and
tongue, separate parts, removed), optionally decimated to FAUST's size with every kept vertex expressed in
barycentric coordinates of a template triangle. Part and side labels come from the model's skinning weights, interpolated like positions.

This module is the only place ``anny`` is imported (:func:`import_anny`), lazily; ``fast_simplification``
is imported only for the ``faust`` topology. Both belong to the ``bodies`` extra.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from zernet.data.dataset import DatasetError
from zernet.data.segmentation import HUMAN_PART_NAMES
from zernet.geometry import Surface, validate_surface

__all__ = [
    "TOPOLOGIES",
    "PART_BONES",
    "FAUST_FACES",
    "MISSING_EXTRA_MESSAGE",
    "TOPOLOGY_ARRAYS",
    "CAVITIES",
    "BodyTopology",
    "import_anny",
    "part_of_bone",
    "side_of_bone",
    "largest_component",
    "cavity_faces",
    "boundary_loops",
    "close_openings",
    "closest_barycentric",
    "decimate_to_faust",
    "labels_from_weights",
    "build_topology",
]

#: Topology name -> anny topology it is built on (see :mod:`zernet.data.bodies`).
TOPOLOGIES = {
    "faust": "anny",
    "full": "anny",
    "coarse-1229": "notoes_collapse10pc",
    "coarse-615": "notoes_collapse5pc",
    "coarse-369": "notoes_collapse3pc",
}
FAUST_FACES = 13776  # 6890 vertices on a closed genus-0 surface
MISSING_EXTRA_MESSAGE = "human bodies need the optional dependency anny: pip install 'zernet[bodies]'"
#: Regions of anny's full template (its texture segmentation) that no scan has: the inside of the mouth
#: (behind the lips, 4 cm deep) and the eye sockets behind the eyeballs (2.5 cm deep). Each is a pocket
#: opening at the lips or the eyelids; :func:`build_topology` cuts them out and closes the openings.
#: anny's collapsed (coarse) topologies carry no segmentation and stay as shipped.
CAVITIES = ("mouth_cavity", "eye_cavity.L", "eye_cavity.R")
#: The arrays of a topology as stored in its cache file, in the constructor's order after the name.
TOPOLOGY_ARRAYS = ("corners", "weights", "faces", "parts", "sides")

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


def import_anny():
    """anny, or a DatasetError naming the extra (the only place anny is imported).

    anny's kernel library (warp) reports its start-up and every kernel load at INFO level: unless the
    caller chose a level already, only its warnings and errors are shown.
    """
    try:
        import warp

        if warp.config.log_level == warp.LOG_INFO:
            warp.config.log_level = warp.LOG_WARNING
        import anny
    except ImportError as error:
        raise DatasetError(MISSING_EXTRA_MESSAGE) from error
    return anny


def part_of_bone(bone: str) -> int:
    """The part (0-7, HUMAN_PART_NAMES order) of an anny bone name; ValueError for an unknown bone."""
    for part, prefixes in PART_BONES.items():
        if bone.startswith(prefixes):
            return part
    raise ValueError(f"anny bone {bone!r} belongs to no part of PART_BONES")


def side_of_bone(bone: str) -> int:
    """+1 for the body's left (.L), -1 for its right (.R), 0 for the midline."""
    return 1 if bone.endswith(".L") else -1 if bone.endswith(".R") else 0


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


def largest_component(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """(kept template vertices in template order, faces renumbered onto them) of the largest component."""
    import trimesh  # here, not at start-up

    mesh = trimesh.Trimesh(np.zeros((n_vertices, 3)), faces, process=False)
    components = trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(len(faces)), min_len=1)
    kept_faces = faces[np.sort(max(components, key=len))]
    kept = np.unique(kept_faces)
    renumber = np.full(n_vertices, -1, dtype=np.int64)
    renumber[kept] = np.arange(len(kept))
    return kept, renumber[kept_faces]


def cavity_faces(model) -> np.ndarray:
    """(F,) True for the faces of ``model.get_triangular_faces()`` in :data:`CAVITIES` (anny's full template)."""
    import_anny()
    from anny.face_segmentation import get_face_segmentation_mask

    if len(model.faces) != len(model.get_triangular_faces()):
        raise ValueError("cavity faces are read on anny's triangle template, whose faces are its triangles")
    return np.asarray(get_face_segmentation_mask(model, list(CAVITIES)), dtype=bool)


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """The holes of an oriented triangle mesh: each a loop of vertices in the order of its faces' edges."""
    half_edges = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    present = set(map(tuple, half_edges.tolist()))
    following = {a: b for a, b in half_edges.tolist() if (b, a) not in present}
    loops = []
    while following:
        start = next(iter(following))
        loop = [start]
        vertex = following.pop(start)
        while vertex != start:
            loop.append(vertex)
            vertex = following.pop(vertex)
        loops.append(np.asarray(loop, dtype=np.int64))
    return loops


def _zip_loop(loop: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Triangles closing one hole like a zip: the loop is cut at its two ends along its longest direction
    (the corners of the mouth, of an eyelid) and the two sides are joined in the order they run along it.
    Each triangle is oriented against the loop, so the closed surface keeps one orientation."""
    points = vertices[loop]
    centred = points - points.mean(0)
    along = centred @ np.linalg.svd(centred, full_matrices=False)[2][0]
    loop, along = np.roll(loop, -int(along.argmin())), np.roll(along, -int(along.argmin()))
    n, end = len(loop), int(along.argmax())
    if end in (1, n - 1):  # the two ends are neighbours (a tiny hole): a fan from one of them
        triangles = [(0, k, k + 1) for k in range(1, n - 1)]
    else:
        first = list(range(0, end + 1))  # loop positions from one end to the other along one side
        second = [0, *range(n - 1, end, -1)]  # and along the other side, up to the other end's neighbour
        triangles = [(0, first[1], second[1])]
        i, j = 1, 1
        while i < len(first) - 1 or j < len(second) - 1:
            if j == len(second) - 1 or (i < len(first) - 1 and along[first[i + 1]] <= along[second[j + 1]]):
                triangles.append((first[i], first[i + 1], second[j]))
                i += 1
            else:
                triangles.append((first[i], second[j], second[j + 1]))
                j += 1
    # Loop positions in increasing order follow the loop; reversed, they oppose it.
    return np.array([loop[sorted(triangle, reverse=True)] for triangle in triangles], dtype=np.int64)


def close_openings(vertices: np.ndarray, faces: np.ndarray, removed: np.ndarray) -> np.ndarray:
    """The faces with ``removed`` (F,) cut out and every hole this leaves closed (:func:`_zip_loop`); the
    vertices only the removed faces used are left unreferenced (no new vertex)."""
    kept = faces[~removed]
    holes_before = {tuple(sorted(loop.tolist())) for loop in boundary_loops(faces)}
    new_holes = [loop for loop in boundary_loops(kept) if tuple(sorted(loop.tolist())) not in holes_before]
    return np.concatenate([kept, *(_zip_loop(loop, vertices) for loop in new_holes)])


def closest_barycentric(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, neighbours: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """For each point, (the triangle of the mesh closest to it, its barycentric coordinates there).

    Candidates are the triangles around the ``neighbours`` nearest mesh vertices, exact among those.
    """
    import trimesh  # here, not at start-up

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


def decimate_to_faust(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(corners (6890, 3) into ``vertices``, barycentric weights, faces (13776, 3)) of the decimated body."""
    try:
        import fast_simplification  # optional, part of the bodies extra
    except ImportError as error:
        raise DatasetError(MISSING_EXTRA_MESSAGE + " (the 'faust' topology also needs fast-simplification)") from error
    # agg=3: fewer sliver triangles than the default 7, and it still reaches the target count.
    points, reduced_faces = fast_simplification.simplify(
        vertices, faces.astype(np.int32), target_count=FAUST_FACES, agg=3.0
    )
    triangles, barycentric = closest_barycentric(vertices, faces, points)
    return faces[triangles], barycentric, reduced_faces.astype(np.int64)


def labels_from_weights(model, corners: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(parts, sides) per topology vertex from the model's skinning weights, interpolated like positions."""
    bones = list(model.bone_labels)
    bone_weights = model.vertex_bone_weights.detach().cpu().numpy().astype(np.float64)
    bone_ids = model.vertex_bone_indices.detach().cpu().numpy().astype(np.int64)
    bone_part = np.array([part_of_bone(bone) for bone in bones])
    bone_side = np.array([side_of_bone(bone) for bone in bones], dtype=np.float64)
    per_part = np.zeros((len(bone_weights), len(HUMAN_PART_NAMES)))
    np.add.at(
        per_part,
        (np.arange(len(bone_weights))[:, None].repeat(bone_ids.shape[1], 1), bone_part[bone_ids]),
        bone_weights,
    )
    side_weight = (bone_weights * bone_side[bone_ids]).sum(1)
    parts = np.einsum("nk,nkp->np", weights, per_part[corners]).argmax(1).astype(np.int64)
    side = np.einsum("nk,nk->n", weights, side_weight[corners])
    sides = np.where(side > 0.5, 1, np.where(side < -0.5, -1, 0)).astype(np.int64)
    return parts, sides


def build_topology(name: str, model) -> BodyTopology:
    """The topology ``name`` of :data:`TOPOLOGIES`, built on ``model`` (an anny model of its base)."""
    template = model.template_vertices.detach().cpu().numpy().astype(np.float64)
    all_faces = model.get_triangular_faces().detach().cpu().numpy().astype(np.int64)
    if TOPOLOGIES[name] == "anny":  # the full template: its mouth and eye sockets closed
        all_faces = close_openings(template, all_faces, cavity_faces(model))
    kept, faces = largest_component(all_faces, len(template))
    if name == "faust":
        local_corners, weights, faces = decimate_to_faust(template[kept], faces)
        corners = kept[local_corners]
    else:
        corners = np.repeat(kept[:, None], 3, axis=1)
        weights = np.tile([1.0, 0.0, 0.0], (len(kept), 1))
    parts, sides = labels_from_weights(model, corners, weights)
    topology = BodyTopology(name, corners, weights, faces, parts, sides)
    validate_surface(Surface(topology.place(template), faces, name=f"body topology {name!r}"))
    return topology
