"""The paper's aneurysm leave-one-out (Table 3), run with zernet's own training command.

For each of the paper's five held-out cases, train on the other 25 aneurysms (a few of them carved off for
validation, never the held-out case), select the epoch on validation, and evaluate on the held-out case.
Prints our MAPE, RRMSE, PCC, HR10/20/30 beside the paper's ZerNet numbers, with the epochs and the wall time
used, then the same columns for the recipe's physics prior alone (the membrane stress estimate with a power
law fitted on the other cases, no network), and writes ``benchmarks/experiments/results/aneurysm_loo.json``.

    .venv/bin/python -m benchmarks.experiments.aneurysm_loo         # configs/aneurysm_regression.yaml
    .venv/bin/python -m benchmarks.experiments.aneurysm_loo --set train.epochs=30 --cases TP_Ia105I TP_Ia33I
    .venv/bin/python -m benchmarks.experiments.aneurysm_loo --seeds 3    # each fold an ensemble of three seeds

Needs the data folder (``--data``, default ``data/aneurysm``: your copy of the aneurysm cases); every fold's run folder is kept under
``--runs`` (default ``runs/aneurysm_loo``), so a fold that already has ``metrics.json`` is not retrained
(``--retrain`` forces it) and an interrupted fold resumes from its last checkpoint. A fold folder trained
with another recipe (its ``config.yaml`` differs from this call's configuration in anything but the data
path, threads, device, evaluation or cache settings) is refused, so the table never mixes recipes.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import EXPERIMENT_RESULTS, REPO, add_data, add_out, arguments, result_file, write_json
from zernet.data.features import MEMBRANE_PRESTRESSES
from zernet.geometry import load_surface, membrane_stress
from zernet.metrics import regression_scores
from zernet.training import apply_overrides, evaluate, load_config, resolve_config, train

# The paper's Table 3, ZerNet columns (MAPE, RRMSE, HR in %; PCC as a fraction).
PAPER = {
    "TP_Ia105I": {"MAPE": 10.11, "RRMSE": 13.04, "PCC": 0.91, "HR10": 65.84, "HR20": 90.81, "HR30": 97.24},
    "TP_Ia166I": {"MAPE": 9.57, "RRMSE": 12.97, "PCC": 0.87, "HR10": 68.92, "HR20": 90.75, "HR30": 95.21},
    "TP_Ia182I": {"MAPE": 14.32, "RRMSE": 18.70, "PCC": 0.87, "HR10": 45.63, "HR20": 77.60, "HR30": 92.58},
    "TP_Ia32I": {"MAPE": 13.80, "RRMSE": 16.32, "PCC": 0.88, "HR10": 50.48, "HR20": 82.53, "HR30": 93.24},
    "TP_Ia33I": {"MAPE": 9.60, "RRMSE": 13.98, "PCC": 0.90, "HR10": 65.30, "HR20": 90.70, "HR30": 97.61},
}
COLUMNS = ("MAPE", "RRMSE", "PCC", "HR10", "HR20", "HR30")


def _as_paper_units(scores: dict) -> dict:
    """Our fractions -> the paper's units (percent, PCC as a fraction)."""
    return {c: scores[c] if c == "PCC" else 100.0 * scores[c] for c in COLUMNS}


def _better(ours: dict, paper: dict) -> bool:
    """Better than the paper on every column: lower errors, higher PCC and hit rates."""
    lower = ours["MAPE"] < paper["MAPE"] and ours["RRMSE"] < paper["RRMSE"]
    higher = all(ours[c] > paper[c] for c in ("PCC", "HR10", "HR20", "HR30"))
    return lower and higher


# Settings that do not change what a fold learns: a run folder trained with other values is reused.
_RUN_ONLY = (("data", "root"), ("train", "threads"), ("train", "device"))


def recipe_differences(stored: dict, intended: dict) -> list[str]:
    """Dotted keys whose values differ between two resolved configurations, ignoring :data:`_RUN_ONLY`,
    ``eval`` and ``cache_dir``."""
    differences = []
    for section in ("data", "patch", "model", "train"):
        a, b = stored.get(section) or {}, intended.get(section) or {}
        for key in sorted(set(a) | set(b)):
            if (section, key) not in _RUN_ONLY and a.get(key) != b.get(key):
                differences.append(f"{section}.{key}: {a.get(key)!r} in the run folder, {b.get(key)!r} here")
    return differences


