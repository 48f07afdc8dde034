"""The paper's correspondence experiment with FAUST's structure, on generated bodies: few people, new people.

FAUST is 10 people in 10 poses each; trained on 8 of them, a model is tested on the 2 others. This benchmark
builds the same structure from generated bodies (``zernet bodies DIR --people 10``: 100 bodies, body ``i`` is
person ``i // 10``, the people's phenotypes spread over the body model's ranges) and, in one run:

1. checks how different the people are: the rest-pose height of each, and the mean distance between two
   people's rest poses at the same template vertex (after centring), against 10 bodies whose phenotypes are
   drawn independently (what ``zernet bodies`` without ``--people`` gives);
2. trains each recipe of ``--recipes`` (``configs/recipes/few_people.yaml``: overrides of
   ``configs/faust_single_scale.yaml``): 72
   training bodies of people 0-7, 8 validation bodies carved from them by the FAUST loader, the 20 test bodies
   of people 8 and 9; a recipe that starts from pretrained weights first trains (once) on ``--pretrain-count``
   bodies of other, independently drawn people (``zernet bodies --seed 1``), which share no phenotype with the
   ten;
3. keeps every epoch's weights (``train.keep_epochs``) and scores each on the test people: exact accuracy
   unrefined and refined (the ring count the run chose on validation), the share within 1 % of the diameter
   and beyond 10 % of it, with the validation accuracy the run saw; the error curve of the selected model;
4. scores each recipe's selected model on 2 more people of a third draw (``zernet bodies --people 2``, seed
   ``--seed`` + 2, written to ``--unseen`` once): the validation bodies are the training people in other
   poses, so they cannot tell which recipe carries better to new people; these can, without the test people;
5. writes ``benchmarks/experiments/results/few_people.{json,md,png}`` (``--out``).

Recipes are compared on validation (both kinds); the test columns are reported, never used to choose.

    .venv/bin/python -m benchmarks.experiments.few_people --topology faust --recipes shipped regularised pretrained
    .venv/bin/python -m benchmarks.experiments.few_people --topology coarse-1229 --epochs 8 --threads 1  # minutes

The shipped backbones this benchmark once exported are made by ``benchmarks.experiments.release`` now.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch
import yaml

from benchmarks.harness import (
    CACHE,
    EXPERIMENT_RESULTS,
    RECIPES,
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
from zernet.data.bodies import BodyGenerator
from zernet.data.bodies.pose import draw_phenotype
from zernet.inference import load_checkpoint
from zernet.io_utils import atomic_save_torch, write_json
from zernet.training import build_dataset, evaluate, load_config, parse_config, train
from zernet.training.config import apply_overrides

#: The recipe catalogue: ``base`` (the run configuration), ``recipes`` (name -> --set overrides),
#: ``pretrained_on_other_people`` and ``renumbered`` (see the file's comments).
BOOK = yaml.safe_load((RECIPES / "few_people.yaml").read_text())
CONFIG = REPO / BOOK["base"]


def base_config() -> dict:
    """The base run configuration with the catalogue's ``base_overrides``: the recipe the others vary."""
    return apply_overrides(load_config(CONFIG), BOOK.get("base_overrides", []))


N_PEOPLE, N_POSES = 10, 10
#: People of the third draw on which recipes are compared (the validation split holds the training people).
N_UNSEEN = 2
N_VERTICES = {"faust": 6890, "coarse-1229": 1229, "coarse-615": 615, "coarse-369": 369}


def renumbered_checkpoint(source: Path, target: Path, seed: int = 0) -> Path:
    """``source`` (a correspondence checkpoint storing its template) with its template's vertices in a random
    order, the output rows following them: the same model for a template of another vertex order (written once)."""
    if target.is_file():
        return target
    checkpoint = load_checkpoint(source)
    order = np.random.default_rng(seed).permutation(len(checkpoint["template_vertices"]))
    renumbered = np.empty_like(order)
    renumbered[order] = np.arange(len(order))
    checkpoint["template_vertices"] = checkpoint["template_vertices"][order]
    checkpoint["template_faces"] = torch.as_tensor(renumbered)[checkpoint["template_faces"]]
    for name in ("output.weight", "output.bias"):
        checkpoint["model"][name] = checkpoint["model"][name][order]
    atomic_save_torch(checkpoint, target)
    return target


def people_bodies(root: Path, topology: str, seed: int, cache_dir: Path) -> Path:
    """The 10 x 10 people bodies under ``root`` (written once); returns the FAUST-layout folder."""
    ensure_bodies(root, N_PEOPLE * N_POSES, 20, seed, topology, people=N_PEOPLE, cache_dir=cache_dir)
    return root / "correspondence"


