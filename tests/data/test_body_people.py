"""Generated bodies with FAUST's structure (``people=``): a few people in several poses each, the test
bodies whole people never seen in training, the people's phenotypes spread over the model's ranges."""

import importlib.util
import json

import numpy as np
import pytest

from zernet.cli import main
from zernet.data import DatasetError
from zernet.data.bodies import generate_bodies
from zernet.data.bodies.pose import PHENOTYPE_RANGES

COARSE = "coarse-369"


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    if importlib.util.find_spec("anny") is None:
        pytest.skip("needs the bodies extra (anny)")
    return tmp_path_factory.mktemp("people-cache")


def test_consecutive_bodies_are_one_person_in_their_own_poses(cache):
    bodies = generate_bodies(count=6, seed=0, topology=COARSE, n_test=2, cache_dir=cache, people=3)
    assert [body.person for body in bodies] == [0, 0, 1, 1, 2, 2]
    assert [body.split for body in bodies] == ["train"] * 4 + ["test"] * 2  # the test split is person 2 alone
    for first, second in zip(bodies[::2], bodies[1::2]):
        assert first.phenotype == second.phenotype and first.pose != second.pose
        assert np.abs(first.vertices - second.vertices).max() > 0.01
    assert len({tuple(body.phenotype.values()) for body in bodies}) == 3
    # The poses are each body's own draw: the same as without people.
    independent = generate_bodies(count=6, seed=0, topology=COARSE, n_test=2, cache_dir=cache)
    assert [body.pose for body in bodies] == [body.pose for body in independent]
    assert all(body.person is None for body in independent)


def test_people_cover_every_phenotype_range_once_per_stratum(cache):
    bodies = generate_bodies(count=10, seed=3, topology=COARSE, n_test=1, cache_dir=cache, people=10)
    for key, (low, high) in PHENOTYPE_RANGES.items():
        values = np.array([body.phenotype[key] for body in bodies])
        strata = np.floor((values - low) / (high - low) * 10).astype(int)
        assert sorted(strata) == list(range(10)), key  # one person per tenth of the range: no bunching


def test_people_that_do_not_split_evenly_are_refused(cache):
    with pytest.raises(DatasetError, match="do not split into 4 people"):
        generate_bodies(count=6, topology=COARSE, n_test=2, cache_dir=cache, people=4)
    with pytest.raises(DatasetError, match="test bodies must be whole people"):
        generate_bodies(count=6, topology=COARSE, n_test=1, cache_dir=cache, people=3)


def test_the_command_writes_whose_each_body_is(cache, tmp_path):
    out = tmp_path / "people"
    argv = ["bodies", str(out), "--count", "4", "--n-test", "2", "--people", "2", "--topology", COARSE]
    assert main([*argv, "--cache-dir", str(cache)]) == 0
    people = json.loads((out / "people.json").read_text())
    assert people["people"] == 2
    assert [entry["person"] for entry in people["bodies"].values()] == [0, 0, 1, 1]
    assert set(people["phenotypes"]) == {"0", "1"}
    assert "2 people in 2 poses each" in (out / "README.txt").read_text()
    assert len(list((out / "correspondence" / "training" / "registrations").glob("tr_reg_*.ply"))) == 4
