"""What ``benchmarks.experiments.report`` compares and how it presents it: constants, the models of each table,
the environment line, number formats, plots, ``report.md`` and the targets check. Nothing here measures
anything.
"""

from __future__ import annotations

import datetime
import os
import platform
from pathlib import Path

import matplotlib
import numpy as np
import torch
import torch_geometric
import yaml

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import matplotlib.ticker

from benchmarks.harness import REPO, commit, markdown_table, result_file, write_markdown

N_VERTICES = 6890
WIDTHS = (64, 128, 256, 512)
# The shipped FAUST recipe (configs/faust_single_scale.yaml): every sample within r0 fitted, r0/4 left out.
BODY_PATCH = dict(r0=5.5, n_samples=12000, n_max=5, inner_radius=1.375, subtract_center=True, backend="front")
BASELINE = "feastnet"


# --------------------------------------------------------------------------------------------------------
# Models compared
# --------------------------------------------------------------------------------------------------------


def timing_models(quick: bool) -> list[dict]:
    """The models of the timing and memory tables: label, registry name, options."""
    models = [
        {"label": "zernet s=1", "name": "zernet", "options": {"angular_resolution": 1}},
        {"label": "zernet s=4", "name": "zernet", "options": {"angular_resolution": 4}},
        {"label": "zernet s=16", "name": "zernet", "options": {"angular_resolution": 16}},
        {"label": "paper-zernet s=4", "name": "paper-zernet", "options": {"angular_resolution": 4}},
    ]
    if not quick:
        models += [
            {"label": "paper-zernet s=1", "name": "paper-zernet", "options": {"angular_resolution": 1}},
            {"label": "paper-zernet s=16", "name": "paper-zernet", "options": {"angular_resolution": 16}},
            {"label": "feastnet 32-64-128-256", "name": "feastnet", "options": {"widths": [32, 64, 128, 256]}},
        ]
    models.append({"label": "feastnet", "name": "feastnet", "options": {}})
    for model in models:
        model["options"].setdefault("widths", list(WIDTHS))
    return models


def training_models(angular_resolution: int) -> list[dict]:
    """The models of the training runs: zernet, the paper's formulation, FeaStNet.

    Widths come from the task (``widths`` unset), identical for the three. zernet and the paper's
    formulation use the same ``s`` (``--train-s``, default 4: the paper formulation's cost grows with s),
    so with the same seed they learn the same function (to rounding): the paper row shows what the
    per-layer fit and the s rotated copies cost in training time.
    """
    s = int(angular_resolution)
    return [
        {"label": "zernet", "name": "zernet", "options": {"angular_resolution": s}},
        {"label": "paper-zernet", "name": "paper-zernet", "options": {"angular_resolution": s}},
        {"label": "feastnet", "name": "feastnet", "options": {}},
    ]


def environment(threads: int) -> dict:
    return {
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "commit": commit(),
        "torch": torch.__version__,
        "torch_geometric": torch_geometric.__version__,
        "threads": threads,
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "load_average_start": load_average(),
    }


def load_average() -> list[float] | None:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except (AttributeError, OSError):
        return None


def aneurysm_recipe_summary() -> str:
    """One line naming the shipped aneurysm recipe's model, for the report's text."""
    model = yaml.safe_load((REPO / "configs" / "aneurysm_regression.yaml").read_text())["model"]
    options = ", ".join(f"{key} {value}" for key, value in model.items() if key != "name")
    return f"{model['name']}, {options}"


def _fmt(value, digits=3) -> str:
    if value is None:
        return "—"
    if isinstance(value, float):
        if value != 0 and (abs(value) < 1e-2 or abs(value) >= 1e4):
            return f"{value:.{digits}g}"
        return f"{value:.{digits}f}"
    return str(value)


def _mib(value) -> str:
    return "—" if value is None else f"{value / 2**20:,.0f}"