def unseen_people(root: Path, topology: str, seed: int, cache_dir: Path) -> Path:
    """:data:`N_UNSEEN` more people x 10 poses (seed ``seed + 2``), neither trained on nor tested: the
    recipes are compared on them (written once); returns the FAUST-layout folder."""
    ensure_bodies(root, N_UNSEEN * N_POSES, N_POSES, seed + 2, topology, people=N_UNSEEN, cache_dir=cache_dir)
    return root / "correspondence"


def unseen_scores(run_dir: Path, config: dict, unseen_root: Path, rings: int, radius: float) -> dict:
    """The run's selected model on the unseen people: exact accuracy unrefined and refined as the run chose
    (its ``rings``, then its global ``radius``), and the share beyond 10 % of the diameter unrefined."""
    config = {**config, "data": {**config["data"], "root": str(unseen_root)}}
    config["data"].update({"train_indices": [], "test_indices": f"0:{N_UNSEEN * N_POSES}", "val_count": 0})
    dataset = build_dataset(parse_config(config), progress=False)
    result = evaluate(
        run_dir / "best.pt",
        dataset=dataset,
        split="test",
        progress=False,
        refine_rings=[rings],
        refine_spectral=[radius],
    )
    refined, unrefined = result["summary"], result.get("unrefined_summary", result["summary"])
    return {
        "exact_unrefined": unrefined["accuracy"],
        "exact_refined": refined["accuracy"],
        "beyond_10pct_unrefined": 1.0 - unrefined["within_0.1"],
    }


def other_bodies(root: Path, topology: str, seed: int, count: int, cache_dir: Path) -> Path:
    """``count`` bodies of independently drawn people (seed ``seed + 1``), 2 of them test, written once."""
    ensure_bodies(root, count, 2, seed + 1, topology, cache_dir=cache_dir)
    return root / "correspondence"


def diversity(root: Path, topology: str, seed: int, cache_dir: Path) -> dict:
    """How different the people are (module docstring, step 1), in centimetres, in their rest poses."""
    people = json.loads((root / "people.json").read_text())["phenotypes"]
    rest = BodyGenerator(topology, "rest", seed, cache_dir)

    def summary(phenotypes: list[dict]) -> dict:
        shapes = [rest.body(0, "train", phenotype=phenotype).vertices for phenotype in phenotypes]
        heights = [100 * float(np.ptp(vertices[:, 1])) for vertices in shapes]
        centred = [vertices - vertices.mean(axis=0) for vertices in shapes]
        distances = [
            100 * float(np.linalg.norm(a - b, axis=1).mean()) for i, a in enumerate(centred) for b in centred[i + 1 :]
        ]
        return {
            "heights_cm": [round(h, 1) for h in heights],
            "height_range_cm": round(max(heights) - min(heights), 1),
            "pair_distance_cm": {
                "min": round(min(distances), 2),
                "median": round(float(np.median(distances)), 2),
                "max": round(max(distances), 2),
            },
        }

    rng = np.random.default_rng(np.random.SeedSequence([seed, 99]))
    independent = [draw_phenotype(rng) for _ in range(N_PEOPLE)]
    return {
        "people": summary([people[str(person)] for person in range(N_PEOPLE)]),
        "independent draws": summary(independent),
    }


def recipe_config(
    data_root: Path, recipe: str, epochs: int | None, threads: int | None, n_vertices: int, cache_dir: Path
) -> dict:
    config = base_config()
    config["cache_dir"] = str(cache_dir)
    config["data"].update({"root": str(data_root), "n_vertices": n_vertices})
    config["train"].update({"threads": threads, "keep_epochs": True})
    if epochs is not None:
        config["train"]["epochs"] = epochs
    config["eval"].update({"renders": 0})
    return apply_overrides(config, BOOK["recipes"][recipe])


def architecture_overrides(recipe: str) -> list[str]:
    """The recipe's overrides that shape the model and its inputs (``data.*``, ``model.*``): a backbone
    pretrained for the recipe must have them too."""
    return [override for override in BOOK["recipes"][recipe] if override.split(".")[0] in ("data", "model")]


