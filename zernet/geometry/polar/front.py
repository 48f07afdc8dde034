"""Geodesic polar coordinates by local front propagation over the mesh (compiled with numba).

From every vertex ``p`` a front is propagated over the triangles, in order of increasing distance (like
Dijkstra's algorithm), until it passes ``r0``: the geodesic polar coordinates update of Melvær and
Reimers (2012, "Geodesic polar coordinates on polygonal meshes"), a close relative of the discrete
exponential map of Schmidt, Grimm and Wyvill (2006). Each vertex carries a distance ``U`` and an
*intrinsic* angle ``θ`` (:mod:`zernet.geometry.polar.fans`: corner angles accumulated around ``p`` and scaled
to 2π, so the angle is linear in the unfolded angle across every wedge and exact on a cone):

* the one-ring of ``p`` is exact: ``U`` is the edge length and ``θ`` the fan angle of the edge;
* a triangle ``(i, j, k)`` with ``i, j`` final updates ``k``: it is unfolded into the plane from its edge
  lengths, the virtual source ``s`` is the point at distances ``U_i, U_j`` from ``i, j`` on the far side
  of edge ``ij``, and if the straight line from ``s`` to ``k`` crosses the edge, ``U_k = |k - s|`` and
  ``θ_k`` is interpolated between ``θ_i`` and ``θ_j`` by the angle the line makes at ``s`` (exact on a
  plane or a cone). Otherwise the geodesic passes through a vertex: ``U_k = U_i + |ik|`` with
  ``θ_k = θ_i`` (or through ``j``);
* ``U_k`` keeps the smallest value offered, so a thin tube is measured the shorter way round.

Then every sample in a triangle whose corners the front reached gets its ``(r, θ)`` the same way from
the unfolded triangle at the edge whose virtual source is nearest (or the path through a corner), and its
intrinsic angle is turned into the tangent-plane angle of the same direction
(:func:`zernet.geometry.polar.fans.tangent_angle_of`); a sample in a triangle around ``p`` gets the straight
segment (exact). Because the front only moves across shared edges, it never jumps to the far side of a
fold, to a touching limb or to another connected component, and it stops at open boundaries. The front
runs until every triangle that can hold a sample within ``r0`` has all its corners final, whatever the
length of its edges (longer than ``r0`` included, around ``p`` too), but at most one median longest edge
past ``r0``: beyond that a corner keeps its tentative distance (see ``_propagate``).

The kernel is compiled on first use and cached on disk (``numba.njit(cache=True)``), so later processes
load it instead of compiling. Sources are split over threads (the kernel releases the GIL).
"""

from __future__ import annotations

import numba
import numpy as np

from zernet.geometry.polar.fans import tangent_angle_of, vertex_fans
from zernet.geometry.sampling import SurfaceSamples
from zernet.geometry.surface import Surface, SurfaceError
from zernet.threads import available_cores, thread_map

__all__ = ["front_polar"]

# Relative tolerance of the test that the line from the virtual source crosses the unfolded edge.
_CROSSING_TOLERANCE = 1e-9
# The front runs past r0 by at most this many median longest edges (see _propagate).
_EXTENSION_EDGES = 1.5
# Which path gave a vertex its distance in a front update (see _propagate).
_THROUGH_I, _UNFOLDED, _THROUGH_OTHER = 0, 1, 2
# Columns of the per-side wedge records (see _wedge_records).
_TO_TARGET, _EDGE, _TARGET_X, _TARGET_Y, _TARGET_REACH = 0, 1, 2, 3, 4