def plot_times(times: dict, path: Path) -> None:
    labels = list(times)
    step = [times[label]["step_seconds"] for label in labels]
    infer = [times[label]["inference_seconds"] for label in labels]
    y = np.arange(len(labels))
    fig, ax = plt.subplots(figsize=(8, 0.5 * len(labels) + 1.5))
    ax.barh(y - 0.2, step, height=0.4, label="training step")
    ax.barh(y + 0.2, infer, height=0.4, label="inference pass")
    ax.set_yticks(y, labels)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("seconds (median, log scale)")
    ax.set_title(f"{N_VERTICES}-vertex surface, {N_VERTICES}-way output, widths {'-'.join(map(str, WIDTHS))}")
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_memory(memory: dict, path: Path) -> None:
    labels = [label for label in memory if "peak_bytes" in memory[label]]
    if not labels:
        return
    y = np.arange(len(labels))
    fig, ax = plt.subplots(figsize=(8, 0.5 * len(labels) + 1.5))
    ax.barh(y - 0.2, [memory[label]["peak_bytes"] / 2**20 for label in labels], height=0.4, label="peak RSS")
    ax.barh(
        y + 0.2,
        [memory[label]["model_bytes"] / 2**20 for label in labels],
        height=0.4,
        label="added by the model and its training step",
    )
    ax.set_yticks(y, labels)
    ax.invert_yaxis()
    ax.set_xlabel("MiB")
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_training(task: dict, runs: dict, path: Path) -> None:
    key = "val_accuracy" if task["higher"] else "val_loss"
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for label, run in runs.items():
        history = run.get("history") or []
        if not history:
            continue
        epochs = [entry["epoch"] for entry in history]
        elapsed = np.cumsum([entry["seconds"] for entry in history])
        values = [entry.get(key) for entry in history]
        axes[0].plot(epochs, values, marker="o", label=label)
        axes[1].plot(elapsed, values, marker="o", label=label)
    axes[0].set_xlabel("epoch")
    axes[1].set_xlabel("training seconds")
    for ax in axes:
        ax.set_ylabel(key.replace("_", " "))
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.suptitle(task["task"])
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _header_lines(results: dict) -> list[str]:
    env = results["environment"]
    return [
        "# zernet vs the paper's formulation vs FeaStNet",
        "",
        f"Generated {env['date']} (commit `{env['commit']}`), torch {env['torch']}, torch_geometric {env['torch_geometric']}, "
        f"{env['threads']} CPU thread(s) on {env['machine']} ({env['cpus']} logical CPUs), float32.",
        "All measurements in one process on the same inputs; memory in one child process per model.",
        f"Load average (1, 5, 15 min) at the start: {env.get('load_average_start')}, at the end: "
        f"{env.get('load_average_end')}. Other processes on the machine slow every model, multi-threaded "
        "ones most: compare ratios within one report, and rerun on an idle machine for absolute times.",
        "",
    ]


def _inputs_lines(builds: dict) -> list[str]:
    return [
        "## Inputs and preprocessing",
        "",
        f"A generated human body (anny, topology `faust`, body 0 of seed 0, varied pose): "
        f"{builds['n_vertices']:,} vertices, {builds['n_faces']:,} faces, area {builds['area']:.0f}; patch "
        "settings " + ", ".join(f"{k} = {v}" for k, v in BODY_PATCH.items()) + ".",
        "",
        *markdown_table(
            ["what", "seconds", "notes"],
            [
                [
                    "zernet patch operator (polar coordinates, fit, sparse matrix)",
                    f"{builds['operator_seconds']:.2f}",
                    f"{builds['operator_nnz']:,} non-zeros, {builds['operator_nnz_per_row']:.1f} per row; used by "
                    "zernet and by paper-zernet (which re-fits from its patch data every layer and step)",
                ],
                ["FeaStNet graph (mesh edges)", f"{builds['edges_seconds']:.3f}", f"{builds['n_edges']:,} edges"],
            ],
            align="lrl",
        ),
        "",
    ]


def _times_lines(times: dict, rounds: int, picture: str) -> list[str]:
    base = times.get(BASELINE)
    lines = [
        f"## Training step and inference, {N_VERTICES}-way output",
        "",
        f"Widths {'-'.join(map(str, WIDTHS))} unless the name says otherwise; cross-entropy against vertex ids, "
        f"Adam; median of {rounds} rounds after one warm-up (models interleaved).",
        "",
    ]
    rows = []
    for label, t in times.items():
        ratio_s = t["step_seconds"] / base["step_seconds"] if base else None
        ratio_i = t["inference_seconds"] / base["inference_seconds"] if base else None
        rows.append(
            [
                label,
                f"{t['parameters']:,}",
                f"{t['step_seconds']:.3f}",
                _fmt(ratio_s, 2),
                f"{t['inference_seconds']:.3f}",
                _fmt(ratio_i, 2),
            ]
        )
    header = ["model", "parameters", "training step (s)", "× FeaStNet", "inference (s)", "× FeaStNet"]
    return lines + markdown_table(header, rows) + ["", f"![step and inference times]({picture})", ""]


def _memory_lines(memory: dict, picture: str) -> list[str]:
    lines = [
        "## Peak memory of a training step",
        "",
        "Child process per model: load the saved operator and edges, reset the peak counter, build the model, "
        "two training steps. 'Peak' is the resident-set peak from the reset on (Linux `VmHWM` after "
        "`/proc/self/clear_refs`; the process-lifetime `ru_maxrss` where unsupported); 'added' is that peak "
        "minus the resident size just before the model was built (inputs excluded).",
        "",
    ]
    base = memory.get(BASELINE, {}).get("model_bytes")
    rows = []
    for label, m in memory.items():
        if "error" in m:
            rows.append([label, f"failed: {m['error']}", "", ""])
            continue
        ratio = m["model_bytes"] / base if base else None
        rows.append([label, _mib(m["peak_bytes"]), _mib(m["model_bytes"]), _fmt(ratio, 2)])
    header = ["model", "peak RSS (MiB)", "added (MiB)", "added × FeaStNet"]
    return lines + markdown_table(header, rows) + ["", f"![peak memory]({picture})", ""]