def pretrain(
    data_root: Path,
    run_dir: Path,
    recipe: str,
    epochs: int | None,
    threads: int | None,
    n_vertices: int,
    cache_dir: Path,
) -> Path:
    """The weights pretrained on other people for ``recipe``'s model and inputs, from scratch (trained once,
    then reused)."""
    if not (run_dir / "best.pt").is_file():
        config = recipe_config(data_root, "shipped", epochs, threads, n_vertices, cache_dir)
        config = apply_overrides(config, architecture_overrides(recipe))
        count = len(list(data_root.glob("training/registrations/tr_reg_*.ply")))
        config["data"].update({"train_indices": f"0:{count - 2}", "test_indices": f"{count - 2}:{count}"})
        config["train"].update({"keep_epochs": False, "init_from": None})
        train(config, run_dir, progress=False, overwrite=True)
    return run_dir


def pretrained_run(args, recipe: str) -> Path:
    """The run pretrained for ``recipe`` on ``--pretrain-count`` bodies of other people (generated and trained
    once; one per model and input set: ``RUNS/pretrain``, or ``RUNS/pretrain-RECIPE`` for a recipe that
    changes them)."""
    topology = args.pretrain_topology or args.topology
    others = other_bodies(args.others, topology, args.seed, args.pretrain_count, args.cache_dir)
    name = f"pretrain-{recipe}" if architecture_overrides(recipe) else "pretrain"
    return pretrain(
        others, args.runs / name, recipe, args.pretrain_epochs, args.threads, N_VERTICES[topology], args.cache_dir
    )


def epoch_scores(run_dir: Path, dataset, rings: int, radius: float, every: int) -> list[dict]:
    """Test scores of every ``every``-th kept epoch and the last (unrefined and refined as the run chose: its
    ``rings``, then its global ``radius``), kept in ``RUN/epochs/test_scores.json`` so that a later
    invocation only adds recipes."""
    stored = run_dir / "epochs" / "test_scores.json"
    if stored.is_file():
        return json.loads(stored.read_text())
    paths = sorted((run_dir / "epochs").glob("epoch_*.pt"))
    rows = []
    for path in paths:
        epoch = int(path.stem.split("_")[1])
        if epoch % every and path != paths[-1]:
            continue
        result = evaluate(
            path, dataset=dataset, split="test", progress=False, refine_rings=[rings], refine_spectral=[radius]
        )
        refined, unrefined = result["summary"], result.get("unrefined_summary", result["summary"])
        rows.append(
            {
                "epoch": epoch,
                "test_exact_unrefined": unrefined["accuracy"],
                "test_exact_refined": refined["accuracy"],
                "test_within_1pct_refined": refined["within_0.01"],
                "test_beyond_10pct_unrefined": 1.0 - unrefined["within_0.1"],
                "test_beyond_10pct_refined": 1.0 - refined["within_0.1"],
            }
        )
    write_json(stored, rows)
    return rows


def per_epoch_rows(history: list[dict], scores: list[dict]) -> list[dict]:
    """One row per trained epoch: its training and validation loss and accuracy (the gap between them),
    with the test scores where the epoch was scored."""
    scored = {row["epoch"]: row for row in scores}
    keys = ("train_loss", "train_accuracy", "val_loss", "val_accuracy")
    return [
        {"epoch": entry["epoch"], **{key: entry.get(key) for key in keys}, **scored.get(entry["epoch"], {})}
        for entry in history
    ]


def run_recipe(name: str, data_root: Path, runs: Path, pretrained: Path | None, args) -> dict:
    run_dir = runs / name
    config = recipe_config(data_root, name, args.epochs, args.threads, N_VERTICES[args.topology], args.cache_dir)
    config = apply_overrides(config, args.overrides)
    started = time.perf_counter()
    if not (run_dir / "metrics.json").is_file():
        train(config, run_dir, progress=False, overwrite=True, init_from=pretrained)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    history = load_checkpoint(run_dir / "last.pt")["state"]["history"]
    rings = int(metrics.get("refine_rings", 0))
    dataset = build_dataset(parse_config(config), progress=False)
    radius = float(metrics.get("refine_spectral") or 0)
    per_epoch = per_epoch_rows(history, epoch_scores(run_dir, dataset, rings, radius, args.score_every))
    unrefined = metrics.get("unrefined_summary", metrics["summary"])
    stored = run_dir / "unseen_scores.json"
    if not stored.is_file():
        write_json(stored, unseen_scores(run_dir, config, args.unseen_root, rings, radius))
    return {
        "recipe": name,
        "overrides": BOOK["recipes"][name],
        "pretrained": pretrained is not None,
        "best_epoch": metrics["best_epoch"],
        "val_accuracy_best": max(entry.get("val_accuracy", 0.0) for entry in history),
        "refine_rings": rings,
        "unseen_validation": json.loads(stored.read_text()),
        "test": {
            "exact_unrefined": unrefined["accuracy"],
            "exact_refined": metrics["summary"]["accuracy"],
            "within_1pct_refined": metrics["summary"]["within_0.01"],
            "beyond_10pct_unrefined": 1.0 - unrefined["within_0.1"],
            "beyond_10pct_refined": 1.0 - metrics["summary"]["within_0.1"],
        },
        "error_curve": metrics.get("error_curve"),
        "per_epoch": per_epoch,
        "seconds": time.perf_counter() - started,
    }


