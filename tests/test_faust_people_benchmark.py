"""The real-people benchmark's split: whole people, never the test people; recipes are valid configurations."""

import pytest

from benchmarks.experiments import faust_people
from zernet.training import parse_config


class _Args:
    cache_dir = "/tmp/cache"
    threads = 1
    set = []


def test_each_recipe_splits_by_person_and_parses(tmp_path):
    base, recipes = faust_people.load_recipes()
    assert "shipped" in recipes and recipes["shipped"] == []
    for overrides in recipes.values():
        config = faust_people.recipe_config(base, overrides, tmp_path, (6, 7), _Args)
        data = config["data"]
        assert (data["train_indices"], data["val_indices"], data["test_indices"]) == ("0:60", "60:70", "70:80")
        parse_config(config)  # every recipe is a configuration the run accepts
    rotated = faust_people.recipe_config(base, [], tmp_path, (7, 6), _Args)["data"]
    assert (rotated["val_indices"], rotated["test_indices"]) == ("70:80", "60:70")


def test_a_folder_holding_the_test_people_is_refused(tmp_path):
    folder = tmp_path / "training" / "registrations"
    folder.mkdir(parents=True)
    (folder / "tr_reg_000.ply").write_text("")
    faust_people.check_data(tmp_path, allow_test_people=False)
    (folder / "tr_reg_085.ply").write_text("")
    with pytest.raises(SystemExit, match="test people"):
        faust_people.check_data(tmp_path, allow_test_people=False)
    faust_people.check_data(tmp_path, allow_test_people=True)
