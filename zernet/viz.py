"""Pictures as PNG files (matplotlib, Agg backend: no screen needed).

- :func:`render_surface`: a surface coloured by a per-vertex field, seen from several views side by side.
- :func:`render_side_by_side`: several surfaces next to each other on one colour scale (matching pictures).
- :func:`render_comparison`: rows of prediction, ground truth and error, same views.
- :func:`plot_error_curve`: the Princeton geodesic error curve(s) of correspondence.
- :func:`plot_training_curves`: loss and metrics per epoch from a training history.

Camera convention: the surface's ``up`` axis (default ``"y"``, the usual convention of PLY/OBJ scans such
as FAUST) points up in every view; "front" looks at the surface from its +z side (for ``up="y"``), "side"
from +x, "back" from -z, "top" from above. Continuous values colour each face by the mean of its three
vertex values. Labels (integers) and masks (booleans) are drawn per vertex: each triangle is split into its
three corner cells (corner, the two edge midpoints, the centroid), each coloured by its own vertex, so one
vertex with another label shows as a small patch around it, whatever its neighbours are. Everything is lit
by a light at the camera so relief is visible.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # before pyplot: render to files only, never open a window

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import colors as mcolors  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

__all__ = [
    "VIEWS",
    "render_surface",
    "render_side_by_side",
    "render_comparison",
    "plot_error_curve",
    "plot_training_curves",
]

#: Named views: (elevation, azimuth) in degrees of matplotlib's camera, in plot coordinates (see _to_plot).
VIEWS = {
    "front": (10.0, -90.0),
    "side": (10.0, 0.0),
    "back": (10.0, 90.0),
    "left": (10.0, 180.0),
    "top": (89.0, -90.0),
    "bottom": (-89.0, -90.0),
}

# Above this many faces, an even subset is drawn (matplotlib's painter's algorithm is slow); FAUST (13776)
# and the aneurysm meshes (up to ~16000) are drawn whole.
_MAX_FACES = 40000
_PANEL_INCHES = 3.2
#: The two colours of a right/wrong mask: light grey for right, red for wrong.
_RIGHT_WRONG = mcolors.ListedColormap(["#d9d9d9", "#d62728"])


def _to_plot(points: np.ndarray, up: str) -> np.ndarray:
    """Map surface coordinates to matplotlib's z-up plot coordinates with ``up`` pointing up.

    For up="y": plot (X, Y, Z) = (x, -z, y), a proper rotation, so the camera at azimuth -90° sits on +z.
    """
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    if up == "y":
        return np.stack([x, -z, y], axis=1)
    if up == "z":
        return np.stack([x, y, z], axis=1)
    if up == "x":
        return np.stack([y, z, x], axis=1)
    raise ValueError(f"up must be 'x', 'y' or 'z', got {up!r}")


def _camera_direction(elev: float, azim: float) -> np.ndarray:
    """Unit vector from the scene towards matplotlib's camera, in plot coordinates."""
    e, a = np.radians(elev), np.radians(azim)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def _is_labels(values: np.ndarray) -> bool:
    return np.issubdtype(values.dtype, np.integer) or values.dtype == bool


def _corner_cells(triangles: np.ndarray) -> np.ndarray:
    """(3F, 4, 3) corner cells of (F, 3, 3) triangles: for each corner, the quadrilateral corner -> middle of
    the next edge -> centroid -> middle of the previous edge. Together they tile each triangle."""
    centroid = triangles.mean(axis=1)
    cells = []
    for i in range(3):
        corner, after, before = triangles[:, i], triangles[:, (i + 1) % 3], triangles[:, (i + 2) % 3]
        cells.append(np.stack([corner, (corner + after) / 2, centroid, (corner + before) / 2], axis=1))
    return np.stack(cells, axis=1).reshape(-1, 4, 3)  # face-major: cells of face f are 3f, 3f+1, 3f+2


def _norm_and_cmap(values: np.ndarray, cmap, vmin, vmax, labels: bool):
    """Colour normalisation and map; labels get a discrete map with one colour per class."""
    if labels:
        n_classes = int(max(values.max(), vmax if vmax is not None else 0)) + 1
        base = plt.get_cmap(cmap if cmap is not None else ("tab10" if n_classes <= 10 else "tab20"))
        palette = [base(i % base.N) for i in range(n_classes)]
        listed = mcolors.ListedColormap(palette)
        return mcolors.BoundaryNorm(np.arange(n_classes + 1) - 0.5, n_classes), listed
    finite = values[np.isfinite(values)]
    low = vmin if vmin is not None else (finite.min() if finite.size else 0.0)
    high = vmax if vmax is not None else (finite.max() if finite.size else 1.0)
    if high <= low:
        high = low + 1e-12
    return mcolors.Normalize(low, high), plt.get_cmap(cmap or "viridis")


