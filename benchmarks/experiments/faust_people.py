"""FAUST correspondence on real people: recipes trained on some people, chosen on another, scored on a third.

Generated bodies measure the generator's distribution; this benchmark measures people. It reads the user's
copy of FAUST's training registrations (``tr_reg_000`` ... ``tr_reg_079``: scan ``XXX`` shows person
``XXX // 10`` in pose ``XXX % 10``) and, for each recipe of ``configs/recipes/faust_people.yaml`` (overrides of
``configs/faust_single_scale.yaml``):

1. trains on people 0-5 (scans 000-059);
2. validates on person 6 (060-069) every epoch: the epoch and the refinement (rings, spectral radius) are
   chosen there, never on the scored person;
3. scores the chosen model on person 7 (070-079): exact accuracy unrefined and refined, within 1 % of the
   diameter, beyond 10 % of it;
4. writes ``benchmarks/experiments/results/faust_people.{json,md}``: per recipe the scores, the time, and per
   epoch the training and validation loss and accuracy with the gap between them. Figures only: never a scan,
   a label or anything derived from them.

``--rotate`` swaps the two held people (chosen on 7, scored on 6), so each recipe is scored on both. Scans
080-099 (people 8 and 9) are FAUST's test set: the benchmark refuses a data folder that holds them unless
``--allow-test-people``, and never reads them either way.

A run folder that already holds ``metrics.json`` is read, not trained again: later invocations add recipes.
``--rescore`` scores such folders again with their recipe's refinement as the configuration now gives it
(``eval.refine_rings``, ``refine_passes``, ``refine_spectral``, chosen on the validated person), written beside
as ``metrics-rescored.json``, which later invocations read in place of the run's own scores; the training
figures stay those of the run.

    .venv/bin/python -m benchmarks.experiments.faust_people --data ~/data/MPI-FAUST --runs ~/runs/faust_people \\
        --cache-dir ~/cache/zernet --recipes shipped scratch-xyz-hks
"""

from __future__ import annotations

import time
from pathlib import Path

import yaml

from benchmarks.harness import (
    EXPERIMENT_RESULTS,
    RECIPES,
    REPO,
    add_data,
    add_out,
    add_threads,
    arguments,
    markdown_table,
    result_file,
    write_json,
    write_markdown,
)
from zernet.inference.model_file import load_checkpoint
from zernet.training import evaluate, load_config, train
from zernet.training.config import apply_overrides

RECIPE_FILE = RECIPES / "faust_people.yaml"
TRAIN_PEOPLE = range(0, 6)
HELD_PEOPLE = (6, 7)  # (validated on, scored on); --rotate swaps them


def scans_of(people) -> str:
    """Registration numbers of whole people as a range string ("0:60" for people 0-5)."""
    people = list(people)
    return f"{10 * people[0]}:{10 * (people[-1] + 1)}"


def load_recipes(path: Path = RECIPE_FILE) -> tuple[dict, dict[str, list[str]]]:
    """The base configuration and each recipe's overrides."""
    catalogue = yaml.safe_load(path.read_text())
    base = load_config(REPO / catalogue["base"])
    return base, {name: list(overrides or []) for name, overrides in catalogue["recipes"].items()}


def recipe_config(base: dict, overrides: list[str], data: Path, held: tuple[int, int], args) -> dict:
    """The run configuration: the recipe's overrides, then the split by person, the cache and the threads."""
    validated_on, scored_on = held
    split = [
        f"data.root={data}",
        f"data.train_indices='{scans_of(TRAIN_PEOPLE)}'",
        f"data.val_indices='{scans_of([validated_on])}'",
        f"data.test_indices='{scans_of([scored_on])}'",
        f"cache_dir={args.cache_dir}",
        f"train.threads={args.threads}",
        "eval.renders=0",
    ]
    return apply_overrides(base, [*overrides, *split, *args.set])


def check_data(data: Path, allow_test_people: bool) -> None:
    """Refuse a folder holding FAUST's test people unless told: they are the independent test."""
    registrations = data / "training" / "registrations"
    folder = registrations if registrations.is_dir() else data
    test_people = sorted(folder.glob("tr_reg_08[0-9].ply")) + sorted(folder.glob("tr_reg_09[0-9].ply"))
    if test_people and not allow_test_people:
        raise SystemExit(
            f"{folder} holds FAUST's test people ({test_people[0].name} ...): this benchmark develops recipes on "
            "people 0-7 only; point --data at a copy of 000-079 or pass --allow-test-people (they are never read)"
        )


def epoch_rows(history: list[dict]) -> list[dict]:
    """Per epoch: training and validation loss and accuracy, and the gap between the accuracies."""
    rows = []
    for entry in history:
        row = {key: entry.get(key) for key in ("epoch", "train_loss", "train_accuracy", "val_loss", "val_accuracy")}
        if row["train_accuracy"] is not None and row["val_accuracy"] is not None:
            row["gap"] = row["train_accuracy"] - row["val_accuracy"]
        rows.append(row)
    return rows


def rescored(run_dir: Path, config: dict) -> dict:
    """The run's model scored again with the refinement ``config`` gives (chosen on its validation split)."""
    evaluation = config["eval"]
    metrics = evaluate(
        run_dir,
        progress=False,
        refine_rings=evaluation["refine_rings"],
        refine_passes=evaluation.get("refine_passes", [1]),
        refine_spectral=evaluation["refine_spectral"],
    )
    write_json(run_dir / "metrics-rescored.json", metrics)
    return metrics


