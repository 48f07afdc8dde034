"""The release recipes (configs/recipes/release.yaml) make the models shipped in the package."""

import importlib.util
import json
import shlex

from benchmarks.experiments.release import PRETRAINED, release_models, run_config
from benchmarks.harness import REPO
from zernet.training.config import parse_config


def test_every_shipped_model_file_has_a_release_recipe():
    assert set(release_models()) == {path.stem for path in PRETRAINED.glob("*.pt")}


def test_zernet_trained_recipes_give_the_configuration_recorded_in_the_shipped_provenance():
    trained = {name: recipe for name, recipe in release_models().items() if "command" not in recipe}
    assert set(trained) == {"bodies", "bodies-xyz-hks", "bodies-faust-template"}
    for name, recipe in trained.items():
        recorded = json.loads((PRETRAINED / f"{name}.json").read_text())["config"]
        ours = parse_config(run_config(recipe)).to_dict()
        theirs = parse_config(recorded).to_dict()
        ours.pop("cache_dir"), theirs.pop("cache_dir")  # where operators are cached changes no weight
        assert ours == theirs, name


def test_a_model_is_made_after_the_models_it_starts_from():
    order = list(release_models())
    assert order.index("bodies-xyz-hks") < order.index("bodies-match-template")  # the template model's backbone
    assert order.index("bodies-match-template") < order.index("bodies-faust-template")  # reads the template part


def test_trainer_commands_name_modules_and_files_that_exist():
    commands = [recipe["command"] for recipe in release_models().values() if "command" in recipe]
    assert len(commands) == 2
    for command in commands:
        words = shlex.split(command)
        assert words[:2] == ["python", "-m"] and importlib.util.find_spec(words[2]) is not None, command
        for word in words[3:]:
            if word.startswith("configs/"):
                assert (REPO / word).is_file(), command