def _draw(ax, surface, values, norm, cmap, view: str, up: str, point_size: float | None) -> None:
    """One view of one surface on a 3D axis: equal aspect, no axes, camera-lit faces or points."""
    if view not in VIEWS:
        raise ValueError(f"unknown view {view!r}; choose from {sorted(VIEWS)}")
    elev, azim = VIEWS[view]
    points = _to_plot(np.asarray(surface.vertices, dtype=np.float64), up)
    camera = _camera_direction(elev, azim)
    faces = getattr(surface, "faces", None)
    if faces is not None:
        faces = np.asarray(faces)
        if len(faces) > _MAX_FACES:
            faces = faces[np.linspace(0, len(faces) - 1, _MAX_FACES).astype(np.int64)]
        # Back faces (pointing away from the camera) are hidden behind front faces of a closed surface
        # anyway; dropping them halves the work. Open surfaces (aneurysms) keep them so the inside shows.
        triangles = points[faces]
        normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
        length = np.linalg.norm(normals, axis=1)
        facing = (normals @ camera) / np.maximum(length, 1e-300)
        shade = 0.55 + 0.45 * np.abs(facing)  # two-sided lighting from the camera
        if _is_labels(values):  # per vertex: three corner cells per face
            triangles = _corner_cells(triangles)
            rgba = cmap(norm(values[faces].reshape(-1)))
            shade = np.repeat(shade, 3)
        else:
            rgba = cmap(norm(values[faces].mean(axis=1)))
        rgba[:, :3] *= shade[:, None]
        # Edges in the face colour hide the hairline seams antialiasing leaves between adjacent triangles.
        collection = Poly3DCollection(triangles, facecolors=rgba, edgecolors=rgba, linewidths=0.3)
        ax.add_collection3d(collection)
    else:
        size = point_size if point_size is not None else max(0.5, 4000.0 / len(points))
        ax.scatter(
            points[:, 0], points[:, 1], points[:, 2], c=cmap(norm(values)), s=size, depthshade=False, linewidths=0
        )
    centre = (points.max(axis=0) + points.min(axis=0)) / 2
    half = (points.max(axis=0) - points.min(axis=0)).max() / 2 * 1.02
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_box_aspect((1, 1, 1), zoom=1.3)
    ax.view_init(elev=elev, azim=azim)
    ax.set_proj_type("ortho")
    ax.set_axis_off()


def _colorbar(fig, axes_row, norm, cmap, labels: bool, label: str | None, class_names=None):
    mappable = plt.cm.ScalarMappable(norm=norm, cmap=cmap)
    bar = fig.colorbar(mappable, ax=axes_row, fraction=0.025, pad=0.02, shrink=0.8)
    if labels:
        n = cmap.N
        bar.set_ticks(np.arange(n))
        names = list(class_names)[:n] if class_names is not None else []
        bar.set_ticklabels(names + [str(i) for i in range(len(names), n)])
    if label:
        bar.set_label(label)
    return bar


def _check_values(surface, values, what: str) -> np.ndarray:
    if hasattr(values, "detach"):
        values = values.detach().cpu().numpy()
    values = np.asarray(values)
    if values.ndim == 2 and values.shape[1] == 1:
        values = values[:, 0]
    n = len(surface.vertices)
    if values.shape != (n,):
        raise ValueError(
            f"{getattr(surface, 'name', '<array>')}: {what} has shape {values.shape}, expected ({n},) "
            "— one value per vertex"
        )
    return values


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, facecolor="white")
    plt.close(fig)
    return path


def render_surface(
    surface,
    values,
    path: str | os.PathLike,
    views: Sequence[str] = ("front", "side", "back"),
    cmap: str | None = None,
    title: str | None = None,
    vmin: float | None = None,
    vmax: float | None = None,
    up: str = "y",
    label: str | None = None,
    class_names: Sequence[str] | None = None,
    point_size: float | None = None,
) -> Path:
    """PNG of ``surface`` coloured by ``values`` (N,), one panel per view, with a colour bar.

    Integer values are drawn as classes (discrete colours, ticks = ``class_names`` or numbers); floats with
    a continuous map (``cmap``, default viridis) from ``vmin`` to ``vmax`` (default: the data range).
    Meshes are drawn as lit faces, point clouds as points. The image is ``3.2 · len(views) + 0.8`` by 3.4
    inches at 100 dpi. Returns the path written.
    """
    values = _check_values(surface, values, "values")
    labels = _is_labels(values)
    values = values.astype(np.int64) if labels else values.astype(np.float64)
    norm, colormap = _norm_and_cmap(values, cmap, vmin, vmax, labels)
    fig = plt.figure(figsize=(_PANEL_INCHES * len(views) + 0.8, _PANEL_INCHES + 0.2))
    axes = []
    for i, view in enumerate(views):
        ax = fig.add_subplot(1, len(views), i + 1, projection="3d")
        _draw(ax, surface, values, norm, colormap, view, up, point_size)
        ax.set_title(view, fontsize=9, pad=0)
        axes.append(ax)
    _colorbar(fig, axes, norm, colormap, labels, label, class_names)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.subplots_adjust(left=0.0, right=0.9, bottom=0.02, top=0.86 if title else 0.92, wspace=0.0)
    return _save(fig, path)