def markdown(result: dict) -> list[str]:
    people, independent = result["diversity"]["people"], result["diversity"]["independent draws"]
    lines = [
        "# few_people: correspondence on 8 people, tested on 2 unseen ones (FAUST's structure, generated)",
        "",
        f"{result['topology']} bodies ({result['n_vertices']} vertices), 10 people x 10 poses "
        f"(`zernet bodies --people 10`, seed {result['seed']}); 72 train / 8 validation (people 0-7) / 20 test "
        f"(people 8-9); `configs/faust_single_scale.yaml`, {result['epochs']} epochs.",
        "",
        "How different the people are (rest poses): heights "
        f"{min(people['heights_cm']):.0f}-{max(people['heights_cm']):.0f} cm (independent draws "
        f"{min(independent['heights_cm']):.0f}-{max(independent['heights_cm']):.0f} cm); mean distance between two "
        f"people at the same template vertex: median {people['pair_distance_cm']['median']} cm, least "
        f"{people['pair_distance_cm']['min']} cm (independent draws: {independent['pair_distance_cm']['median']} / "
        f"{independent['pair_distance_cm']['min']} cm).",
        "",
        f"Recipes are compared on validation: the best epoch's exact accuracy on the validation bodies (the "
        f"training people in other poses) and on {N_UNSEEN} more people of another draw (`zernet bodies "
        f"--people {N_UNSEEN}`, seed {result['seed'] + 2}: unrefined / refined, and beyond 10 % of the diameter "
        "unrefined), which sees what the validation bodies cannot: how the recipe carries to new people. The "
        "test people are only reported.",
        "",
    ]
    header = [
        "recipe",
        "best val exact",
        "unseen-people val",
        "test exact (unrefined)",
        "test exact (refined)",
        "within 1 %",
        "beyond 10 % (unrefined / refined)",
        "rings",
    ]
    rows = []
    for entry in result["recipes"]:
        test, unseen = entry["test"], entry["unseen_validation"]
        rows.append(
            [
                entry["recipe"],
                f"{entry['val_accuracy_best']:.3f} (epoch {entry['best_epoch']})",
                f"{100 * unseen['exact_unrefined']:.1f} / {100 * unseen['exact_refined']:.1f} %, "
                f"{100 * unseen['beyond_10pct_unrefined']:.2f} %",
                f"{100 * test['exact_unrefined']:.1f} %",
                f"{100 * test['exact_refined']:.1f} %",
                f"{100 * test['within_1pct_refined']:.1f} %",
                f"{100 * test['beyond_10pct_unrefined']:.2f} / {100 * test['beyond_10pct_refined']:.2f} %",
                entry["refine_rings"],
            ]
        )
    lines += markdown_table(header, rows)
    header = [
        "epoch",
        "train loss / val loss",
        "train acc",
        "val exact",
        "gap",
        "test exact unrefined",
        "refined",
        "beyond 10 % unrefined",
    ]
    for entry in result["recipes"]:
        rows = []
        for row in entry["per_epoch"]:
            train_acc, val_acc = row.get("train_accuracy") or 0.0, row.get("val_accuracy") or 0.0
            scored = "test_exact_refined" in row
            rows.append(
                [
                    row["epoch"],
                    f"{row.get('train_loss') or 0:.3f} / {row.get('val_loss') or 0:.3f}",
                    f"{train_acc:.3f}",
                    f"{val_acc:.3f}",
                    f"{train_acc - val_acc:+.3f}",
                    f"{100 * row['test_exact_unrefined']:.1f} %" if scored else "-",
                    f"{100 * row['test_exact_refined']:.1f} %" if scored else "-",
                    f"{100 * row['test_beyond_10pct_unrefined']:.2f} %" if scored else "-",
                ]
            )
        lines += ["", f"Per epoch, {entry['recipe']}:", "", *markdown_table(header, rows)]
    return lines


