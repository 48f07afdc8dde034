"""Make every model shipped in the package again, from nothing: the one way weights get into ``zernet/``.

What each model is and how it is trained is data, ``configs/recipes/release.yaml``; this script generates the
bodies a model needs, trains it and ships it: a backbone or a whole correspondence model goes through
:func:`zernet.training.init_from.export_backbone`, a model of a trainer of its own is copied as that trainer
wrote it. Beside every shipped ``zernet/pretrained/NAME.pt`` it writes ``NAME.json``: what it is, the configuration, the command,
the commit and the training history. A model whose run folder already holds a finished run (or whose
trainer's model file is there) is shipped without training it again, so an interrupted release goes on with
the models it had not finished.

    .venv/bin/python -m benchmarks.experiments.release --list            # the models, in order
    .venv/bin/python -m benchmarks.experiments.release                   # all of them (about seven hours)
    .venv/bin/python -m benchmarks.experiments.release bodies bodies-xyz-hks

The models are made in the file's order; a later one may start from an earlier one (the template model from
``bodies-xyz-hks``, ``bodies-faust-template`` reads the template model), so a partial release keeps the order.
"""

from __future__ import annotations

import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

from benchmarks.harness import RECIPES, REPO, arguments, commit, ensure_bodies
from zernet.inference import load_checkpoint
from zernet.inference.model_file import read_model_file
from zernet.io_utils import plain, write_json
from zernet.training import load_config, train
from zernet.training.config import apply_overrides
from zernet.training.init_from import export_backbone

RELEASE = RECIPES / "release.yaml"
PRETRAINED = REPO / "zernet" / "pretrained"


def release_models() -> dict[str, dict]:
    """Name -> recipe of every shipped model, in the order they are made."""
    return yaml.safe_load(RELEASE.read_text())["models"]


def trainer_commands(recipe: dict) -> list[str]:
    """The commands of a model made by a trainer of its own, in order (``command``: one, or a list)."""
    command = recipe["command"]
    return [command] if isinstance(command, str) else list(command)


def run_config(recipe: dict) -> dict:
    """The ``zernet train`` configuration of a model trained by zernet: its base with its overrides, reading
    the correspondence folder of its generated bodies."""
    root = Path(recipe["bodies"]["folder"]) / "correspondence"
    return apply_overrides(load_config(REPO / recipe["base"]), [f"data.root={root}", *recipe["set"]])


def train_and_ship(name: str, recipe: dict) -> None:
    """Generate the bodies, train (unless the run is finished), export the weights and their provenance."""
    bodies = recipe["bodies"]
    ensure_bodies(REPO / bodies["folder"], bodies["count"], bodies["n_test"], bodies["seed"], bodies["topology"])
    run_dir = REPO / recipe["run"]
    if not (run_dir / "metrics.json").is_file():
        train(run_config(recipe), run_dir, progress=True, overwrite=True)
    target = PRETRAINED / f"{name}.pt"
    written = export_backbone(run_dir, target, with_output=recipe["ship"] == "whole")
    state = load_checkpoint(run_dir / "last.pt")["state"]
    history = state["history"]
    provenance = {
        "what": recipe["what"],
        "trained_on": recipe["trained_on"],
        "config": yaml.safe_load((run_dir / "config.yaml").read_text()),
        "command": f"python -m benchmarks.experiments.release {name}",
        "commit": commit(),
        "epochs": len(history),
        "val_accuracy": [entry.get("val_accuracy") for entry in history],
        "best_epoch": state.get("best_epoch"),
        **written,
    }
    write_json(target.with_suffix(".json"), provenance)
    print(f"wrote {target} ({written['bytes'] / 1e6:.1f} MB) and its provenance", flush=True)


def run_trainer_and_ship(name: str, recipe: dict) -> None:
    """Run the model's own trainer (unless its model file is there), copy the file into the package and
    write the provenance stored in it beside it."""
    model = REPO / recipe["model"]
    if not model.is_file():
        for line in trainer_commands(recipe):  # a fine-tune in stages: each starts from the last one's file
            command = shlex.split(line)
            subprocess.run([sys.executable, *command[1:]] if command[0] == "python" else command, cwd=REPO, check=True)
    target = PRETRAINED / f"{name}.pt"
    shutil.copyfile(model, target)
    stored = read_model_file(target)
    provenance = {"model_file": target.name, "release": f"python -m benchmarks.experiments.release {name}"}
    write_json(target.with_suffix(".json"), plain({**provenance, **(stored.get("provenance") or {})}))
    print(f"wrote {target} and its provenance", flush=True)


def main(argv: list[str] | None = None) -> int:
    models = release_models()
    parser = arguments(__doc__)
    parser.add_argument("names", nargs="*", metavar="NAME", help=f"models to make (default all: {', '.join(models)})")
    parser.add_argument("--list", action="store_true", help="list the models and how each is trained, then stop")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.names) - set(models))
    if unknown:
        parser.error(f"unknown model {', '.join(unknown)}; the models are {', '.join(models)}")
    if args.list:
        for name, recipe in models.items():
            how = "trained by " + " then ".join(trainer_commands(recipe)) if "command" in recipe else "zernet train"
            print(f"{name:26} {how}")
        return 0
    for name, recipe in models.items():
        if args.names and name not in args.names:
            continue
        print(f"model {name} ...", flush=True)
        if "command" in recipe:
            run_trainer_and_ship(name, recipe)
        else:
            train_and_ship(name, recipe)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
