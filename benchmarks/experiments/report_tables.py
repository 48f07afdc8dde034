"""What ``benchmarks/report.py`` compares and how it presents it: constants, the models of each table, the
environment line, number formats, plots, ``report.md`` and the targets check. Nothing here measures anything.
"""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
from pathlib import Path

import matplotlib
import numpy as np
import torch
import torch_geometric
import yaml

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
N_VERTICES = 6890
WIDTHS = (64, 128, 256, 512)
BODY_AREA = 15000.0
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
    try:
        commit = (
            subprocess.run(
                ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT
            ).stdout.strip()
            or "unknown"
        )
    except OSError:
        commit = "unknown"
    return {
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "commit": commit,
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


def plain(value):
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


def aneurysm_recipe_summary() -> str:
    """One line naming the shipped aneurysm recipe's model, for the report's text."""
    model = yaml.safe_load((ROOT / "configs" / "aneurysm_regression.yaml").read_text())["model"]
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
        f"Generated {env['date']} by `{results['command']}` "
        f"(commit `{env['commit']}`), torch {env['torch']}, torch_geometric {env['torch_geometric']}, "
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
        "| what | seconds | notes |",
        "|---|---:|---|",
        f"| zernet patch operator (polar coordinates, fit, sparse matrix) | {builds['operator_seconds']:.2f} | "
        f"{builds['operator_nnz']:,} non-zeros, {builds['operator_nnz_per_row']:.1f} per row; used by zernet "
        "and by paper-zernet (which re-fits from its patch data every layer and step) |",
        f"| FeaStNet graph (mesh edges) | {builds['edges_seconds']:.3f} | {builds['n_edges']:,} edges |",
        "",
    ]


def _times_lines(times: dict, rounds: int) -> list[str]:
    base = times.get(BASELINE)
    lines = [
        f"## Training step and inference, {N_VERTICES}-way output",
        "",
        f"Widths {'-'.join(map(str, WIDTHS))} unless the name says otherwise; cross-entropy against vertex ids, "
        f"Adam; median of {rounds} rounds after one warm-up (models interleaved).",
        "",
        "| model | parameters | training step (s) | × FeaStNet | inference (s) | × FeaStNet |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for label, t in times.items():
        ratio_s = t["step_seconds"] / base["step_seconds"] if base else None
        ratio_i = t["inference_seconds"] / base["inference_seconds"] if base else None
        lines.append(
            f"| {label} | {t['parameters']:,} | {t['step_seconds']:.3f} | {_fmt(ratio_s, 2)} | "
            f"{t['inference_seconds']:.3f} | {_fmt(ratio_i, 2)} |"
        )
    return lines + ["", "![step and inference times](report-times.png)", ""]


def _memory_lines(memory: dict) -> list[str]:
    lines = [
        "## Peak memory of a training step",
        "",
        "Child process per model: load the saved operator and edges, reset the peak counter, build the model, "
        "two training steps. 'Peak' is the resident-set peak from the reset on (Linux `VmHWM` after "
        "`/proc/self/clear_refs`; the process-lifetime `ru_maxrss` where unsupported); 'added' is that peak "
        "minus the resident size just before the model was built (inputs excluded).",
        "",
        "| model | peak RSS (MiB) | added (MiB) | added × FeaStNet |",
        "|---|---:|---:|---:|",
    ]
    base = memory.get(BASELINE, {}).get("model_bytes")
    for label, m in memory.items():
        if "error" in m:
            lines.append(f"| {label} | failed: {m['error']} | | |")
            continue
        ratio = m["model_bytes"] / base if base else None
        lines.append(f"| {label} | {_mib(m['peak_bytes'])} | {_mib(m['model_bytes'])} | {_fmt(ratio, 2)} |")
    return lines + ["", "![peak memory](report-memory.png)", ""]


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


def _task_lines(task: dict, runs: dict) -> list[str]:
    metric = task["metric"]
    base = runs.get(BASELINE, {}).get("summary", {}).get(metric)
    base_time = runs.get(BASELINE, {}).get("train_seconds")
    lines = [
        f"### {task['task']}",
        "",
        f"| model | test {metric} ({'higher' if task['higher'] else 'lower'} is better) | "
        f"× FeaStNet | epochs | best epoch | training seconds | × FeaStNet |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for label, run in runs.items():
        if "error" in run:
            lines.append(f"| {label} | failed: {run['error']} | | | | | |")
            continue
        value = run["summary"].get(metric)
        ratio = value / base if (value is not None and base) else None
        ratio_t = run["train_seconds"] / base_time if base_time else None
        lines.append(
            f"| {label} | {_fmt(value, 4)} | {_fmt(ratio, 2)} | {run['epochs']} | "
            f"{run['best_epoch']} | {_fmt(run['train_seconds'], 1)} | {_fmt(ratio_t, 2)} |"
        )
    baseline = next((run.get("baseline") for run in runs.values() if run.get("baseline")), None)
    if baseline:
        lines.append("")
        lines.append("Reference: " + ", ".join(f"{k} {_fmt(v, 4)}" for k, v in baseline.items()) + ".")
    return lines + ["", f"![{task['task']}](report-training-{task['slug']}.png)", ""]


def write_report(out: Path, results: dict, args) -> Path:
    """``<out>/report.md`` from the measured ``results`` (the sections that were measured)."""
    lines = _header_lines(results)
    if results.get("builds"):
        lines += _inputs_lines(results["builds"])
    if results.get("times"):
        lines += _times_lines(results["times"], args.rounds)
    if results.get("memory"):
        lines += _memory_lines(results["memory"])
    training = results.get("training", {})
    if training:
        lines += _training_intro(args)
        for task in results["tasks"]:
            if training.get(task["slug"]):
                lines += _task_lines(task, training[task["slug"]])
    lines += ["## Targets of issue 5", ""]
    lines += [f"- {line}" for line in results.get("targets", [])]
    lines.append("")
    path = out / "report.md"
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


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
