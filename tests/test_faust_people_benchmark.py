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


def test_rescoring_keeps_the_training_figures_and_is_read_back(tmp_path, monkeypatch):
    # A trained run scored again with the refinement the config gives now: the new scores replace the run's,
    # its training time and history stay, and a later invocation reads them without evaluating again.
    run_dir = tmp_path / "shipped-held67"
    run_dir.mkdir()
    scores = {"accuracy": 0.6, "within_0.01": 0.8, "within_0.1": 0.97}
    trained = {"summary": scores, "unrefined_summary": scores, "refine_rings": 3, "train_seconds": 1440.0}
    faust_people.write_json(run_dir / "metrics.json", trained)
    history = [{"epoch": 1, "train_loss": 3.4, "val_loss": 1.9, "train_accuracy": 0.3, "val_accuracy": 0.46}]
    monkeypatch.setattr(faust_people, "load_checkpoint", lambda path: {"state": {"history": history}})
    refined = {"accuracy": 0.99, "within_0.01": 0.999, "within_0.1": 0.9991}
    calls = []

    def evaluate(run, progress, refine_rings, refine_passes, refine_spectral):
        calls.append((refine_rings, refine_passes, refine_spectral))
        return {"summary": refined, "unrefined_summary": scores, "refine_rings": 3, "refine_passes": 16}

    monkeypatch.setattr(faust_people, "evaluate", evaluate)
    config = {"eval": {"refine_rings": [0, 3], "refine_passes": [1, 4, 8, 16], "refine_spectral": [0.0]}}
    entry = faust_people.run_recipe("shipped", config, run_dir, rescore=True)
    assert calls == [([0, 3], [1, 4, 8, 16], [0.0])]
    assert entry["scored_person"]["exact_refined"] == 0.99 and entry["scored_person"]["exact_unrefined"] == 0.6
    assert entry["refine_passes"] == 16 and entry["train_seconds"] == 1440.0
    assert entry["per_epoch"][0]["gap"] == pytest.approx(0.3 - 0.46)
    again = faust_people.run_recipe("shipped", config, run_dir)
    assert len(calls) == 1 and again["scored_person"] == entry["scored_person"]