def render_side_by_side(
    surfaces: Sequence,
    values: Sequence,
    path: str | os.PathLike,
    titles: Sequence[str],
    views: Sequence[str] = ("front", "back"),
    cmap: str = "turbo",
    title: str | None = None,
    up: str = "y",
) -> Path:
    """PNG of several surfaces side by side, each coloured by its own per-vertex float values on one shared
    colour scale (the range of all values), ``views`` of each: e.g. a colour field on a source surface and
    the same field carried to a target by a correspondence. Returns the path written."""
    if not (len(surfaces) == len(values) == len(titles)) or not surfaces:
        raise ValueError("render_side_by_side needs as many surfaces, value arrays and titles, at least one")
    values = [_check_values(s, v, "values").astype(np.float64) for s, v in zip(surfaces, values)]
    both = np.concatenate(values)
    norm, colormap = _norm_and_cmap(both, cmap, np.nanmin(both), np.nanmax(both), False)
    columns = len(surfaces) * len(views)
    fig = plt.figure(figsize=(_PANEL_INCHES * columns * 0.75, _PANEL_INCHES + 0.4))
    for i, (surface, field, name) in enumerate(zip(surfaces, values, titles)):
        for j, view in enumerate(views):
            ax = fig.add_subplot(1, columns, i * len(views) + j + 1, projection="3d")
            _draw(ax, surface, field, norm, colormap, view, up, None)
            ax.set_title(f"{name} ({view})", fontsize=9, pad=0)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.02, top=0.86 if title else 0.92, wspace=0.0)
    return _save(fig, path)


def render_comparison(
    surface,
    prediction,
    truth,
    error,
    path: str | os.PathLike,
    views: Sequence[str] = ("front", "side", "back"),
    cmap: str | None = None,
    error_cmap: str = "magma_r",
    title: str | None = None,
    up: str = "y",
    error_label: str = "error",
    class_names: Sequence[str] | None = None,
    error_max: float | None = None,
) -> Path:
    """PNG with three rows — prediction, ground truth, error — of the same views of one surface.

    Prediction and truth share one colour scale (classes, or the truth's range widened to cover the
    prediction). The error row has its own scale: a boolean ``error`` (e.g. ``pred != truth`` for labels)
    is drawn per vertex in two colours with a two-entry colour bar (right, wrong); a numeric one (the
    per-vertex geodesic error for correspondence, the absolute relative error for regression) from 0 to
    ``error_max`` (default: its maximum). ``error`` may be None to draw only two rows. Returns the path.
    """
    prediction = _check_values(surface, prediction, "prediction")
    truth = _check_values(surface, truth, "truth")
    labels = _is_labels(prediction) and _is_labels(truth)
    if labels:
        prediction, truth = prediction.astype(np.int64), truth.astype(np.int64)
        both = np.concatenate([prediction, truth])
        norm, colormap = _norm_and_cmap(both, cmap, None, None, True)
    else:
        prediction, truth = prediction.astype(np.float64), truth.astype(np.float64)
        both = np.concatenate([prediction, truth])
        finite = both[np.isfinite(both)]
        norm, colormap = _norm_and_cmap(finite, cmap, finite.min(), finite.max(), False)
    rows = [("prediction", prediction), ("ground truth", truth)]
    if error is not None:
        error = _check_values(surface, error, "error")
        error = error.astype(np.int64) if error.dtype == bool else error.astype(np.float64)
        rows.append((error_label, error))

    fig = plt.figure(figsize=(_PANEL_INCHES * len(views) + 1.2, _PANEL_INCHES * len(rows) + 0.4))
    for r, (row_name, values) in enumerate(rows):
        row_names = class_names
        if row_name == error_label and _is_labels(values):  # a right/wrong mask: two colours, two ticks
            row_norm, row_cmap, row_labels = mcolors.BoundaryNorm([-0.5, 0.5, 1.5], 2), _RIGHT_WRONG, True
            row_names = ("right", "wrong")
        elif row_name == error_label:
            finite = values[np.isfinite(values)]
            top = error_max if error_max is not None else (finite.max() if finite.size else 1.0)
            row_norm, row_cmap = mcolors.Normalize(0.0, top if top > 0 else 1.0), plt.get_cmap(error_cmap)
            values = np.where(np.isfinite(values), values, top)
            row_labels = False
        else:
            row_norm, row_cmap, row_labels = norm, colormap, labels
        axes = []
        for c, view in enumerate(views):
            ax = fig.add_subplot(len(rows), len(views), r * len(views) + c + 1, projection="3d")
            _draw(ax, surface, values, row_norm, row_cmap, view, up, None)
            if r == 0:
                ax.set_title(view, fontsize=9, pad=0)
            axes.append(ax)
        axes[0].text2D(
            -0.02, 0.5, row_name, transform=axes[0].transAxes, rotation=90, va="center", ha="right", fontsize=10
        )
        _colorbar(fig, axes, row_norm, row_cmap, row_labels, None, row_names)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.subplots_adjust(left=0.04, right=0.9, bottom=0.01, top=0.92 if title else 0.96, wspace=0.0, hspace=0.05)
    return _save(fig, path)