def membrane_baseline(data: Path, cases: list[str], cache_dir: str) -> dict:
    """The physics prior alone: per held-out case, the membrane stress under unit pressure
    (:func:`zernet.geometry.membrane.membrane_stress` at the recipe's middle prestress) mapped to the target by a power
    law ``y = b · σ^a`` fitted (least squares on logs) to every vertex of the other cases. Scores in the
    paper's units. Says how much of our result the network adds over the estimate it is given."""
    surfaces = {path.stem: load_surface(path, fields=["J2m"]) for path in sorted(Path(data).glob("*.mat"))}
    prestress = MEMBRANE_PRESTRESSES[len(MEMBRANE_PRESTRESSES) // 2]
    log_stress = {name: np.log(membrane_stress(s, prestress, cache_dir=cache_dir)) for name, s in surfaces.items()}
    log_target = {name: np.log(s.fields["J2m"].reshape(-1)) for name, s in surfaces.items()}
    scores = {}
    for case in cases:
        others = [name for name in surfaces if name != case]
        slope, offset = np.polyfit(
            np.concatenate([log_stress[n] for n in others]), np.concatenate([log_target[n] for n in others]), 1
        )
        prediction = np.exp(offset + slope * log_stress[case])
        scores[case] = _as_paper_units(regression_scores(prediction, np.exp(log_target[case])))
    return scores


def train_fold(config: dict, run_dir: Path, retrain: bool) -> dict | None:
    """Train one fold into ``run_dir`` (or reuse / resume what is there); its metrics, or None on a recipe
    mismatch (printed)."""
    if (run_dir / "config.yaml").exists() and not retrain:
        # Resolving the stored configuration fills in options added since with their defaults, which
        # reproduce the behaviour of the code the folder was trained with.
        stored = resolve_config(load_config(run_dir / "config.yaml"))
        differences = recipe_differences(stored, resolve_config(config))
        if differences:
            print(
                f"{run_dir} was trained with another recipe; use --retrain or another --runs folder:\n  "
                + "\n  ".join(differences)
            )
            return None
    metrics_path = run_dir / "metrics.json"
    if metrics_path.exists() and not retrain:
        return json.loads(metrics_path.read_text())
    resume = (run_dir / "last.pt").exists() and not retrain
    return train(config if not resume else None, run_dir, resume=resume, progress=False)


def main(argv: list[str] | None = None) -> int:
    parser = arguments(__doc__)
    parser.add_argument("--config", type=Path, default=REPO / "configs" / "aneurysm_regression.yaml")
    add_data(parser, Path("data/aneurysm"), "folder of the aneurysm .mat files (your copy)")
    parser.add_argument("--cases", nargs="+", default=list(PAPER))
    parser.add_argument("--runs", type=Path, default=REPO / "runs" / "aneurysm_loo")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides")
    parser.add_argument(
        "--seeds",
        type=int,
        default=1,
        help="train each fold with train.seed = 0 .. SEEDS-1 (run folders CASE, CASE-seed1, ...) "
        "and score the ensemble of the seeds (default 1: one model)",
    )
    parser.add_argument("--retrain", action="store_true", help="train folds that already have metrics")
    add_out(parser, EXPERIMENT_RESULTS / "aneurysm_loo")
    args = parser.parse_args(argv)

    if not args.data.is_dir():
        print(f"aneurysm data folder not found: {args.data} (give --data)")
        return 2
    if args.seeds < 1:
        parser.error("--seeds must be >= 1")
    base = apply_overrides(load_config(args.config), [f"data.root={args.data}", *args.set])

    results = {}
    for case in args.cases:
        start = time.perf_counter()
        members = []  # (run folder, metrics) per seed
        for seed in range(args.seeds):
            run_dir = args.runs / (case if seed == 0 else f"{case}-seed{seed}")
            config = apply_overrides(base, [f"data.test={case}"] + ([f"train.seed={seed}"] if seed else []))
            metrics = train_fold(config, run_dir, args.retrain)
            if metrics is None:
                return 2
            members.append((run_dir, metrics))
        if len(members) == 1:
            scores = _as_paper_units(members[0][1]["per_shape"][case])
        else:
            ensemble = evaluate([run_dir for run_dir, _ in members], progress=False)
            scores = _as_paper_units(ensemble["per_shape"][case])
        first = members[0][1]
        results[case] = {
            "ours": scores,
            "paper": PAPER[case],
            "better_than_paper": _better(scores, PAPER[case]),
            "seeds": args.seeds,
            "members_MAPE": [100.0 * m["per_shape"][case]["MAPE"] for _, m in members],
            "epochs_trained": first.get("epochs_trained"),
            "best_epoch": [m.get("best_epoch") for _, m in members] if args.seeds > 1 else first.get("best_epoch"),
            "train_seconds": sum(m.get("train_seconds") or 0.0 for _, m in members),
            "baseline": first.get("baseline"),
            "wall_seconds_this_call": time.perf_counter() - start,
        }

    header = f"{'case':<11}" + "".join(f"{c:>16}" for c in COLUMNS) + f"{'epochs':>8}{'train s':>9}"
    print(header)
    print("-" * len(header))
    for case, row in results.items():
        cells = "".join(f"{row['ours'][c]:>8.2f} ({row['paper'][c]:>5.2f})" for c in COLUMNS)
        print(f"{case:<11}{cells}{row['epochs_trained'] or 0:>8}{row['train_seconds'] or 0:>9.0f}")
    mean = {c: sum(r["ours"][c] for r in results.values()) / len(results) for c in COLUMNS}
    paper_mean = {c: sum(PAPER[k][c] for k in results) / len(results) for c in COLUMNS}
    print(f"{'mean':<11}" + "".join(f"{mean[c]:>8.2f} ({paper_mean[c]:>5.2f})" for c in COLUMNS))
    what = f"ensembles of {args.seeds} seeds" if args.seeds > 1 else "one model per fold"
    print(f"ours ({what}; train s summed over the seeds) and the paper's ZerNet in brackets; MAPE, RRMSE, HR in %")
    print(
        f"better than the paper on every column: "
        f"{sum(r['better_than_paper'] for r in results.values())} of {len(results)} cases"
    )

    print("\nthe physics prior alone (membrane stress, power law fitted on the other cases; no network):")
    baseline = membrane_baseline(args.data, list(results), base.get("cache_dir") or ".zernet-cache")
    for case, row in baseline.items():
        print(f"{case:<11}" + "".join(f"{row[c]:>16.2f}" for c in COLUMNS))
    baseline_mean = {c: sum(r[c] for r in baseline.values()) / len(baseline) for c in COLUMNS}
    print(f"{'mean':<11}" + "".join(f"{baseline_mean[c]:>16.2f}" for c in COLUMNS))

    table = {
        "config": base,
        "seeds": args.seeds,
        "cases": results,
        "mean": mean,
        "paper_mean": paper_mean,
        "membrane_baseline": {"cases": baseline, "mean": baseline_mean},
    }
    write_json(result_file(args.out, ".json"), table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
