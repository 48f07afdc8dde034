"""The run folder: ``train.log``, ``config.yaml``, ``metrics.json`` and ``plots/``.

Checkpoints (``last.pt``, ``previous.pt``, ``best.pt``) are written by :mod:`zernet.training.checkpoint`.
In a distributed run only rank 0 writes here.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import yaml
from tqdm.auto import tqdm

from zernet.io_utils import atomic_write_bytes, plain, write_json
from zernet.metrics import regression_scores

__all__ = [
    "RUN_FILES",
    "open_log",
    "close_log",
    "clear_run_files",
    "write_config_yaml",
    "write_json",
    "write_plots",
    "epoch_line",
    "picture_name",
    "regression_title",
]

#: The files a fresh run replaces.
RUN_FILES = ("last.pt", "previous.pt", "best.pt", "metrics.json", "train.log")


class _TqdmHandler(logging.Handler):
    """Console output that does not tear through an active progress bar."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            tqdm.write(self.format(record))
        except Exception:  # a closed console must not stop training
            self.handleError(record)


def open_log(run_dir: Path, echo: bool = True, main: bool = True) -> logging.Logger:
    """A logger writing to ``run_dir/train.log`` (appending, so a resumed run keeps its history) and the console.

    ``main=False`` (ranks other than 0 of a distributed run): no file, and only warnings on the console.
    """
    logger = logging.getLogger(f"zernet.run.{run_dir.resolve()}")
    logger.setLevel(logging.INFO)
    logger.propagate = False
    close_log(logger)
    if main:
        file_handler = logging.FileHandler(run_dir / "train.log", mode="a", encoding="utf-8")
        file_handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s", "%Y-%m-%d %H:%M:%S"))
        logger.addHandler(file_handler)
    if echo:
        console = _TqdmHandler()
        console.setFormatter(logging.Formatter("%(message)s"))
        if not main:
            console.setLevel(logging.WARNING)
        logger.addHandler(console)
    return logger


def close_log(logger: logging.Logger) -> None:
    for handler in list(logger.handlers):
        logger.removeHandler(handler)
        handler.close()


def clear_run_files(run_dir: Path) -> None:
    """Remove what an earlier run left in ``run_dir`` (a fresh run with overwrite)."""
    for name in RUN_FILES:
        stale = run_dir / name
        if stale.exists():
            stale.unlink()


def write_config_yaml(run_dir: Path, config: dict) -> Path:
    """``run_dir/config.yaml``: the full configuration, defaults filled in."""
    return atomic_write_bytes(run_dir / "config.yaml", yaml.safe_dump(plain(config), sort_keys=False).encode("utf-8"))


def epoch_line(entry: dict, epochs: int, improved: bool) -> str:
    """The log line of one epoch; `` *`` marks a new best model."""
    parts = [f"epoch {entry['epoch']}/{epochs}", f"train loss {entry['train_loss']:.4g}"]
    for key in ("train_accuracy", "val_loss", "val_accuracy", "val_MAPE"):
        if key in entry:
            parts.append(f"{key.replace('_', ' ')} {entry[key]:.4g}")
    parts.append(f"{entry['seconds']:.1f} s")
    return ", ".join(parts) + (" *" if improved else "")


def write_plots(
    run_dir: Path,
    history: list[dict],
    metrics: dict,
    kept: list[dict],
    class_names,
    renders: int,
    logger: logging.Logger | None = None,
) -> list[str]:
    """Training curves (the selected epoch marked), the error curve (correspondence) and renders of a few
    shapes of the split the metrics are of, named ``<split>_<shape>.png``; returns the paths."""
    from zernet import viz  # matplotlib is imported when a run draws, not when zernet starts

    plot_dir = run_dir / "plots"
    plot_dir.mkdir(exist_ok=True)
    split = metrics.get("split", "test")
    written = []
    if history:
        written.append(
            viz.plot_training_curves(
                history,
                plot_dir / "training_curves.png",
                title=f"training ({metrics['kind']})",
                best_epoch=metrics.get("best_epoch"),
            )
        )
    if "error_curve" in metrics:
        curve = metrics["error_curve"]
        written.append(
            viz.plot_error_curve(
                {f"zernet ({split})": (curve["radii"], curve["fractions"])}, plot_dir / "error_curve.png"
            )
        )
    for item in kept[:renders]:
        path = plot_dir / f"{split}_{picture_name(item['name'], split)}.png"
        written.append(_render_shape(item, metrics["kind"], path, class_names, logger))
    return [str(p) for p in written]


def picture_name(shape: str, split: str) -> str:
    """A file-name-safe shape name without a leading folder named like the split (``test/x`` -> ``x``)."""
    parts = Path(shape).parts
    if len(parts) > 1 and parts[0] == split:
        shape = str(Path(*parts[1:]))
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in shape)[:80]


def _render_shape(item: dict, kind: str, path: Path, class_names, logger) -> Path:
    from zernet import viz

    surface, pred, target, error = item["surface"], item["prediction"], item["target"], item["error"]
    if kind == "correspondence":
        # Vertex indices carry no visual meaning: colour each vertex by the height of the vertex it is
        # matched to (prediction) or should be matched to (truth) on the same shape, so a correct map
        # gives two identical pictures.
        height = surface.vertices[:, 1]
        return viz.render_comparison(
            surface,
            height[pred],
            height[target],
            error,
            path,
            error_label="geodesic error",
            title=f"{item['name']}: matched vertex height",
            error_max=0.1,
        )
    if kind == "segmentation":
        # Labels and the right/wrong mask are both drawn per vertex: one wrong vertex shows in both rows.
        return viz.render_comparison(
            surface,
            pred,
            target,
            np.asarray(pred) != np.asarray(target),
            path,
            error_label="wrong label",
            class_names=class_names,
            title=f"{item['name']}: {np.mean(pred == target):.1%} correct",
        )
    return viz.render_comparison(
        surface,
        pred,
        target,
        np.minimum(error, 1.0),
        path,
        error_label="relative error",
        title=regression_title(item["name"], pred, target, logger),
        error_max=0.5,
    )


def regression_title(name: str, pred, target, logger: logging.Logger | None = None) -> str:
    """``name: MAPE x`` with the MAPE of ``metrics.json`` (vertices with a zero target left out), and a
    note (and a warning) when the targets cross or touch zero, where relative errors mean little."""
    target = np.asarray(target, dtype=np.float64)
    mape = regression_scores(pred, target)["MAPE"]
    title = f"{name}: MAPE {mape:.3f}" if np.isfinite(mape) else f"{name}: MAPE undefined (all targets zero)"
    if target.size and target.min() <= 0 <= target.max():
        note = "targets cross zero" if target.min() < 0 < target.max() else "targets touch zero"
        title += f" ({note}: relative errors are not meaningful)"
        if logger is not None:
            logger.warning(
                f"{name}: {note}; MAPE leaves out the zero targets and is not a meaningful score "
                "for such a field (compare RRMSE or MAE)"
            )
    return title
