"""The paper's human experiments on generated bodies: zernet's variants, the paper's formulation and FeaStNet.

In one run, on the same generated bodies (:mod:`zernet.data.bodies`), the same splits, epochs and seed, for
correspondence and segmentation, this trains

    zernet             single scale             (model section of configs/bodies_*.yaml)
    zernet-multiscale  three scales in parallel (model and patch sections of configs/faust_multi_scale.yaml)
    zernet-directional direction-preserving     (model section of configs/faust_directional.yaml)
    paper-zernet       the paper's formulation  (zernet's section, model name paper-zernet, 50 samples per patch)
    feastnet           FeaStNet                 (PyTorch Geometric's FeaStConv, the same widths)

each with its task's widths and the training recipe of ``configs/bodies_<task>.yaml`` (learning rate,
dropout, ...), and reports per model:

- the accuracy of every epoch's model on the test bodies and on the validation bodies (curves);
- the model selected on validation (never on the test bodies): exact correspondence accuracy and the geodesic
  error curve from 0 to 10 % of the geodesic diameter (:func:`zernet.metrics.correspondence_scores`, the
  Princeton protocol), or segmentation accuracy with the IoU of each part;
- correspondence refined by averaging over mesh rings (:mod:`zernet.inference.refine`), the radius chosen on
  the validation bodies among ``--refine-rings``: its scores beside the unrefined ones, for every model;
- wall time per epoch (training and validation, this machine, ``--threads`` threads) and the training time
  until the first epoch whose model reaches the target on the test bodies (``--target``).

Each epoch is trained by the ordinary training loop (``zernet.training.train``, continued epoch by epoch
with ``resume``, which is exact), and the model after each epoch is scored on the test bodies for the curve.

Bodies are coarse by default (``--topology coarse-1229``: 1,229 vertices, 50 bodies, 34 train / 6 validation
/ 10 test), so that the whole comparison runs in well under an hour on two cores; ``--topology faust
--count 100 --n-test 20 --val-count 8`` is the FAUST-sized setting of the issue's targets (hours on a CPU).
Writes ``benchmarks/experiments/results/bodies.md``, ``bodies.json`` and ``bodies.png`` (``--out`` for
another stem).

    .venv/bin/python -m benchmarks.experiments.bodies                       # coarse, 20 epochs, all models
    .venv/bin/python -m benchmarks.experiments.bodies --tasks segmentation --models zernet feastnet --epochs 10
    .venv/bin/python -m benchmarks.experiments.bodies --topology faust --count 100 --n-test 20 --val-count 8 --epochs 30
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch

from benchmarks.harness import (
    CACHE,
    EXPERIMENT_RESULTS,
    REPO,
    add_data,
    add_out,
    add_threads,
    arguments,
    ensure_bodies,
    markdown_table,
    result_file,
    write_markdown,
)
from benchmarks.harness import write_json as write_result  # a result file, with commit and machine
from zernet.data.bodies import TOPOLOGIES
from zernet.inference import load_checkpoint
from zernet.inference.predict import model_from_checkpoint, predict_record
from zernet.io_utils import plain, write_json
from zernet.training import apply_overrides, build_dataset, load_config, parse_config, train
from zernet.training.evaluation import evaluate_members, select_refine_rings

MODELS = ("zernet", "zernet-multiscale", "zernet-directional", "paper-zernet", "feastnet")
TASKS = ("correspondence", "segmentation")
TASK_CONFIGS = {
    "correspondence": "configs/bodies_correspondence.yaml",
    "segmentation": "configs/bodies_segmentation.yaml",
}
#: Options only the zernet families take (FeaStNet is given the rest of the model section).
ZERNET_ONLY = ("angular_resolution", "pooling", "n_scales", "wiring", "nonlinearity", "norm", "input_skip", "n_max")


def parse_args(argv=None) -> argparse.Namespace:
    p = arguments(__doc__)
    p.add_argument("--tasks", nargs="+", choices=TASKS, default=list(TASKS))
    p.add_argument("--models", nargs="+", choices=MODELS, default=list(MODELS))
    p.add_argument("--epochs", type=int, default=20, help="epochs of every model (default 20)")
    p.add_argument("--topology", choices=sorted(TOPOLOGIES), default="coarse-1229")
    p.add_argument("--count", type=int, default=50, help="bodies generated (default 50)")
    p.add_argument("--n-test", type=int, default=10, help="of them, test bodies (default 10)")
    p.add_argument("--val-count", type=int, default=6, help="validation bodies carved from the training ones")
    p.add_argument("--seed", type=int, default=0, help="seed of the bodies, the split and the training")
    add_threads(p, default=1)
    p.add_argument(
        "--target",
        type=float,
        nargs=2,
        default=(0.97, 0.97),
        metavar=("CORR", "SEG"),
        help="test accuracy targets for correspondence and segmentation (default 0.97 0.97)",
    )
    p.add_argument(
        "--refine-rings",
        type=int,
        nargs="+",
        default=[0, 1, 2, 3],
        metavar="N",
        help="correspondence refinement radii to choose among on validation (default 0 1 2 3)",
    )
    p.add_argument(
        "--set",
        dest="overrides",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="overrides applied to every run's configuration (e.g. train.lr=1e-3)",
    )
    add_data(p, None, "bodies folder (default data/bodies-TOPOLOGY-COUNT)")
    p.add_argument("--runs", type=Path, default=REPO / "runs" / "bench_bodies", help="run folders")
    p.add_argument(
        "--keep",
        action="store_true",
        help="reuse the results in STEM.json of (task, model) pairs whose configuration is unchanged, "
        "and continue an interrupted pair from its last trained epoch (models can be added)",
    )
    add_out(p, EXPERIMENT_RESULTS / "bodies")
    return p.parse_args(argv)


def run_config(task: str, model: str, bodies: Path, args) -> dict:
    """The configuration of one (task, model) run: the task's recipe with the model's section."""
    config = load_config(REPO / TASK_CONFIGS[task])
    widths = config["model"].get("widths")
    if task == "segmentation":
        config["data"]["meshes"] = str(bodies / "segmentation" / "meshes")
        config["data"]["labels"] = str(bodies / "segmentation" / "labels")
    else:
        config["data"]["root"] = str(bodies / "correspondence")
        config["data"]["n_vertices"] = None  # the topology's own count
        n_train = args.count - args.n_test
        config["data"]["train_indices"] = list(range(n_train))
        config["data"]["test_indices"] = list(range(n_train, args.count))
    config["data"]["val_count"] = args.val_count
    config["data"]["seed"] = args.seed
    if model == "zernet-multiscale":
        multi = load_config(REPO / "configs" / "faust_multi_scale.yaml")
        config["patch"] = multi["patch"]
        config["model"] = dict(multi["model"])
    elif model == "zernet-directional":
        config["model"] = dict(load_config(REPO / "configs" / "faust_directional.yaml")["model"])
    elif model in ("paper-zernet", "feastnet"):
        config["model"] = dict(config["model"], name=model)
    if model == "paper-zernet":  # the paper's sampling rule too: the 50 nearest samples of each patch
        config["patch"]["scales"] = [dict(scale, patch_size=50) for scale in config["patch"]["scales"]]
    if model == "feastnet":
        config["model"] = {k: v for k, v in config["model"].items() if k not in ZERNET_ONLY}
    config["model"]["widths"] = widths
    config["model"]["dropout"] = config["model"].get("dropout", 0.25)
    # Trained one epoch at a time (run_one): the cosine schedule, if any, spans the whole budget.
    config["train"].update(
        {
            "epochs": args.epochs,
            "lr_schedule_epochs": args.epochs,
            "patience": None,
            "seed": args.seed,
            "threads": args.threads,
            "device": "cpu",
        }
    )
    config["eval"] = {"renders": 0, "plots": False}  # refinement is chosen once, for the selected model
    config["cache_dir"] = str(CACHE)
    return apply_overrides(config, args.overrides)


def selected_scores(run_dir: Path, dataset, indices, refine_rings) -> dict:
    """Scores of the selected model (``best.pt``) of ``run_dir`` on the shapes ``indices``; a correspondence
    refined over the rings (among ``refine_rings``) that score best on the validation bodies."""
    checkpoint = load_checkpoint(run_dir / "best.pt")
    members = [(model_from_checkpoint(checkpoint, torch.device("cpu")), checkpoint)]
    rings, choice = select_refine_rings(members, dataset, refine_rings, torch.device("cpu"), progress=False)
    metrics, _ = evaluate_members(
        members, dataset, indices, torch.device("cpu"), progress=False, keep=0, refine_rings=rings
    )
    metrics["refine_choice"] = choice
    return metrics


def test_accuracy(run_dir: Path, name: str, dataset, indices) -> float:
    """Vertex accuracy (exact correspondence, or correct part) of a checkpoint, pooled over the shapes: the
    ``accuracy`` of :func:`selected_scores` without refinement or geodesic distances, cheap enough for every epoch."""
    checkpoint = load_checkpoint(run_dir / name)
    members = [(model_from_checkpoint(checkpoint, torch.device("cpu")), checkpoint)]
    hits = total = 0
    for i in indices:
        pred, _ = predict_record(members, dataset[i], torch.device("cpu"))
        target = np.asarray(dataset[i].target)
        hits, total = hits + int((np.asarray(pred) == target).sum()), total + len(target)
    return hits / total


CURVE_FILE = "bench_test_curve.json"  # in each run folder: the test curve so far, so --keep continues a pair


def trained_curve(run_dir: Path, config) -> list[float]:
    """The test curve of the epochs already trained in ``run_dir`` with this configuration (``[]`` if none): an
    interrupted pair continues from its last epoch instead of starting over."""
    path, last = run_dir / CURVE_FILE, run_dir / "last.pt"
    if not (path.is_file() and last.is_file()):
        return []
    stored = json.loads(path.read_text())
    trained = load_checkpoint(last)["state"]["epoch"]
    same = stored.get("config") == json.loads(json.dumps(plain(config.to_dict())))
    return list(stored["test_curve"]) if same and len(stored["test_curve"]) == trained else []


def run_one(task: str, model: str, bodies: Path, args) -> dict:
    """Train ``model`` on ``task`` epoch by epoch, scoring every epoch's model on the test bodies."""
    config = parse_config(run_config(task, model, bodies, args))
    dataset = build_dataset(config, progress=False, workers=1)
    test = list(dataset.splits["test"])
    run_dir = args.runs / f"{task}-{model}"
    test_curve = trained_curve(run_dir, config) if args.keep else []
    for epoch in range(len(test_curve) + 1, args.epochs + 1):
        epoch_config = parse_config(apply_overrides(config.to_dict(), [f"train.epochs={epoch}"]))
        train(epoch_config, run_dir, resume=epoch > 1, overwrite=epoch == 1, progress=False, workers=1)
        test_curve.append(test_accuracy(run_dir, "last.pt", dataset, test))
        write_json(run_dir / CURVE_FILE, {"config": plain(config.to_dict()), "test_curve": test_curve})
        print(f"  {task} {model} epoch {epoch}: test accuracy {test_curve[-1]:.4f}", flush=True)
    state = load_checkpoint(run_dir / "last.pt")["state"]
    selected = selected_scores(run_dir, dataset, test, args.refine_rings)
    unrefined = selected.get("unrefined_summary", selected["summary"])
    if abs(unrefined["accuracy"] - test_curve[state["best_epoch"] - 1]) > 1e-9:
        print(
            f"  warning: the selected model scores {unrefined['accuracy']:.4f}, its epoch's curve point "
            f"{test_curve[state['best_epoch'] - 1]:.4f}",
            flush=True,
        )
    history = state["history"]
    seconds = [float(h["seconds"]) for h in history]
    target = args.target[0] if task == "correspondence" else args.target[1]
    reached = next((i for i, acc in enumerate(test_curve) if acc >= target), None)
    return {
        "task": task,
        "model": model,
        "config": config.to_dict(),
        "n_train": len(dataset.splits["train"]),
        "n_val": len(dataset.splits.get("val", [])),
        "n_test": len(test),
        "n_vertices": int(dataset[test[0]].n_vertices),
        "parameters": _parameters(run_dir),
        "test_curve": test_curve,
        "val_curve": [h.get("val_accuracy") for h in history],
        "train_curve": [h.get("train_accuracy") for h in history],
        "seconds_per_epoch": float(np.mean(seconds)),
        "train_seconds": float(np.sum(seconds)),
        "best_epoch": state["best_epoch"],
        "selected": unrefined,
        "refine_rings": selected.get("refine_rings", 0),
        "refine_choice": selected.get("refine_choice"),
        "refined": selected["summary"] if selected.get("refine_rings") else None,
        "error_curve": selected.get("error_curve"),
        "target": target,
        "epochs_to_target": None if reached is None else reached + 1,
        "seconds_to_target": None if reached is None else float(np.sum(seconds[: reached + 1])),
    }


