"""The training loop: build the data and the model, fit, select the best epoch on validation, test it.

:func:`train` trains a model described by a run configuration (normally read from a YAML file, see
``configs/``), selects the best epoch on a validation split carved from the training shapes, evaluates that
model on the test split and writes a complete run folder:

``config.yaml``  the full configuration with defaults filled in;
``last.pt``      checkpoint after the latest epoch (model, optimiser, RNG states, history, config);
``previous.pt``  the ``last.pt`` of the epoch before: ``resume`` falls back to it if last.pt is damaged;
``best.pt``      checkpoint of the epoch with the best validation metric;
``train.log``    what happened, one line per event and per epoch;
``metrics.json`` the validation-selected model evaluated on the test shapes (``"split": "val"`` when the
                 data set has none), with the shapes left out by ``data.on_error: skip`` (``"skipped"``);
``plots/``       training curves, the geodesic error curve (correspondence), renders of test shapes.

Every random choice is seeded from the configuration (see :mod:`zernet.training.schedule`), and the
checkpoint written after every epoch holds the RNG states, the optimiser state and the early-stopping
counters, so ``resume=True`` continues exactly where the last checkpoint left off: the final weights equal
those of an uninterrupted run.
"""

from __future__ import annotations

import dataclasses
import logging
import time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from zernet.data import PreprocessError, SkippedShapesWarning
from zernet.data.preprocess import failure_listing
from zernet.distributed import DistributedContext, is_main
from zernet.distributed import setup as setup_distributed
from zernet.inference.batch import model_basis_orders, model_directional_order
from zernet.inference.model_file import load_checkpoint
from zernet.inference.runtime import flush_denormals, resolve_device
from zernet.inference.spec import build_model_from_spec, model_spec
from zernet.inference.targets import feature_stats, target_stats
from zernet.inference.template_graph import geodesic_soft_labels
from zernet.io_utils import atomic_save_torch, plain
from zernet.metrics import geodesic_diameter
from zernet.training.augment import check_augmentation
from zernet.training.build import build_dataset, check_model_config, is_correspondence, preprocess_spec
from zernet.training.checkpoint import (
    RunRecord,
    load_resume_checkpoint,
    make_checkpoint,
    save_epoch_checkpoints,
    save_epoch_weights,
)
from zernet.training.config import ConfigError, EvalSection, RunConfig, TrainSection, parse_config
from zernet.training.epoch import Objective, train_one_epoch, validate
from zernet.training.evaluation import (
    evaluate_members,
    global_refinement_unavailable,
    select_refinement,
    summary_line,
)
from zernet.training.init_from import InitSource, initialise_from, load_init_source, voting_shapes
from zernet.training.init_from import describe as describe_init
from zernet.training.losses import check_loss_targets, resolve_loss
from zernet.training.residency import ShapeStore
from zernet.training.run_dir import (
    clear_run_files,
    close_log,
    epoch_line,
    open_log,
    write_config_yaml,
    write_json,
    write_plots,
)
from zernet.training.schedule import seed_everything, set_rng_state
from zernet.training.stopping import BUDGET, Monitor, initial_state, record_epoch, reopen_if_limits_raised

__all__ = ["train", "merge_resume_config", "RESUME_CHANGEABLE"]


@dataclass
class _Splits:
    train: list[int]
    val: list[int]
    test: list[int]


