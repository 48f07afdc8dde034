"""Vertex fans of a triangle mesh: corner angles, the intrinsic angle around each vertex, and its map to
the tangent plane (compiled with numba).

The faces around a vertex ``v`` form its *fan*: wedges ``(v, a, b)`` (the face's corners in its own
order, starting at ``v``), each with its corner angle ``α`` at ``v``. Walking the wedges in order
(``b`` of one wedge is ``a`` of the next) gives the *intrinsic angle* around ``v``: a direction inside
wedge ``w`` at angle ``t`` from the edge ``v → a`` has the angle

    ``start[w] + scale[v] · t``,

where ``start`` accumulates the scaled corner angles of the wedges before ``w`` and ``scale[v] =
2π / Σ α`` for an interior vertex (the angle defect spread evenly, as in the geodesic polar coordinates
of Melvær and Reimers 2012) and ``min(1, 2π / Σ α)`` for a boundary vertex, whose fan is open. The first
wedge of the walk starts at the tangent-plane angle of its edge ``v → a`` (measured in the vertex frame,
from ``e1`` towards ``e2``), so the intrinsic angle is close to the tangent-plane angle.

Intrinsic angles are what a front unfolds consistently: across a wedge they are linear in the unfolded
angle, so interpolating them along the front is exact on a cone. :func:`tangent_angle_of` maps an
intrinsic angle back to the tangent-plane angle of the same direction (the direction inside its wedge,
projected to the tangent plane), the convention of the frames and of the transport angles.

A vertex whose fan is not one ordered walk (non-manifold, inconsistently oriented faces) gets wedges
that start at the tangent-plane angle of whichever of their edges comes first counterclockwise (a wedge
of a flipped face is *reversed*: it runs from ``v → b`` to ``v → a``), with one scale per vertex: still
continuous inside each wedge, no longer exact on a cone.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["VertexFans", "corner_angles", "vertex_fans", "tangent_angle_of"]


class VertexFans:
    """The wedges of every vertex and their intrinsic start angles.

    Attributes:
        wedge_start: (N + 1,) CSR offsets; vertex ``v`` owns wedges ``wedge_start[v]:wedge_start[v + 1]``.
        wedge_face: (W,) face of each wedge (W = 3 F).
        wedge_corner: (W,) corner (0, 1, 2) of the vertex in that face.
        start_angle: (W,) intrinsic angle of the wedge's edge ``v → a``.
        scale: (N,) intrinsic angle per unit of unfolded angle at each vertex.
        corner: (F, 3) corner angles of every face.
        ordered: (N,) True where the fan is one ordered walk (exact on a cone).
        reversed: (W,) True for a wedge that runs from ``v → b`` to ``v → a`` (only where not ordered).
    """

    def __init__(self, wedge_start, wedge_face, wedge_corner, start_angle, scale, corner, ordered, reversed_):
        self.wedge_start = wedge_start
        self.wedge_face = wedge_face
        self.wedge_corner = wedge_corner
        self.start_angle = start_angle
        self.scale = scale
        self.corner = corner
        self.ordered = ordered
        self.reversed = reversed_


def corner_angles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) interior angle of every face at each of its corners (radians; 0 for a degenerate corner)."""
    corners = vertices[faces]
    out = np.empty(faces.shape, dtype=np.float64)
    for c in range(3):
        u = corners[:, (c + 1) % 3] - corners[:, c]
        w = corners[:, (c + 2) % 3] - corners[:, c]
        out[:, c] = np.arctan2(np.linalg.norm(np.cross(u, w), axis=1), np.einsum("fi,fi->f", u, w))
    return out