def front_polar(
    surface: Surface,
    samples: SurfaceSamples,
    frames: np.ndarray,
    r0: float,
    n_threads: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Geodesic polar coordinates of the samples within ``r0`` of every vertex, by front propagation.

    Args:
        surface: triangle mesh with N vertices.
        samples: M samples on it (:func:`zernet.geometry.sample_surface`).
        frames: (N, 3, 3) per-vertex frames, rows ``(e1, e2, n)`` (:func:`zernet.geometry.tangent_frames`).
        r0: patch radius (absolute units), > 0.
        n_threads: threads (``None``: the cores available to this process).

    Returns:
        ``(center, sample, radius, angle)``: (P,) int64, int64, float64, float64 pairs with
        ``radius <= r0``, sorted by centre then radius; ``angle`` in ``[-π, π)`` from ``frames[p, 0]``
        towards ``frames[p, 1]``.

    Raises:
        SurfaceError: for a point cloud (the front needs triangles), or mismatched frames.
    """
    if surface.is_point_cloud:
        raise SurfaceError(
            f"{surface.name}: the front backend needs a triangle mesh, got a point cloud "
            "(zernet.geometry.cloud_mesh.mesh_from_cloud triangulates it through its points)"
        )
    if not r0 > 0:
        raise ValueError(f"r0 must be positive, got {r0}")
    n = surface.n_vertices
    if frames.shape != (n, 3, 3):
        raise SurfaceError(f"{surface.name}: frames have shape {frames.shape}, expected ({n}, 3, 3)")
    points = np.ascontiguousarray(surface.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(surface.faces, dtype=np.int64)
    frames = np.ascontiguousarray(frames, dtype=np.float64)
    fans = vertex_fans(points, faces, frames)
    face_sample_start, face_samples = _face_samples(samples.face_index, len(faces))
    corners = points[faces]
    # opposite[f, c]: length of the edge of face f opposite its corner c.
    opposite = np.linalg.norm(np.roll(corners, -1, axis=1) - np.roll(corners, 1, axis=1), axis=2)
    reach = _sample_reach(corners, samples.points, samples.face_index)
    arguments = (
        points, faces, fans.wedge_start, fans.wedge_face, fans.wedge_corner, fans.start_angle, fans.scale,
        fans.corner, fans.reversed, *_wedge_records(faces, fans.wedge_face, fans.wedge_corner, opposite, reach), reach,
        face_sample_start, face_samples,
        np.ascontiguousarray(samples.points, dtype=np.float64), frames, float(r0),
        _EXTENSION_EDGES * float(np.median(opposite.max(axis=1))),
    )  # fmt: skip
    n_threads = available_cores() if n_threads is None else n_threads
    chunks = [c for c in np.array_split(np.arange(n, dtype=np.int64), max(1, 4 * n_threads)) if len(c)]
    results = thread_map(lambda chunk: _front_chunk(chunk, *arguments), chunks, n_threads)
    if not results:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    # The chunks are in vertex order and each is sorted by (centre, radius).
    center, sample, radius, angle = (np.concatenate(parts) for parts in zip(*results))
    return center, sample, radius, angle


def _sample_reach(corners: np.ndarray, sample_points: np.ndarray, face_index: np.ndarray) -> np.ndarray:
    """(F, 3) largest distance from each corner of a face to the samples in it (-1 for a face without samples).

    A sample ``x`` in face ``f`` within ``r0`` of the source has every corner ``c`` within
    ``r0 + |x - c| <= r0 + reach[f, c]`` (triangle inequality), which bounds how far the front must run.
    """
    reach = np.full(corners.shape[:2], -1.0)
    distance = np.linalg.norm(sample_points[:, None, :] - corners[face_index], axis=2)  # (M, 3)
    np.maximum.at(reach, face_index, distance)
    return reach


def _wedge_records(faces, wedge_face, wedge_corner, opposite, reach):
    """What a front update across each wedge needs, one record per wedge, so that the wedges of a vertex
    are read in one sweep of memory.

    Wedge ``w`` is vertex ``i`` at corner ``c`` of face ``f``; its side 0 updates the corner ``a = (c + 1) %
    3`` from ``i`` and the other corner ``b = (c + 2) % 3``, its side 1 updates ``b`` from ``i`` and ``a``.

    Returns:
        ``(target, side_geometry, far_edge, reach_at)``: (W, 2) the target vertex of each side; (W, 2, 5)
        per side the lengths ``|i target|`` and ``|i other|``, the target unfolded into the plane of edge
        ``i → other`` (``i`` at the origin, ``other`` at ``(|i other|, 0)``, ``y >= 0``) and the target's
        ``reach`` (columns ``_TO_TARGET, _EDGE, _TARGET_X, _TARGET_Y, _TARGET_REACH``); (W,) the length
        ``|a b|``; (W,) the ``reach`` of corner ``c``.
    """
    n_wedges = len(wedge_face)
    target = np.empty((n_wedges, 2), dtype=np.int64)
    side_geometry = np.empty((n_wedges, 2, 5))
    for side in range(2):
        target_corner = (wedge_corner + 1 + side) % 3
        other_corner = (wedge_corner + 2 - side) % 3
        to_target = opposite[wedge_face, other_corner]
        other_to_target = opposite[wedge_face, wedge_corner]
        edge = opposite[wedge_face, target_corner]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = (to_target * to_target - other_to_target * other_to_target + edge * edge) / (2.0 * edge)
        x = np.where(edge > 0.0, x, 0.0)
        target[:, side] = faces[wedge_face, target_corner]
        side_geometry[:, side, _TO_TARGET] = to_target
        side_geometry[:, side, _EDGE] = edge
        side_geometry[:, side, _TARGET_X] = x
        side_geometry[:, side, _TARGET_Y] = np.sqrt(np.maximum(to_target * to_target - x * x, 0.0))
        side_geometry[:, side, _TARGET_REACH] = reach[wedge_face, target_corner]
    return target, side_geometry, opposite[wedge_face, wedge_corner], reach[wedge_face, wedge_corner]


def _face_samples(face_index: np.ndarray, n_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR of the samples in each face."""
    order = np.argsort(face_index, kind="stable").astype(np.int64)
    start = np.searchsorted(face_index[order], np.arange(n_faces + 1)).astype(np.int64)
    return start, order


# ====================================================================== compiled kernel
@numba.njit(cache=True, nogil=True)
def _front_chunk(
    sources, points, faces, wedge_start, wedge_face, wedge_corner, start_angle, scale, corner, reversed_, wedge_target,
    side_geometry, far_edge, reach_at, reach, face_sample_start, face_samples, sample_points, frames, r0, extension,
):  # fmt: skip
    """Front propagation from each of ``sources``; returns the (center, sample, radius, angle) pairs."""
    n = points.shape[0]
    distance = np.full(n, np.inf)
    angle = np.zeros(n)
    final = np.zeros(n, dtype=np.bool_)
    exact = np.zeros(n, dtype=np.bool_)  # the source and its one-ring: never overwritten
    touched = np.empty(n, dtype=np.int64)
    face_stamp = np.full(faces.shape[0], -1, dtype=np.int64)
    heap_key = np.empty(64)
    heap_vertex = np.empty(64, dtype=np.int64)
    capacity = max(1024, 64 * len(sources))
    out_center = np.empty(capacity, dtype=np.int64)
    out_sample = np.empty(capacity, dtype=np.int64)
    out_radius = np.empty(capacity)
    out_angle = np.empty(capacity)
    count = 0
    for p in sources:
        first = count  # this source's pairs are out_*[first:count]
        n_touched, heap_key, heap_vertex = _propagate(
            p, wedge_start, wedge_face, wedge_corner, start_angle, scale, corner, reversed_, wedge_target, side_geometry,
            far_edge, reach_at, r0, extension, distance, angle, final, exact, touched, heap_key, heap_vertex,
        )  # fmt: skip
        for t in range(n_touched):
            v = touched[t]
            if not final[v]:
                continue
            for slot in range(wedge_start[v], wedge_start[v + 1]):
                f = wedge_face[slot]
                if face_stamp[f] == p or face_sample_start[f] == face_sample_start[f + 1]:
                    continue
                face_stamp[f] = p
                a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
                if not (np.isfinite(distance[a]) and np.isfinite(distance[b]) and np.isfinite(distance[c])):
                    continue  # a corner the front never reached
                if distance[a] > r0 + reach[f, 0] or distance[b] > r0 + reach[f, 1] or distance[c] > r0 + reach[f, 2]:
                    continue  # no sample of the face is within r0
                adjacent = a == p or b == p or c == p
                for slot_sample in range(face_sample_start[f], face_sample_start[f + 1]):
                    s = face_samples[slot_sample]
                    x, y, z = sample_points[s, 0], sample_points[s, 1], sample_points[s, 2]
                    if adjacent:  # straight from the source
                        r, theta = _distance(points, p, x, y, z), _tangent_angle(points, frames, p, x, y, z)
                    else:
                        r, theta = _sample_polar(f, x, y, z, points, faces, distance, angle, r0)
                        if r > r0:
                            continue
                        theta = tangent_angle_of(
                            p, theta, points, faces, frames, wedge_start, wedge_face, wedge_corner, start_angle,
                            scale, corner, reversed_,
                        )  # fmt: skip
                    if r > r0:
                        continue
                    if count == out_center.shape[0]:
                        out_center, out_sample, out_radius, out_angle = _grow(
                            out_center, out_sample, out_radius, out_angle
                        )
                    out_center[count] = p
                    out_sample[count] = s
                    out_radius[count] = r
                    out_angle[count] = _wrap(theta)
                    count += 1
        # Sorted by radius (stable) here, so the chunks come out sorted by (centre, radius) with no global sort.
        order = first + np.argsort(out_radius[first:count], kind="mergesort")
        out_sample[first:count] = out_sample[order]
        out_radius[first:count] = out_radius[order]
        out_angle[first:count] = out_angle[order]
        for t in range(n_touched):  # reset only what this source touched
            v = touched[t]
            distance[v] = np.inf
            final[v] = False
            exact[v] = False
    return out_center[:count].copy(), out_sample[:count].copy(), out_radius[:count].copy(), out_angle[:count].copy()


@numba.njit(cache=True, nogil=True)
def _propagate(
    p, wedge_start, wedge_face, wedge_corner, start_angle, scale, corner, reversed_, wedge_target, side_geometry,
    far_edge, reach_at, r0, extension, distance, angle, final, exact, touched, heap_key, heap_vertex,
):  # fmt: skip
    """Run the front from vertex ``p``; fills ``distance``, ``angle`` (intrinsic, see
    :mod:`zernet.geometry.polar.fans`), ``final`` for the touched vertices and returns their count and the
    (maybe grown) heap.

    Stopping rule: a sample ``x`` of face ``f`` within ``r0`` has every corner ``c`` within
    ``r0 + reach[f, c]`` (``reach``: the largest corner-to-sample distance in the face). So when a corner
    ``i`` of a face with samples is popped at a distance ``<= r0 + reach[f, i]``, the front is run on
    until the face's other corners ``c`` are final: past ``min(U_i + |ic|, r0 + reach[f, c])``. Faces
    without samples, and faces whose samples are all beyond ``r0``, do not extend it; long edges (even
    longer than ``r0``, also around ``p`` itself) are handled. The extension past ``r0`` is capped at
    ``extension`` (the mesh's median longest edge): a corner of a large face beyond it keeps the
    tentative distance its final neighbours gave it (an upper bound, usually already the final value).

    Label-correcting: a final vertex offered a shorter distance (in an obtuse triangle a vertex can be
    reached before the corners of the triangle its geodesic crosses) is reopened and propagated again.
    """
    n_touched = 1
    touched[0] = p
    distance[p] = 0.0
    angle[p] = 0.0
    exact[p] = True
    final[p] = True
    heap_size = 0
    bound = r0
    for slot in range(wedge_start[p], wedge_start[p + 1]):
        for side in range(2):
            q = wedge_target[slot, side]
            to_q = side_geometry[slot, side, _TO_TARGET]
            if reach_at[slot] >= 0.0:  # the face holds samples: its corners must be final
                bound = max(bound, min(to_q, r0 + min(side_geometry[slot, side, _TARGET_REACH], extension)))
            if exact[q]:
                continue
            touched[n_touched] = q
            n_touched += 1
            distance[q] = to_q
            at_end = side == 1 if not reversed_[slot] else side == 0  # q is the wedge's last edge
            angle[q] = start_angle[slot] + (scale[p] * corner[wedge_face[slot], wedge_corner[slot]] if at_end else 0.0)
            exact[q] = True
            heap_size, heap_key, heap_vertex = _heap_push(heap_key, heap_vertex, heap_size, distance[q], q)
    while heap_size > 0:
        key, i, heap_size = _heap_pop(heap_key, heap_vertex, heap_size)
        if key > distance[i] or final[i]:
            continue  # a stale entry
        if key > bound:
            break
        final[i] = True
        for slot in range(wedge_start[i], wedge_start[i + 1]):
            relevant = reach_at[slot] >= 0.0 and key <= r0 + min(reach_at[slot], extension)
            for side in range(2):
                to_target = side_geometry[slot, side, _TO_TARGET]
                if relevant:
                    bound = max(
                        bound, min(key + to_target, r0 + min(side_geometry[slot, side, _TARGET_REACH], extension))
                    )
                target, other = wedge_target[slot, side], wedge_target[slot, 1 - side]
                if exact[target]:
                    continue
                u = distance[i] + to_target
                path = _THROUGH_I
                edge, kx, ky, sx, sy = 0.0, 0.0, 0.0, 0.0, 0.0
                if final[other]:  # otherwise the path through i is an upper bound until other is final
                    edge = side_geometry[slot, side, _EDGE]
                    kx, ky = side_geometry[slot, side, _TARGET_X], side_geometry[slot, side, _TARGET_Y]
                    through, sx, sy = _unfolded_distance(distance[i], distance[other], edge, kx, ky)
                    via_other = distance[other] + far_edge[slot]
                    if through < u and through <= via_other:
                        u, path = through, _UNFOLDED
                    elif via_other < u:
                        u, path = via_other, _THROUGH_OTHER
                if u < distance[target] * (1.0 - 1e-12):
                    if not np.isfinite(distance[target]):
                        touched[n_touched] = target
                        n_touched += 1
                    distance[target] = u
                    # The angle only for an accepted update: most offers lose, and it costs three arctan2.
                    if path == _UNFOLDED:
                        angle[target] = _unfolded_angle(angle[i], angle[other], edge, sx, sy, kx, ky)
                    else:
                        angle[target] = angle[other] if path == _THROUGH_OTHER else angle[i]
                    final[target] = False
                    heap_size, heap_key, heap_vertex = _heap_push(heap_key, heap_vertex, heap_size, u, target)
    return n_touched, heap_key, heap_vertex


@numba.njit(cache=True, nogil=True, inline="always")
def _distance(points, i, x, y, z):
    """|x - points[i]|."""
    dx, dy, dz = x - points[i, 0], y - points[i, 1], z - points[i, 2]
    return np.sqrt(dx * dx + dy * dy + dz * dz)


@numba.njit(cache=True, nogil=True, inline="always")
def _tangent_angle(points, frames, p, x, y, z):
    """Angle of ``x - points[p]`` projected to p's tangent plane, from ``frames[p, 0]`` to ``frames[p, 1]``."""
    dx, dy, dz = x - points[p, 0], y - points[p, 1], z - points[p, 2]
    along_e1 = dx * frames[p, 0, 0] + dy * frames[p, 0, 1] + dz * frames[p, 0, 2]
    along_e2 = dx * frames[p, 1, 0] + dy * frames[p, 1, 1] + dz * frames[p, 1, 2]
    return np.arctan2(along_e2, along_e1)


@numba.njit(cache=True, nogil=True, inline="always")
def _wrap(angle):
    """Angle mapped to ``[-π, π)``."""
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


@numba.njit(cache=True, nogil=True)
def _unfolded_distance(ui, uj, length, kx, ky):
    """Distance to the point ``(kx, ky)`` (``ky >= 0``) from the virtual source of an edge unfolded with
    ``i`` at the origin and ``j`` at ``(length, 0)``: the source is at distances ``ui, uj`` from ``i, j``
    at y <= 0. Returns ``(distance, sx, sy)``; the distance is ``inf`` when the straight line from the
    source to the point misses the edge or the distances do not fit the edge."""
    if length <= 0.0:
        return np.inf, 0.0, 0.0
    sx = (ui * ui - uj * uj + length * length) / (2.0 * length)
    height2 = ui * ui - sx * sx
    if height2 < 0.0:
        return np.inf, 0.0, 0.0
    sy = -np.sqrt(height2)
    dx, dy = kx - sx, ky - sy
    if dy <= 0.0:
        return np.inf, 0.0, 0.0
    crossing = sx - sy * dx / dy  # where the line from the source to the point meets the edge's line
    tolerance = _CROSSING_TOLERANCE * length
    if crossing < -tolerance or crossing > length + tolerance:
        return np.inf, 0.0, 0.0
    return np.sqrt(dx * dx + dy * dy), sx, sy


@numba.njit(cache=True, nogil=True)
def _unfolded_angle(theta_i, theta_j, length, sx, sy, kx, ky):
    """Intrinsic angle at ``(kx, ky)``: ``theta_i`` and ``theta_j`` interpolated by the angle the line from
    the source makes at the source (exact when the unfolded front comes from one point)."""
    to_i = np.arctan2(-sy, -sx)
    to_j = np.arctan2(-sy, length - sx)
    to_x = np.arctan2(ky - sy, kx - sx)
    span = to_i - to_j
    ratio = (to_i - to_x) / span if abs(span) > 1e-12 else 0.0
    ratio = min(max(ratio, 0.0), 1.0)
    return theta_i + ratio * _wrap(theta_j - theta_i)


@numba.njit(cache=True, nogil=True)
def _sample_polar(f, x, y, z, points, faces, distance, angle, r0):
    """(r, intrinsic θ) of the point ``(x, y, z)`` in face ``f`` (not around the source), whose corners are
    final: the smallest distance over the virtual sources of its three edges and the paths through its
    corners. θ is left 0 when ``r > r0`` (the caller drops the point)."""
    best = np.inf
    best_corner, best_unfolded = 0, False  # the path that gave ``best``, for its angle below
    best_length, best_sx, best_sy, best_kx, best_ky = 0.0, 0.0, 0.0, 0.0, 0.0
    for c in range(3):
        i, j = faces[f, c], faces[f, (c + 1) % 3]
        ex, ey, ez = points[j, 0] - points[i, 0], points[j, 1] - points[i, 1], points[j, 2] - points[i, 2]
        length = np.sqrt(ex * ex + ey * ey + ez * ez)
        ox, oy, oz = x - points[i, 0], y - points[i, 1], z - points[i, 2]
        to_corner2 = ox * ox + oy * oy + oz * oz
        kx = (ox * ex + oy * ey + oz * ez) / length if length > 0.0 else 0.0
        ky = np.sqrt(max(to_corner2 - kx * kx, 0.0))
        r, sx, sy = _unfolded_distance(distance[i], distance[j], length, kx, ky)
        if r < best:
            best, best_corner, best_unfolded = r, c, True
            best_length, best_sx, best_sy, best_kx, best_ky = length, sx, sy, kx, ky
        via = distance[i] + np.sqrt(to_corner2)
        if via < best:
            best, best_corner, best_unfolded = via, c, False
    if best > r0:
        return best, 0.0
    i = faces[f, best_corner]
    if not best_unfolded:
        return best, angle[i]
    j = faces[f, (best_corner + 1) % 3]
    return best, _unfolded_angle(angle[i], angle[j], best_length, best_sx, best_sy, best_kx, best_ky)


@numba.njit(cache=True, nogil=True)
def _grow(center, sample, radius, angle):
    """The output arrays with twice the room."""
    size = center.shape[0]
    bigger = (np.empty(2 * size, np.int64), np.empty(2 * size, np.int64), np.empty(2 * size), np.empty(2 * size))
    bigger[0][:size] = center
    bigger[1][:size] = sample
    bigger[2][:size] = radius
    bigger[3][:size] = angle
    return bigger


@numba.njit(cache=True, nogil=True)
def _heap_push(keys, values, size, key, value):
    """Push onto a binary min-heap kept in (keys, values); grows the arrays when full."""
    if size == keys.shape[0]:
        grown_keys = np.empty(2 * size)
        grown_values = np.empty(2 * size, dtype=np.int64)
        grown_keys[:size] = keys
        grown_values[:size] = values
        keys, values = grown_keys, grown_values
    position = size
    while position > 0:
        parent = (position - 1) // 2
        if keys[parent] <= key:
            break
        keys[position] = keys[parent]
        values[position] = values[parent]
        position = parent
    keys[position] = key
    values[position] = value
    return size + 1, keys, values


@numba.njit(cache=True, nogil=True)
def _heap_pop(keys, values, size):
    """Pop the smallest (key, value) of the heap; returns them and the new size."""
    key, value = keys[0], values[0]
    size -= 1
    last_key, last_value = keys[size], values[size]
    position = 0
    while True:
        child = 2 * position + 1
        if child >= size:
            break
        if child + 1 < size and keys[child + 1] < keys[child]:
            child += 1
        if keys[child] >= last_key:
            break
        keys[position] = keys[child]
        values[position] = values[child]
        position = child
    keys[position] = last_key
    values[position] = last_value
    return key, value, size