def train(
    config: Mapping[str, Any] | RunConfig | None,
    run_dir: str | Path,
    resume: bool = False,
    progress: bool = True,
    overwrite: bool = False,
    workers: int | None = None,
    init_from: str | Path | None = None,
) -> dict:
    """Train, select the best epoch on validation, evaluate it on the test split and fill ``run_dir``.

    Args:
        config: the run configuration (a :class:`~zernet.training.config.RunConfig` or a mapping as in
            ``configs/*.yaml``). With ``resume`` it may be ``None`` (the run's own config is used);
            otherwise only the keys of :data:`RESUME_CHANGEABLE` may differ from the run's.
        run_dir: the run folder; created if needed.
        resume: continue from ``run_dir/last.pt`` exactly where it stopped.
        progress: show progress bars (preprocessing, steps of each epoch).
        overwrite: start afresh even if ``run_dir`` already holds a checkpoint (otherwise an error, so that a
            finished run is never clobbered by accident).
        workers: processes for preprocessing (None: the data module's default).
        init_from: start from the weights of another run (its folder, i.e. its best.pt, or a checkpoint
            file) or shipped ones (``"pretrained:NAME"``); see :mod:`zernet.training.init_from`. Overrides
            the configuration's ``train.init_from``. Not with ``resume`` (a resumed run has weights).

    Returns:
        The test metrics (also written to ``run_dir/metrics.json``).
    """
    run_dir = Path(run_dir)
    checkpoint, resume_note, source = None, None, None
    if resume and init_from is not None:
        raise ConfigError(
            "--init-from starts a new run from another run's weights; it cannot be combined with "
            "--resume (a resumed run continues from its own checkpoint and keeps its init-from)"
        )
    if resume:
        checkpoint, resume_note = load_resume_checkpoint(run_dir)
    else:
        config = None if config is None else parse_config(config)
        init_from = config.train.init_from if init_from is None and config is not None else init_from
        if init_from is not None:  # before the run folder is touched, so a bad path fails in a second
            source = load_init_source(init_from)
        config = _fresh_run_config(config, run_dir, overwrite)
    run_dir.mkdir(parents=True, exist_ok=True)
    logger = open_log(run_dir, main=is_main())
    ctx, completed = None, False
    try:
        if resume_note:
            logger.warning(resume_note)
        if checkpoint is not None:
            config = merge_resume_config(checkpoint["config"], config, logger, checkpoint["state"]["epoch"])
        check_model_config(config)  # a bad model option fails now, before any shape is loaded
        # Joins the torchrun process group, if any (see zernet.distributed); a no-op for one process.
        ctx = setup_distributed(resolve_device(config.train.device))
        if ctx.is_main:
            write_config_yaml(run_dir, config.to_dict())
        metrics = _run(config, run_dir, checkpoint, progress and ctx.is_main, logger, workers, ctx, source)
        completed = True
        return metrics
    finally:
        if ctx is not None:
            ctx.close(completed)
        close_log(logger)


def _fresh_run_config(config, run_dir: Path, overwrite: bool) -> RunConfig:
    """The checked configuration of a new run; refuses to clobber a run unless ``overwrite``."""
    if config is None:
        raise ConfigError("train needs a configuration (or resume=True with an existing run folder)")
    config = parse_config(config)
    if (run_dir / "last.pt").exists() and not overwrite:
        raise ConfigError(
            f"{run_dir} already holds a run (last.pt); resume it with --resume or choose another --run-dir"
        )
    if is_main():  # in a distributed run only rank 0 touches the run folder
        clear_run_files(run_dir)
    return config


#: What may change when a run is resumed: none of it changes the weights still to train (on_error only says
#: what a shape that fails to load would do; the shapes of a run are cached).
RESUME_CHANGEABLE = (
    ("train", "epochs"),
    ("train", "patience"),
    ("train", "threads"),
    ("data", "on_error"),
    ("data", "residency"),
)


def merge_resume_config(stored: Mapping[str, Any], given, logger: logging.Logger, trained: int = 0) -> RunConfig:
    """On resume the stored configuration wins, except for :data:`RESUME_CHANGEABLE` (the epoch budget,
    patience, CPU threads, the bad-shape policy, the residency of the shapes). ``train.epochs`` never drops below the ``trained`` epochs,
    so ``config.yaml`` never claims fewer epochs than the checkpoints hold."""
    config = parse_config(stored)
    if given is None:
        return config
    given = parse_config(given)
    sections = {}
    for section, key in RESUME_CHANGEABLE:
        old, new = getattr(getattr(config, section), key), getattr(getattr(given, section), key)
        if section == "train" and key == "epochs" and new < trained:
            logger.warning(
                f"resume: train.epochs {new} is below the {trained} epochs already trained; keeping {trained}"
            )
            new = trained
        if new != old:
            logger.info(f"resume: {section}.{key} changed from {old} to {new}")
            sections.setdefault(section, {})[key] = new
    config = dataclasses.replace(
        config, **{name: dataclasses.replace(getattr(config, name), **changes) for name, changes in sections.items()}
    )
    changeable = {f"{section}.{key}" for section, key in RESUME_CHANGEABLE}
    differing = [
        key for key in _differing_keys(plain(given.to_dict()), plain(config.to_dict())) if key not in changeable
    ]
    if differing:
        allowed = ", ".join(f"{section}.{key}" for section, key in RESUME_CHANGEABLE)
        logger.warning(
            f"resume: the given configuration differs from the run's in {', '.join(differing)}; "
            f"continuing with the run's own config.yaml (only {allowed} may change on resume)"
        )
    return config