def _parameters(run_dir: Path) -> int:
    return int(sum(v.numel() for v in load_checkpoint(run_dir / "best.pt")["model"].values()))


def _pct(value) -> str:
    return "n/a" if value is None else f"{100 * value:.1f}"


def markdown(results: list[dict], args) -> list[str]:
    first = results[0]
    lines = [
        "# Generated bodies: zernet variants, the paper's formulation and FeaStNet",
        "",
        f"Bodies: topology {args.topology} ({first['n_vertices']} vertices), {first['n_train']} train / "
        f"{first['n_val']} validation / {first['n_test']} test, seed {args.seed}; {args.epochs} epochs each, "
        f"{args.threads} thread(s); model selected on validation. Overrides: {args.overrides or 'none'}.",
        "",
    ]
    for task in TASKS:
        rows = [r for r in results if r["task"] == task]
        if not rows:
            continue
        lr = rows[0]["config"]["train"]["lr"]
        lines += [f"## {task} (lr {lr}, target {_pct(rows[0]['target'])} % on test)", ""]
        if task == "correspondence":
            header = ["model", "params", "exact %", "<=1 % diam", "<=2.5 %", "<=5 %"]
            header += ["refined: rings, exact %, <=1 %", "best epoch", "s/epoch", "epochs (s) to target"]
            table = []
            for r in rows:
                s, refined = r["selected"], r.get("refined")
                refined_text = (
                    "none chosen"
                    if not refined
                    else (f"{r['refine_rings']}, {_pct(refined['accuracy'])}, {_pct(refined['within_0.01'])}")
                )
                table.append(
                    [
                        r["model"],
                        f"{r['parameters']:,}",
                        _pct(s["accuracy"]),
                        _pct(s["within_0.01"]),
                        _pct(s["within_0.025"]),
                        _pct(s["within_0.05"]),
                        refined_text,
                        r["best_epoch"],
                        f"{r['seconds_per_epoch']:.1f}",
                        _to_target(r),
                    ]
                )
        else:
            header = ["model", "params", "accuracy %", "mean IoU", "per-part IoU", "best epoch", "s/epoch"]
            header += ["epochs (s) to target"]
            table = [
                [
                    r["model"],
                    f"{r['parameters']:,}",
                    _pct(r["selected"]["accuracy"]),
                    f"{r['selected']['mean_iou']:.3f}",
                    " ".join(f"{v:.2f}" for v in r["selected"]["per_class_iou"]),
                    r["best_epoch"],
                    f"{r['seconds_per_epoch']:.1f}",
                    _to_target(r),
                ]
                for r in rows
            ]
        lines += markdown_table(header, table)
        epochs = range(1, len(rows[0]["test_curve"]) + 1)
        curves = [[r["model"], *(f"{100 * a:.1f}" for a in r["test_curve"])] for r in rows]
        lines += ["", "Test accuracy of every epoch's model (%):", ""]
        lines += markdown_table(["model", *map(str, epochs)], curves)
        lines.append("")
    return lines