def plot_error_curve(
    curves: Mapping[str, tuple[Sequence[float], Sequence[float]]],
    path: str | os.PathLike,
    title: str = "Correspondence: geodesic error (Princeton protocol)",
) -> Path:
    """PNG of one or more geodesic error curves: % of vertices with error <= r against r (% of diameter).

    curves: {label: (radii as fractions of the geodesic diameter, fractions of vertices in [0, 1])}, e.g.
    from :func:`zernet.metrics.error_curve`. Returns the path.
    """
    if not curves:
        raise ValueError("plot_error_curve needs at least one curve")
    fig, ax = plt.subplots(figsize=(5.5, 4.2))
    for label, (radii, fractions) in curves.items():
        radii, fractions = np.asarray(radii, dtype=np.float64), np.asarray(fractions, dtype=np.float64)
        if radii.shape != fractions.shape:
            raise ValueError(f"curve {label!r}: {radii.size} radii but {fractions.size} fractions")
        ax.plot(100 * radii, 100 * fractions, label=f"{label} ({100 * fractions[0]:.1f} % exact)", linewidth=1.8)
    ax.set_xlabel("geodesic error (% of the geodesic diameter)")
    ax.set_ylabel("% correspondences within the error")
    ax.set_ylim(0, 100)
    ax.set_xlim(left=0)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower right", fontsize=9)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


def plot_training_curves(
    history: Sequence[Mapping[str, float]],
    path: str | os.PathLike,
    title: str | None = None,
    best_epoch: int | None = None,
) -> Path:
    """PNG of a training history: losses (left, log scale when all positive) and other metrics (right).

    history: one dict per epoch, e.g. ``{"epoch": 3, "train_loss": .., "val_loss": .., "val_accuracy": ..}``.
    Keys ending in ``loss`` go left, every other numeric key except ``epoch``, ``seconds`` and ``lr`` goes
    right (train_* solid, val_* dashed). ``best_epoch``: the selected model's epoch, marked in both panels
    by a vertical line. Returns the path.
    """
    if not history:
        raise ValueError("plot_training_curves needs a non-empty history (one dict per epoch)")
    epochs = [h.get("epoch", i + 1) for i, h in enumerate(history)]
    keys = []
    for entry in history:
        for key, value in entry.items():
            if key not in keys and isinstance(value, (int, float)) and not isinstance(value, bool):
                keys.append(key)
    skip = {"epoch", "seconds", "lr", "time"}
    loss_keys = [k for k in keys if k.endswith("loss")]
    metric_keys = [k for k in keys if k not in skip and k not in loss_keys]
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, chosen, name in ((left, loss_keys, "loss"), (right, metric_keys, "metric")):
        for key in chosen:
            x = [e for e, h in zip(epochs, history) if key in h]
            y = [float(h[key]) for h in history if key in h]
            ax.plot(x, y, "--" if key.startswith("val") else "-", marker="." if len(x) < 30 else None, label=key)
        if best_epoch is not None:
            ax.axvline(best_epoch, color="0.4", linestyle=":", linewidth=1.2, label=f"selected epoch {best_epoch}")
        if chosen:
            values = np.array([float(h[k]) for h in history for k in chosen if k in h])
            if name == "loss" and values.size and np.all(values > 0) and values.max() / values.min() > 20:
                ax.set_yscale("log")
        else:
            ax.text(0.5, 0.5, f"no {name} recorded", ha="center", va="center", transform=ax.transAxes)
        if chosen or best_epoch is not None:
            ax.legend(fontsize=8)
        ax.set_xlabel("epoch")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_ylabel(name)
        ax.grid(True, alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return _save(fig, path)