def _differing_keys(a, b, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two plain mappings."""
    if not (isinstance(a, dict) and isinstance(b, dict)):
        return [prefix.rstrip(".") or "config"] if a != b else []
    keys = list(dict.fromkeys(list(a) + list(b)))
    return [k for key in keys for k in _differing_keys(a.get(key), b.get(key), f"{prefix}{key}.")]


def _run(
    config: RunConfig,
    run_dir: Path,
    checkpoint: dict | None,
    progress: bool,
    logger: logging.Logger,
    workers: int | None,
    ctx: DistributedContext,
    source: InitSource | None = None,
) -> dict:
    """Build, fit, select, test."""
    if config.train.threads:
        torch.set_num_threads(int(config.train.threads))
    logger.info(
        ("resuming" if checkpoint else "starting") + f" run in {run_dir} on {ctx.device} "
        f"({torch.get_num_threads()} CPU threads"
        + (f", {ctx.world_size} ranks, {ctx.backend})" if ctx.distributed else ")")
    )
    dataset, splits, preprocess_seconds = _load_dataset(config, progress, workers, ctx, logger)
    record, objective = _describe_run(config, dataset, splits, checkpoint, logger, ctx.device)
    # Read only if the output layer is carried to this run's template.
    voters = (dataset[i] for i in voting_shapes(splits.train))
    model, optimizer, state = _build_model(record, config.train, checkpoint, ctx.device, logger, source, voters)
    logger.info(
        f"model {record.model_spec['name']} ({sum(p.numel() for p in model.parameters()):,} parameters), "
        f"loss {objective.loss}, lr {config.train.lr} ({config.train.lr_schedule}), "
        f"{config.train.shapes_per_step} shape(s) per step"
    )
    shapes = ShapeStore(
        dataset,
        splits.train + splits.val,
        config.data.residency,
        ctx.device,
        model_directional_order(model),
        model_basis_orders(model),
        progress,
    )
    logger.info(shapes.describe())
    monitor = Monitor.for_task(objective.task)
    with flush_denormals():  # tiny softmax gradients would otherwise slow late epochs down by 2-3x
        _fit(
            model,
            optimizer,
            state,
            shapes,
            splits,
            record,
            objective,
            monitor,
            config.train,
            ctx,
            run_dir,
            progress,
            logger,
        )
    del shapes  # the held operators are not needed for the test
    if not ctx.is_main:
        # Rank 0 alone evaluates the selected model on the test split and writes metrics.json.
        return {
            "rank": ctx.rank,
            "epochs_trained": state["epoch"],
            "best_epoch": state["best_epoch"],
            "stop_reason": state["stop_reason"],
        }
    metrics, predictions = _test(
        model, state, dataset, splits, monitor, config.eval, run_dir, ctx.device, progress, logger
    )
    metrics["preprocess_seconds"] = preprocess_seconds
    metrics["skipped"] = [{"name": name, "reason": reason} for name, reason in dataset.failures.items()]
    metrics["forms"] = dataset.info.get("forms", {})  # data.forms: training shapes made per form
    return _report(metrics, predictions, state["history"], dataset, config, run_dir, logger)


def _load_dataset(config: RunConfig, progress: bool, workers, ctx: DistributedContext, logger):
    """The data set and its splits (rank 0 fills the cache first; the other ranks then read it)."""
    started = time.perf_counter()
    with ctx.main_first(), warnings.catch_warnings():
        # Skipped shapes are written to train.log (below) instead of being warned about as well.
        warnings.simplefilter("ignore", SkippedShapesWarning)
        try:
            dataset = build_dataset(config, progress=progress, workers=workers)
        except PreprocessError as error:
            _log_file_only(logger, f"stopped before training: {failure_listing(error.failures, error.total)}")
            raise
    seconds = time.perf_counter() - started
    splits = _Splits(
        list(dataset.splits["train"]), list(dataset.splits.get("val", [])), list(dataset.splits.get("test", []))
    )
    if not splits.train:
        raise ConfigError("the data set has no training shapes")
    logger.info(
        f"data: {config.data.kind}, {dataset.task}, {len(splits.train)} train / {len(splits.val)} val / "
        f"{len(splits.test)} test shapes (loaded in {seconds:.1f} s)"
    )
    made = dataset.info.get("forms")
    if made:
        logger.info(
            "forms of the training shapes (data.forms), in the train count: "
            + ", ".join(f"{count} {form}" for form, count in made.items())
        )
    if ctx.is_main:  # reported once, not by every rank of a distributed run
        _report_data(dataset, splits, config.data.kind, logger)
    return dataset, splits, seconds


def _report_data(dataset, splits: _Splits, kind: str, logger) -> None:
    """Warnings about the data set: skipped shapes (each with its reason), missing splits, unused classes."""
    for name, reason in dataset.failures.items():
        logger.warning(f"skipped shape {name} (data.on_error: skip): {reason}")
    if not splits.val:
        logger.warning("no validation shapes: the last epoch is kept as the model and early stopping is off")
    if not splits.test:
        logger.warning(
            "no test shapes: the final scores are of the validation split, on which the model is "
            "chosen, and are labelled val"
        )
    _check_class_count(dataset, kind, logger)


def _log_file_only(logger: logging.Logger, message: str) -> None:
    """An ERROR line in train.log only (the command line reports the error itself)."""
    record = logger.makeRecord(logger.name, logging.ERROR, __file__, 0, message, None, None)
    for handler in logger.handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)


def _check_class_count(dataset, kind: str, logger) -> None:
    """One warning when ``num_classes`` is larger than the labels the data set uses (segmentation)."""
    if dataset.task != "classification" or is_correspondence(dataset, kind) or dataset.num_classes is None:
        return
    seen = set()
    for i in range(len(dataset)):
        seen.update(np.unique(np.asarray(dataset.target(i))).tolist())
    missing = [c for c in range(int(dataset.num_classes)) if c not in seen]
    if missing:
        shown = ", ".join(map(str, missing[:10])) + (" ..." if len(missing) > 10 else "")
        logger.warning(
            f"data.num_classes is {dataset.num_classes} but no shape has a vertex of class {shown}: "
            "their per-class scores are null in metrics.json"
        )


def _describe_run(config: RunConfig, dataset, splits: _Splits, checkpoint: dict | None, logger, device: torch.device):
    """The run's fixed record (model spec, scaling, preprocessing) and the training objective (its tables on
    ``device``)."""
    task = dataset.task
    check_augmentation(config.train, dataset.feature_kind)
    loss_name = resolve_loss(config.train.loss, task)
    first = dataset[splits.train[0]]
    out_channels = int(dataset.num_classes) if task == "classification" else 1
    spec = model_spec(config.model, first.features.shape[1], out_channels, dataset.patch_configs)
    targets = _target_scaling(config.train, task, dataset, splits, checkpoint, logger)
    check_loss_targets(loss_name, dataset, splits.train + splits.val)
    features = _feature_scaling(config.train, dataset, splits, checkpoint, logger)
    correspondence = is_correspondence(dataset, config.data.kind)
    # Correspondence by vertex index: every shape has the template's connectivity, the first one's included;
    # the first training shape (area-normalised) is the template's geometry for the global refinement.
    has_template = correspondence and first.surface.faces is not None
    template_faces = torch.as_tensor(first.surface.faces, dtype=torch.int64) if has_template else None
    template_vertices = torch.as_tensor(first.surface.vertices, dtype=torch.float32) if has_template else None
    record = RunRecord(
        config=config.to_dict(),
        model_spec=spec,
        task=task,
        num_classes=None if dataset.num_classes is None else int(dataset.num_classes),
        correspondence=correspondence,
        target_stats=targets,
        target_exponent=float(dataset.info.get("target_exponent") or 0.0),
        feature_stats=features,
        preprocess=preprocess_spec(dataset),
        template_faces=template_faces,
        template_vertices=template_vertices,
    )
    soft_labels = None
    if config.train.label_radius > 0:
        if not has_template:
            raise ConfigError(
                "train.label_radius spreads a correspondence target over the template's vertices; this run "
                f"(data.kind {config.data.kind!r}) has no template mesh: set it to 0"
            )
        diameter = geodesic_diameter(first.surface.vertices, first.surface.faces)
        indices, weights = geodesic_soft_labels(
            first.surface.vertices, first.surface.faces, config.train.label_radius, diameter
        )
        soft_labels = (indices.to(device), weights.to(device))
        logger.info(
            f"soft labels: each target spread over the template vertices within {config.train.label_radius} of "
            f"its diameter ({float((weights > 0).sum(dim=1).float().mean()):.1f} on average, the true one "
            f"weighing {float(weights.max(dim=1).values.mean()):.2f})"
        )
    return record, Objective(task, loss_name, targets, features, soft_labels)


def _target_scaling(train: TrainSection, task: str, dataset, splits: _Splits, checkpoint, logger) -> dict | None:
    if checkpoint is not None:
        return checkpoint["target_stats"]
    if task != "regression" or not (train.standardize_targets or train.target_transform != "none"):
        return None
    stats = target_stats(dataset, splits.train, train.target_transform, train.standardize_targets)
    logger.info(
        f"targets: transform {stats['transform']}, standardised with training mean "
        f"{stats['mean']:.6g}, std {stats['std']:.6g}"
    )
    return stats


def _feature_scaling(train: TrainSection, dataset, splits: _Splits, checkpoint, logger) -> dict | None:
    if checkpoint is not None:
        return checkpoint.get("feature_stats")
    if not train.standardize_features:
        return None
    stats = feature_stats(dataset, splits.train)
    logger.info("input features standardised per channel with the training vertices' mean and std")
    return stats


def _build_model(
    record: RunRecord,
    train: TrainSection,
    checkpoint: dict | None,
    device,
    logger,
    source: InitSource | None = None,
    voters=(),
):
    """The model, its Adam optimiser and the loop state: fresh from ``train.seed`` (then, with ``source``,
    taking another run's weights, its output layer carried to this run's template by ``source``'s vote on the
    training records ``voters`` if it has one), or as checkpointed."""
    # Seed right before the model is built, so its initialisation depends only on train.seed.
    seed_everything(train.seed)
    model = build_model_from_spec(record.model_spec)
    init_info = None
    if source is not None and checkpoint is None:
        template = None
        if record.template_vertices is not None:
            template = (record.template_vertices.numpy(), record.template_faces.numpy())
        init_info = initialise_from(model, source, template, voters, device)
    model = model.to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=train.lr, weight_decay=train.weight_decay)
    state = initial_state()
    if init_info is not None:
        state["init_from"] = init_info  # checkpointed with the state: a resumed run still reports it
    if checkpoint is not None:
        model.load_state_dict(checkpoint["model"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        state = checkpoint["state"]
        set_rng_state(checkpoint["rng"])
        logger.info(
            f"resumed after epoch {state['epoch']} (best {state['best_metric']} at epoch {state['best_epoch']})"
        )
    if state.get("init_from"):
        logger.info(describe_init(state["init_from"]))
    return model, optimizer, state


def _fit(
    model,
    optimizer,
    state: dict,
    shapes: ShapeStore,
    splits: _Splits,
    record: RunRecord,
    objective: Objective,
    monitor: Monitor,
    train: TrainSection,
    ctx: DistributedContext,
    run_dir: Path,
    progress: bool,
    logger,
) -> None:
    """Train epoch by epoch until early stopping or the budget; checkpoint after every epoch."""
    # DistributedDataParallel in a distributed run (averages the gradients over the ranks), else the model
    # itself. Only the training forward goes through it; validation, checkpoints and evaluation use `model`.
    net = ctx.wrap(model)
    reopen_if_limits_raised(state, train.epochs, train.patience)
    while not state["stopped"] and state["epoch"] < train.epochs:
        epoch = state["epoch"] + 1
        started = time.perf_counter()
        entry = train_one_epoch(net, model, optimizer, shapes, splits.train, epoch, train, objective, ctx, progress)
        if splits.val:
            # Split over the ranks and recombined exactly: every rank sees the same metric and stops alike.
            entry.update(
                ctx.mean_over_shards(lambda part: validate(model, shapes, part, ctx.device, objective), splits.val)
            )
        entry["seconds"] = time.perf_counter() - started
        improved = record_epoch(state, entry, monitor, train.epochs, train.patience, bool(splits.val))
        checkpoint = make_checkpoint(record, model, optimizer, state)
        if ctx.is_main:  # only rank 0 writes in a distributed run
            save_epoch_checkpoints(checkpoint, run_dir, improved)
            if train.keep_epochs:
                save_epoch_weights(checkpoint, run_dir, epoch)
        logger.info(epoch_line(entry, train.epochs, improved))
        if state["stopped"] and state["stop_reason"] != BUDGET:
            logger.info(f"stopping after epoch {epoch}: {state['stop_reason']}")
    best_text = "n/a" if state["best_metric"] is None else f"{state['best_metric']:.4g}"
    logger.info(
        f"training done: {state['epoch']} epochs in {state['train_seconds']:.1f} s; best epoch "
        f"{state['best_epoch']} ({monitor.name} {best_text})"
    )


def _test(
    model,
    state: dict,
    dataset,
    splits: _Splits,
    monitor: Monitor,
    evaluation: EvalSection,
    run_dir: Path,
    device,
    progress: bool,
    logger,
) -> tuple[dict, list[dict]]:
    """The selected model (best.pt) on the test split (the validation split if there is none); a
    correspondence refined as ``evaluation.refine_rings``, ``refine_passes`` and ``refine_spectral`` say, a
    segmentation as ``evaluation.refine_rings`` says."""
    best = load_checkpoint(run_dir / "best.pt")
    model.load_state_dict(best["model"])
    if splits.test:
        split, indices = "test", splits.test
    else:
        split, indices = "val", splits.val
    members = [(model, best)]
    candidates, radii = list(evaluation.refine_rings), list(evaluation.refine_spectral)
    passes_candidates = list(evaluation.refine_passes)
    for key, values in (("refine_rings", candidates), ("refine_passes", passes_candidates), ("refine_spectral", radii)):
        if len(values) > 1 and not splits.val:
            logger.warning(f"no validation split to choose eval.{key} among {values}: using {min(values)}")
            values[:] = [min(values)]
    unavailable = global_refinement_unavailable(best) if any(radii) else None
    if unavailable is not None:
        logger.warning(unavailable)
        radii = [0.0]
    rings, passes, radius, choice = select_refinement(
        members, dataset, candidates, radii, device, progress, passes_candidates
    )
    metrics, predictions = evaluate_members(
        members, dataset, indices, device, progress, refine_rings=rings, refine_spectral=radius, refine_passes=passes
    )
    if choice is not None:
        metrics["refine_choice"] = choice
        logger.info(
            f"refine rings {rings}"
            + (f" x {passes} passes" if "passes" in choice else "")
            + ", chosen on the validation split (exact accuracy by rings"
            + (" x passes" if "passes" in choice else "")
            + ": "
            + ", ".join(f"{k}: {v:.4f}" for k, v in choice["accuracy"].items())
            + ")"
        )
        if "spectral_accuracy" in choice:
            logger.info(
                f"global refinement radius {radius:g}, chosen on the validation split after {rings} rings "
                "(exact accuracy by radius, 0 = off: "
                + ", ".join(f"{k}: {v:.4f}" for k, v in choice["spectral_accuracy"].items())
                + ")"
            )
    chosen = (rings, passes, radius)
    if (
        best["task"] == "classification"
        and (best.get("refine_rings"), best.get("refine_passes", 1), best.get("refine_spectral")) != chosen
    ):
        best["refine_rings"] = rings  # what `predict` applies to a new surface
        best["refine_passes"] = passes
        best["refine_spectral"] = radius
        atomic_save_torch(best, run_dir / "best.pt")
    metrics.update(
        {
            "split": split,
            "checkpoint": "best.pt",
            "best_epoch": state["best_epoch"],
            "epochs_trained": state["epoch"],
            "stop_reason": state["stop_reason"],
            "selection": {"metric": monitor.name, "value": state["best_metric"]},
            "train_seconds": state["train_seconds"],
        }
    )
    if state.get("init_from"):
        metrics["init_from"] = state["init_from"]
    return metrics, predictions


def _report(
    metrics: dict, predictions: list[dict], history: list[dict], dataset, config: RunConfig, run_dir: Path, logger
) -> dict:
    """Plots (if ``eval.plots``) and ``metrics.json``; returns the metrics."""
    if config.eval.plots:
        try:
            metrics["plots"] = write_plots(
                run_dir,
                history,
                metrics,
                predictions,
                getattr(dataset, "info", {}).get("class_names"),
                config.eval.renders,
                logger,
            )
        except Exception as error:  # a plotting problem must not throw away a finished training run
            logger.warning(f"plots failed: {type(error).__name__}: {error}")
            metrics["plots"] = []
    write_json(run_dir / "metrics.json", metrics)
    logger.info(
        f"{metrics['split']} metrics: {summary_line(metrics)}"
        + (f" ({len(metrics['skipped'])} shapes skipped)" if metrics.get("skipped") else "")
    )
    logger.info(f"wrote {run_dir / 'metrics.json'}")
    return metrics