def _to_target(r: dict) -> str:
    return "not reached" if r["epochs_to_target"] is None else f"{r['epochs_to_target']} ({r['seconds_to_target']:.0f})"


def plot(results: list[dict], path: Path) -> None:
    tasks = [t for t in TASKS if any(r["task"] == t for r in results)]
    corr = [r for r in results if r["task"] == "correspondence"]
    columns = len(tasks) + (1 if corr else 0)
    fig, axes = plt.subplots(1, columns, figsize=(5.2 * columns, 4.2), squeeze=False)
    for ax, task in zip(axes[0], tasks):
        for r in (r for r in results if r["task"] == task):
            epochs = np.arange(1, len(r["test_curve"]) + 1)
            (line,) = ax.plot(epochs, 100 * np.asarray(r["test_curve"]), label=f"{r['model']} (test)")
            ax.plot(epochs, 100 * np.asarray(r["val_curve"], dtype=float), linestyle=":", color=line.get_color())
        ax.set(xlabel="epoch", ylabel="accuracy (%)", title=f"{task}: test (solid), validation (dotted)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    if corr:
        ax = axes[0][-1]
        for r in corr:
            curve = r["error_curve"]
            ax.plot(100 * np.asarray(curve["radii"]), 100 * np.asarray(curve["fractions"]), label=r["model"])
        ax.set(
            xlabel="geodesic error (% of diameter)",
            ylabel="% correspondences",
            xlim=(0, 10),
            ylim=(0, 100),
            title="correspondence: error curve (selected, refined)",
        )
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def kept_results(args, bodies: Path) -> dict:
    """Results of STEM.json whose run configuration equals this call's, by (task, model)."""
    path = result_file(args.out, ".json")
    if not args.keep or not path.is_file():
        return {}
    kept = {}
    for result in json.loads(path.read_text()).get("results", []):
        task, model = result["task"], result["model"]
        if task in TASKS and model in MODELS and _same(result["config"], run_config(task, model, bodies, args)):
            kept[(task, model)] = result
    return kept


def _same(stored: dict, config: dict) -> bool:
    as_text = lambda c: json.dumps(_relative(plain(parse_config(c).to_dict())), sort_keys=True)  # noqa: E731
    return as_text(stored) == as_text(config)


def _relative(value):
    """``value`` with paths inside the repository written relative to it (results name no local folders)."""
    if isinstance(value, str):
        return value[len(str(REPO)) + 1 :] if value.startswith(str(REPO) + "/") else value
    if isinstance(value, dict):
        return {k: _relative(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_relative(v) for v in value]
    return value


def main(argv=None) -> int:
    args = parse_args(argv)
    folder = args.data or REPO / "data" / f"bodies-{args.topology}-{args.count}"
    bodies = ensure_bodies(folder, args.count, args.n_test, args.seed, args.topology)
    kept = kept_results(args, bodies)
    results, started = [], time.perf_counter()
    for task in args.tasks:
        for model in args.models:
            if (task, model) in kept:
                print(f"{task} / {model}: kept from {result_file(args.out, '.json')}", flush=True)
                results.append(kept[(task, model)])
                continue
            print(f"{task} / {model}", flush=True)
            results.append(run_one(task, model, bodies, args))
            report = {
                "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
                "results": results,
                "wall_seconds": time.perf_counter() - started,
            }
            write_result(result_file(args.out, ".json"), _relative(plain(report)))
            write_markdown(result_file(args.out, ".md"), markdown(results, args))
            plot(results, result_file(args.out, ".png"))
    print("\n".join(markdown(results, args)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