def plot(result: dict, path: Path) -> None:
    figure, (curves, epochs) = plt.subplots(1, 2, figsize=(11, 4))
    for entry in result["recipes"]:
        if entry["error_curve"]:
            curve = entry["error_curve"]
            curves.plot(curve["radii"], curve["fractions"], label=entry["recipe"])
        rows = entry["per_epoch"]
        tested = [r for r in rows if "test_exact_refined" in r]
        line = epochs.plot(
            [r["epoch"] for r in tested], [r["test_exact_refined"] for r in tested], "o-", label=entry["recipe"]
        )
        epochs.plot(
            [r["epoch"] for r in rows], [r.get("val_accuracy") or np.nan for r in rows], "--", color=line[0].get_color()
        )
    curves.set(xlabel="geodesic error / diameter", ylabel="fraction of test vertices", xlim=(0, 0.1), ylim=(0, 1))
    curves.set_title("error curve, test people (selected epoch, refined)")
    epochs.set(xlabel="epoch", ylabel="exact accuracy", ylim=(0, 1))
    epochs.set_title("test people (solid, refined) and validation (dashed)")
    for axes in (curves, epochs):
        axes.grid(alpha=0.3)
        axes.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def main() -> None:
    parser = arguments(__doc__)
    parser.add_argument("--topology", default="faust", choices=sorted(N_VERTICES))
    add_data(parser, REPO / "data" / "people", "the people bodies' folder (written once)")
    parser.add_argument(
        "--unseen",
        type=Path,
        default=REPO / "data" / "people-unseen",
        help="the unseen people the recipes are compared on (written once)",
    )
    parser.add_argument("--others", type=Path, default=REPO / "data" / "others", help="the pretraining bodies")
    parser.add_argument("--runs", type=Path, default=REPO / "runs" / "few_people")
    parser.add_argument(
        "--recipes",
        nargs="+",
        default=["shipped", "pretrained"],
        choices=list(BOOK["recipes"]),
        help="recipes of configs/recipes/few_people.yaml",
    )
    parser.add_argument(
        "--epochs",
        type=int,
        default=None,
        help="epochs of the recipes that set none (a recipe's own train.epochs wins)",
    )
    parser.add_argument("--pretrain-count", type=int, default=100, help="bodies of other people to pretrain on")
    parser.add_argument("--pretrain-epochs", type=int, default=None)
    parser.add_argument(
        "--pretrain-topology",
        default=None,
        choices=sorted(N_VERTICES),
        help="topology of the pretraining bodies (default --topology): the patch operators are intrinsic at a "
        "fixed area, so convolutions learnt on coarser bodies apply to finer ones",
    )
    parser.add_argument(
        "--score-every", type=int, default=1, help="score every K-th epoch on the test people (and the last)"
    )
    parser.add_argument(
        "--set",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        dest="overrides",
        help="change every recipe's configuration after its own changes, as 'zernet train --set' does "
        "(e.g. train.lr=2e-3); give each variant its own --runs",
    )
    parser.add_argument("--seed", type=int, default=0)
    add_threads(parser)
    parser.add_argument("--cache-dir", type=Path, default=CACHE, help="generated bodies and patch operators")
    add_out(parser, EXPERIMENT_RESULTS / "few_people")
    args = parser.parse_args()

    data_root = people_bodies(args.data, args.topology, args.seed, args.cache_dir)
    args.unseen_root = unseen_people(args.unseen, args.topology, args.seed, args.cache_dir)
    pretrained_recipes = [name for name in args.recipes if name in BOOK["pretrained_on_other_people"]]
    result = {
        "topology": args.topology,
        "n_vertices": N_VERTICES[args.topology],
        "seed": args.seed,
        "epochs": args.epochs or base_config()["train"]["epochs"],
        "pretraining": None
        if not pretrained_recipes
        else {
            "topology": args.pretrain_topology or args.topology,
            "bodies": args.pretrain_count,
            "epochs": args.pretrain_epochs or base_config()["train"]["epochs"],
        },
        "diversity": diversity(args.data, args.topology, args.seed, args.cache_dir),
        "recipes": [],
    }
    for name in args.recipes:
        starts_from = next(
            (o.partition("=")[2] for o in BOOK["recipes"][name] if o.startswith("train.init_from=")), None
        )
        if starts_from in BOOK["renumbered"]:
            renumbered_checkpoint(REPO / BOOK["renumbered"][starts_from], REPO / starts_from)
    for name in args.recipes:
        print(f"recipe {name} ...", flush=True)
        pretrained = pretrained_run(args, name) if name in pretrained_recipes else None
        result["recipes"].append(run_recipe(name, data_root, args.runs, pretrained, args))
        write_result(result_file(args.out, ".json"), result)
    lines = markdown(result)
    write_markdown(result_file(args.out, ".md"), lines)
    plot(result, result_file(args.out, ".png"))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