def run_recipe(name: str, config: dict, run_dir: Path, rescore: bool = False) -> dict:
    """Train the recipe (unless its run folder is complete) and read its figures."""
    started = time.perf_counter()
    if not (run_dir / "metrics.json").is_file():
        train(config, run_dir, progress=False, overwrite=True)
    seconds = time.perf_counter() - started
    metrics = yaml.safe_load((run_dir / "metrics.json").read_text())
    scores = run_dir / "metrics-rescored.json"
    if rescore or scores.is_file():
        again = rescored(run_dir, config) if rescore else yaml.safe_load(scores.read_text())
        metrics = {**metrics, **again, "train_seconds": metrics.get("train_seconds", seconds)}
    history = load_checkpoint(run_dir / "last.pt")["state"]["history"]
    refined = metrics["summary"]
    unrefined = metrics.get("unrefined_summary", refined)
    return {
        "recipe": name,
        "best_epoch": metrics.get("best_epoch"),
        "refine_rings": metrics.get("refine_rings"),
        "refine_passes": metrics.get("refine_passes", 1),
        "refine_spectral": metrics.get("refine_spectral"),
        "scored_person": {
            "exact_unrefined": unrefined["accuracy"],
            "exact_refined": refined["accuracy"],
            "within_1pct_unrefined": unrefined.get("within_0.01"),
            "within_1pct_refined": refined.get("within_0.01"),
            "beyond_10pct_unrefined": 1.0 - unrefined["within_0.1"],
            "beyond_10pct_refined": 1.0 - refined["within_0.1"],
        },
        "per_epoch": epoch_rows(history),
        # Training time as the run measured it; 0 when an earlier invocation trained it.
        "train_seconds": metrics.get("train_seconds", seconds),
    }


def markdown(result: dict) -> list[str]:
    validated_on, scored_on = result["held_people"]
    lines = [
        "# FAUST correspondence on real people",
        "",
        f"Trained on people 0-5 (scans 000-059), epoch and refinement chosen on person {validated_on}, scored on "
        f"person {scored_on} (10 scans each). Times are training wall-clock on the machine of the JSON file, "
        "as loaded as it was: compare them only roughly.",
        "",
    ]
    rows = []
    for entry in result["recipes"]:
        s = entry["scored_person"]
        rows.append(
            [
                entry["recipe"],
                f"{entry['best_epoch']}",
                f"{100 * s['exact_unrefined']:.1f} %",
                f"{100 * s['exact_refined']:.1f} %",
                f"{100 * s['within_1pct_refined']:.2f} %" if s["within_1pct_refined"] is not None else "-",
                f"{100 * s['beyond_10pct_unrefined']:.2f} / {100 * s['beyond_10pct_refined']:.2f} %",
                f"{entry['refine_rings']} x {entry.get('refine_passes', 1)} / {entry['refine_spectral']}",
                f"{entry['train_seconds'] / 60:.0f} min",
            ]
        )
    lines += markdown_table(
        [
            "recipe",
            "epoch",
            "exact",
            "refined",
            "within 1 %",
            "beyond 10 % (unrefined / refined)",
            "rings x passes / radius",
            "time",
        ],
        rows,
    )
    for entry in result["recipes"]:
        lines += ["", f"## {entry['recipe']}: per epoch (validation: person {validated_on})", ""]
        lines += markdown_table(
            ["epoch", "train loss", "val loss", "train acc", "val acc", "gap"],
            [
                [
                    str(row["epoch"]),
                    _number(row["train_loss"]),
                    _number(row["val_loss"]),
                    _percent(row["train_accuracy"]),
                    _percent(row["val_accuracy"]),
                    _percent(row.get("gap")),
                ]
                for row in entry["per_epoch"]
            ],
        )
    return lines


def _number(value) -> str:
    return "-" if value is None else f"{value:.3f}"


def _percent(value) -> str:
    return "-" if value is None else f"{100 * value:.1f} %"


def main() -> None:
    parser = arguments(__doc__)
    add_data(parser, None, "MPI-FAUST folder with tr_reg_000-079 (people 0-7)")
    parser.add_argument("--runs", type=Path, required=True, help="folder of the run folders (outside the repo)")
    parser.add_argument("--cache-dir", type=Path, required=True, help="patch-operator cache (outside the repo)")
    parser.add_argument("--recipes", nargs="+", help="recipe names (default: all of configs/recipes/faust_people.yaml)")
    parser.add_argument("--rotate", action="store_true", help="choose on person 7, score on person 6")
    add_threads(parser, default=2)
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="overrides for every recipe")
    parser.add_argument("--allow-test-people", action="store_true")
    parser.add_argument(
        "--rescore",
        action="store_true",
        help="score trained run folders again with the refinement the config gives now",
    )
    add_out(parser, EXPERIMENT_RESULTS / "faust_people")
    args = parser.parse_args()

    if args.data is None:
        raise SystemExit("--data DIR is required: the MPI-FAUST folder holding tr_reg_000-079")
    check_data(args.data, args.allow_test_people)
    base, recipes = load_recipes()
    names = args.recipes or list(recipes)
    unknown = sorted(set(names) - set(recipes))
    if unknown:
        raise SystemExit(f"unknown recipe(s) {unknown}; {RECIPE_FILE.name} has {sorted(recipes)}")
    held = HELD_PEOPLE[::-1] if args.rotate else HELD_PEOPLE
    entries = []
    for name in names:
        run_dir = args.runs / (f"{name}-held{held[0]}{held[1]}")
        config = recipe_config(base, recipes[name], args.data, held, args)
        entries.append(run_recipe(name, config, run_dir, args.rescore))
        print(f"{name}: {entries[-1]['scored_person']}", flush=True)
    result = {"train_people": list(TRAIN_PEOPLE), "held_people": list(held), "recipes": entries}
    stem = Path(f"{args.out}_rotated") if args.rotate else args.out
    write_json(result_file(stem, ".json"), result)
    write_markdown(result_file(stem, ".md"), markdown(result))


if __name__ == "__main__":
    main()