def vertex_fans(vertices: np.ndarray, faces: np.ndarray, frames: np.ndarray) -> VertexFans:
    """The fans of every vertex of a triangle mesh (module docstring).

    Args:
        vertices: (N, 3) float64.
        faces: (F, 3) int64.
        frames: (N, 3, 3) rows ``(e1, e2, n)``.

    Returns:
        :class:`VertexFans`.
    """
    n = vertices.shape[0]
    vertex = faces.ravel()
    order = np.argsort(vertex, kind="stable").astype(np.int64)
    wedge_start = np.searchsorted(vertex[order], np.arange(n + 1)).astype(np.int64)
    wedge_face = (order // 3).astype(np.int64)
    wedge_corner = (order % 3).astype(np.int64)
    corner = corner_angles(vertices, faces)
    start_angle, scale, ordered, reversed_ = _walk_fans(
        np.ascontiguousarray(vertices, dtype=np.float64), np.ascontiguousarray(faces, dtype=np.int64),
        np.ascontiguousarray(frames, dtype=np.float64), wedge_start, wedge_face, wedge_corner, corner,
    )  # fmt: skip
    return VertexFans(wedge_start, wedge_face, wedge_corner, start_angle, scale, corner, ordered, reversed_)


@numba.njit(cache=True, nogil=True, inline="always")
def _projected_angle(vertices, frames, v, q):
    """Tangent-plane angle at ``v`` of the edge ``v → q``."""
    dx = vertices[q, 0] - vertices[v, 0]
    dy = vertices[q, 1] - vertices[v, 1]
    dz = vertices[q, 2] - vertices[v, 2]
    along_e1 = dx * frames[v, 0, 0] + dy * frames[v, 0, 1] + dz * frames[v, 0, 2]
    along_e2 = dx * frames[v, 1, 0] + dy * frames[v, 1, 1] + dz * frames[v, 1, 2]
    return np.arctan2(along_e2, along_e1)


@numba.njit(cache=True, nogil=True)
def _walk_fans(vertices, faces, frames, wedge_start, wedge_face, wedge_corner, corner):
    """Start angles, scales and the ordered flags of all fans (see :func:`vertex_fans`)."""
    n = wedge_start.shape[0] - 1
    n_wedges = wedge_face.shape[0]
    start_angle = np.zeros(n_wedges)
    scale = np.ones(n)
    ordered = np.zeros(n, dtype=np.bool_)
    reversed_ = np.zeros(n_wedges, dtype=np.bool_)
    visited = np.zeros(n_wedges, dtype=np.bool_)
    for v in range(n):
        lo, hi = wedge_start[v], wedge_start[v + 1]
        if hi == lo:
            continue
        # The first wedge: one whose edge v -> a is no other wedge's v -> b (a boundary), else any.
        first = lo
        for w in range(lo, hi):
            a = faces[wedge_face[w], (wedge_corner[w] + 1) % 3]
            shared = False
            for x in range(lo, hi):
                if faces[wedge_face[x], (wedge_corner[x] + 2) % 3] == a:
                    shared = True
                    break
            if not shared:
                first = w
                break
        total = 0.0
        count = 0
        w = first
        while w >= 0 and not visited[w]:
            visited[w] = True
            start_angle[w] = total  # unscaled for now
            total += corner[wedge_face[w], wedge_corner[w]]
            count += 1
            b = faces[wedge_face[w], (wedge_corner[w] + 2) % 3]
            following = -1
            for x in range(lo, hi):
                if not visited[x] and faces[wedge_face[x], (wedge_corner[x] + 1) % 3] == b:
                    following = x
                    break
            w = following
        last_b = -1  # the b of the last wedge walked: the fan is closed when it is the first wedge's a
        for x in range(lo, hi):
            if visited[x] and start_angle[x] + corner[wedge_face[x], wedge_corner[x]] >= total - 1e-12:
                last_b = faces[wedge_face[x], (wedge_corner[x] + 2) % 3]
        closed = last_b == faces[wedge_face[first], (wedge_corner[first] + 1) % 3]
        if count == hi - lo and total > 0.0:
            ordered[v] = True
            s = 2.0 * np.pi / total
            scale[v] = s if closed else min(1.0, s)
            offset = _projected_angle(vertices, frames, v, faces[wedge_face[first], (wedge_corner[first] + 1) % 3])
            for x in range(lo, hi):
                start_angle[x] = offset + scale[v] * start_angle[x]
        else:  # not one walk: each wedge on its own, from its counterclockwise-first edge
            ratio, weight = 0.0, 0.0
            for x in range(lo, hi):
                f, c = wedge_face[x], wedge_corner[x]
                begin = _projected_angle(vertices, frames, v, faces[f, (c + 1) % 3])
                end = _projected_angle(vertices, frames, v, faces[f, (c + 2) % 3])
                span = (end - begin + np.pi) % (2.0 * np.pi) - np.pi
                reversed_[x] = span < 0.0
                start_angle[x] = end if span < 0.0 else begin
                visited[x] = True
                ratio += abs(span)
                weight += corner[f, c]
            scale[v] = ratio / weight if weight > 0.0 else 1.0
    return start_angle, scale, ordered, reversed_


@numba.njit(cache=True, nogil=True)
def tangent_angle_of(
    v, theta, vertices, faces, frames, wedge_start, wedge_face, wedge_corner, start_angle, scale, corner, reversed_
):
    """The tangent-plane angle at vertex ``v`` of the direction with intrinsic angle ``theta``.

    The wedge holding ``theta`` is found, the direction is rebuilt inside that face (at unfolded angle
    ``(theta - start) / scale`` from its first edge, ``v → a``, or ``v → b`` when reversed) and projected to ``v``'s tangent plane. An angle
    in the gap of an open fan goes to the nearer boundary edge.
    """
    best_gap, best_w, best_t = np.inf, -1, 0.0
    s = scale[v]
    for w in range(wedge_start[v], wedge_start[v + 1]):
        f, c = wedge_face[w], wedge_corner[w]
        span = s * corner[f, c]
        rel = (theta - start_angle[w]) % (2.0 * np.pi)
        if rel <= span:
            best_w, best_t, best_gap = w, rel / s, 0.0
            break
        gap_before = 2.0 * np.pi - rel  # theta just before the wedge's first edge
        gap_after = rel - span  # theta just after its second edge
        if gap_before < best_gap:
            best_gap, best_w, best_t = gap_before, w, 0.0
        if gap_after < best_gap:
            best_gap, best_w, best_t = gap_after, w, corner[f, c]
    if best_w < 0:
        return theta
    f, c = wedge_face[best_w], wedge_corner[best_w]
    a, b = faces[f, (c + 1) % 3], faces[f, (c + 2) % 3]
    if reversed_[best_w]:
        a, b = b, a
    ux = vertices[a, 0] - vertices[v, 0]
    uy = vertices[a, 1] - vertices[v, 1]
    uz = vertices[a, 2] - vertices[v, 2]
    length = np.sqrt(ux * ux + uy * uy + uz * uz)
    if length <= 0.0:
        return theta
    ux, uy, uz = ux / length, uy / length, uz / length
    wx = vertices[b, 0] - vertices[v, 0]
    wy = vertices[b, 1] - vertices[v, 1]
    wz = vertices[b, 2] - vertices[v, 2]
    along = wx * ux + wy * uy + wz * uz
    wx, wy, wz = wx - along * ux, wy - along * uy, wz - along * uz
    length = np.sqrt(wx * wx + wy * wy + wz * wz)
    if length <= 0.0:
        return theta
    wx, wy, wz = wx / length, wy / length, wz / length
    ct, st = np.cos(best_t), np.sin(best_t)
    dx, dy, dz = ct * ux + st * wx, ct * uy + st * wy, ct * uz + st * wz
    along_e1 = dx * frames[v, 0, 0] + dy * frames[v, 0, 1] + dz * frames[v, 0, 2]
    along_e2 = dx * frames[v, 1, 0] + dy * frames[v, 1, 1] + dz * frames[v, 1, 2]
    return np.arctan2(along_e2, along_e1)