def _training_intro(args) -> list[str]:
    return [
        "## Fixed-budget training runs",
        "",
        f"`zernet.training.train` (the training command's loop, data, splits and metrics); every model with the same "
        f"epochs, seed 0, no early stopping; the test metric of the epoch chosen on validation. Synthetic "
        f"tasks ({args.epochs} epochs): the recipe of configs/creatures.yaml for every model, s = {args.train_s} "
        f"for zernet and paper-zernet. Bodies ({args.bodies_epochs} epochs): the recipe of configs/demo.yaml "
        f"(40 generated coarse-615 bodies: 28 train, 4 validation, 8 test) for every model, 8-part segmentation "
        f"and correspondence (615 classes, the vertex index; metric: exact-vertex accuracy). "
        f"Aneurysm ({args.aneurysm_epochs} epochs): zernet runs the shipped recipe "
        f"(configs/aneurysm_regression.yaml: {aneurysm_recipe_summary()}), FeaStNet (its own Lin16 input "
        f"layer) the same widths, input features and "
        f"training settings except weight decay (none: with the recipe's coupled L2 of 1e-3 beside the L1 loss "
        f"its weights decay to zero and it predicts a constant); the paper's formulation is left out there (it "
        f"learns zernet's function at several times the cost).",
        "",
    ]


def _task_lines(task: dict, runs: dict, picture: str) -> list[str]:
    metric = task["metric"]
    base = runs.get(BASELINE, {}).get("summary", {}).get(metric)
    base_time = runs.get(BASELINE, {}).get("train_seconds")
    header = ["model", f"test {metric} ({'higher' if task['higher'] else 'lower'} is better)", "× FeaStNet"]
    header += ["epochs", "best epoch", "training seconds", "× FeaStNet"]
    rows = []
    for label, run in runs.items():
        if "error" in run:
            rows.append([label, f"failed: {run['error']}", "", "", "", "", ""])
            continue
        value = run["summary"].get(metric)
        ratio = value / base if (value is not None and base) else None
        ratio_t = run["train_seconds"] / base_time if base_time else None
        rows.append(
            [
                label,
                _fmt(value, 4),
                _fmt(ratio, 2),
                run["epochs"],
                run["best_epoch"],
                _fmt(run["train_seconds"], 1),
                _fmt(ratio_t, 2),
            ]
        )
    lines = [f"### {task['task']}", "", *markdown_table(header, rows)]
    baseline = next((run.get("baseline") for run in runs.values() if run.get("baseline")), None)
    if baseline:
        lines.append("")
        lines.append("Reference: " + ", ".join(f"{k} {_fmt(v, 4)}" for k, v in baseline.items()) + ".")
    return lines + ["", f"![{task['task']}]({picture})", ""]


def picture(stem: Path, part: str) -> Path:
    """The report's picture of ``part`` (``times``, ``memory``, ``training-<task>``), beside ``STEM.md``."""
    return result_file(stem, f"-{part}.png")


def write_report(stem: Path, results: dict, args) -> Path:
    """``STEM.md`` from the measured ``results`` (the sections that were measured)."""
    lines = _header_lines(results)
    if results.get("builds"):
        lines += _inputs_lines(results["builds"])
    if results.get("times"):
        lines += _times_lines(results["times"], args.rounds, picture(stem, "times").name)
    if results.get("memory"):
        lines += _memory_lines(results["memory"], picture(stem, "memory").name)
    training = results.get("training", {})
    if training:
        lines += _training_intro(args)
        for task in results["tasks"]:
            if training.get(task["slug"]):
                task_picture = picture(stem, f"training-{task['slug']}").name
                lines += _task_lines(task, training[task["slug"]], task_picture)
    lines += ["## Targets of issue 5", ""]
    lines += [f"- {line}" for line in results.get("targets", [])]
    return write_markdown(result_file(stem, ".md"), lines)


def check_targets(results: dict) -> list[str]:
    lines = []
    times = results.get("times", {})
    if "zernet s=4" in times and BASELINE in times:
        ratio = times["zernet s=4"]["step_seconds"] / times[BASELINE]["step_seconds"]
        verdict = "met" if ratio <= 0.8 else "NOT met"
        lines.append(
            f"zernet s=4 training step = {ratio:.2f} × FeaStNet's at widths {'-'.join(map(str, WIDTHS))} "
            f"(target <= 0.80): **{verdict}**."
        )
    for task in results.get("tasks", []):
        runs = results.get("training", {}).get(task["slug"], {})
        ours = runs.get("zernet", {}).get("summary", {}).get(task["metric"])
        theirs = runs.get(BASELINE, {}).get("summary", {}).get(task["metric"])
        if ours is None or theirs is None:
            continue
        better = ours > theirs if task["higher"] else ours < theirs
        lines.append(
            f"{task['task']}: zernet {task['metric']} {ours:.4f} vs FeaStNet {theirs:.4f} at equal epochs: "
            f"**{'zernet better' if better else 'zernet NOT better'}**."
        )
    return lines
