"""The release recipes (configs/recipes/release.yaml) make the models shipped in the package."""

import importlib.util
import json
import shlex

from benchmarks.experiments.release import PRETRAINED, release_models, run_config, trainer_commands
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
    assert order.index("bodies-xyz-hks") < order.index("bodies-template-part")  # the first template model's backbone
    assert order.index("bodies-template-part") < order.index("bodies-match-template")  # fine-tuned from it
    assert order.index("bodies-template-part") < order.index("bodies-faust-template")  # reads the template part


def test_trainer_commands_name_modules_and_files_that_exist():
    recipes = {name: recipe for name, recipe in release_models().items() if "command" in recipe}
    assert set(recipes) == {"bodies-template-part", "bodies-match-template", "bodies-match-descriptors"}
    commands = [command for recipe in recipes.values() for command in trainer_commands(recipe)]
    assert len(commands) == 4
    for command in commands:
        words = shlex.split(command)
        assert words[:2] == ["python", "-m"] and importlib.util.find_spec(words[2]) is not None, command
        for word in words[3:]:
            if word.startswith("configs/"):
                assert (REPO / word).is_file(), command


def _option(words: list[str], name: str) -> str:
    return words[words.index(name) + 1]


def test_a_model_made_in_stages_starts_each_from_the_last_and_ships_the_last():
    recipe = release_models()["bodies-match-template"]
    stages = [shlex.split(command) for command in trainer_commands(recipe)]
    assert _option(stages[0], "--init-from") == "zernet/pretrained/bodies-template-part.pt"
    for before, after in zip(stages, stages[1:]):
        assert _option(after, "--init-from") == _option(before, "--out")
    assert _option(stages[-1], "--out") == recipe["model"]
