"""Residency of the prepared operators (``data.residency``): every level trains the same numbers, ``auto``
decides by size and free memory, and the chosen level is reported."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tiny_configs import tiny_config

import zernet.data.preprocess as preprocess
from zernet.operators import PatchOperator
from zernet.training import build_dataset, parse_config, train
from zernet.training.residency import MEMORY_FRACTION, ShapeStore, choose_residency

LEVELS = ("stream", "host", "device", "auto")


@pytest.fixture
def streamed(monkeypatch):
    """Data sets read back from the cache on every access (as FAUST-size ones are), however small."""
    monkeypatch.setattr(preprocess, "IN_MEMORY_VERTEX_LIMIT", 0)


@pytest.mark.parametrize("shapes_per_step", [1, 2])
def test_every_level_gives_the_same_validation_curve(tmp_path, cache_dir, streamed, shapes_per_step):
    histories = {}
    for level in LEVELS:
        config = tiny_config(cache_dir, epochs=2, shapes_per_step=shapes_per_step)
        config["data"]["residency"] = level
        config["eval"]["renders"] = 0
        train(config, tmp_path / level, progress=False, workers=0)
        log = (tmp_path / level / "train.log").read_text()
        chosen = "host" if level == "auto" else level  # tiny shapes fit in memory
        assert f"data residency: {chosen} (" in log
        histories[level] = torch.load(tmp_path / level / "last.pt", weights_only=True)["state"]["history"]
    reference = histories["stream"]
    for level in LEVELS[1:]:
        for got, expected in zip(histories[level], reference):
            for key in ("train_loss", "val_loss", "val_accuracy"):
                np.testing.assert_allclose(got[key], expected[key], rtol=1e-6, err_msg=f"{level} {key}")


def test_held_shapes_are_prepared_once_and_read_without_the_cache(cache_dir, streamed, monkeypatch):
    config = parse_config(tiny_config(cache_dir))
    dataset = build_dataset(config, progress=False, workers=0)
    assert not dataset.in_memory
    indices = dataset.splits["train"] + dataset.splits["val"]
    store = ShapeStore(dataset, indices, "device", torch.device("cpu"), None, [(0, 2, 1, 3, 4, 5, 6, 7, 8, 9)])
    assert store.level == "device" and store.held_bytes > 0

    def no_reads(*args, **kwargs):
        raise AssertionError("a held shape was read from the cache again")

    monkeypatch.setattr(PatchOperator, "load", no_reads)
    monkeypatch.setattr(preprocess, "read_shape", no_reads)
    first = store[indices[0]]
    assert first is store[indices[0]]  # the same record, its tensors prepared
    op = first.geometry.operators[0]
    assert op.prepared_nbytes == op.pairs.nbytes  # on the CPU the pairs alone: the backward reads them as stored
    assert f"holding {len(store._held)} shapes" in store.describe()
    # A step of two held shapes reads their own pairs: the batch joins no host arrays.
    batch = PatchOperator.concatenate([store[i].geometry.operators[0] for i in indices[:2]])
    x = torch.randn(batch.n_vertices, 3)
    expected = torch.cat([store[i].geometry.operators[0].apply(x[: op.n_vertices]) for i in indices[:1]])
    assert torch.equal(batch.apply(x)[: op.n_vertices], expected)
    assert "frames" not in batch.__dict__ and batch._padded is None


def test_auto_chooses_by_size_and_free_memory():
    gb = 10**9
    cpu, cuda = torch.device("cpu"), torch.device("cuda", 0)
    assert choose_residency("auto", gb, 10, cpu, {"host": 100 * gb})[0] == "host"
    assert choose_residency("auto", gb, 10, cpu, {"host": 15 * gb})[0] == "stream"
    assert choose_residency("auto", gb, 10, cuda, {"device": 30 * gb, "host": 100 * gb})[0] == "device"
    assert choose_residency("auto", gb, 10, cuda, {"device": 10 * gb, "host": 100 * gb})[0] == "host"
    assert choose_residency("auto", gb, 10, cuda, {"device": 10 * gb, "host": 10 * gb})[0] == "stream"
    level, reason = choose_residency("auto", gb, 10, cuda, {"device": 30 * gb})
    assert "10 shapes" in reason and f"{MEMORY_FRACTION:.0%}" in reason
    assert choose_residency("stream", gb, 10, cpu) == (
        "stream",
        "data.residency stream; 10 shapes x 1000 MB = 10.00 GB of prepared operators",
    )
    with pytest.raises(ValueError, match="residency"):
        choose_residency("gpu", gb, 10, cpu)


def test_auto_holds_a_faust_size_training_set_on_a_24_gb_machine():
    # Measured (benchmarks/speed/bench_operator.py --formats, a 6,890-vertex body, the shipped FAUST patch
    # settings): 24.1 MB held per shape as float16 vertex pairs, 162.3 MB as format 4's float32 CSR matrix and
    # transpose. FAUST's 72 training and 8 validation scans, with 12 GB available of 24 GB:
    cpu, available = torch.device("cpu"), {"host": 12 * 10**9}
    assert choose_residency("auto", int(24.1e6), 80, cpu, available)[0] == "host"  # 1.9 GB
    assert choose_residency("auto", int(162.3e6), 80, cpu, available)[0] == "stream"  # 13 GB: what format 4 did


def test_residency_is_checked_and_may_change_on_resume(tmp_path, cache_dir):
    from zernet.training import ConfigError
    from zernet.training.loop import RESUME_CHANGEABLE

    config = tiny_config(cache_dir)
    config["data"]["residency"] = "everywhere"
    with pytest.raises(ConfigError, match="data.residency"):
        parse_config(config)
    assert ("data", "residency") in RESUME_CHANGEABLE


def test_a_step_copy_shares_the_host_arrays_and_leaves_the_held_geometry_alone(cache_dir):
    config = parse_config(tiny_config(cache_dir))
    dataset = build_dataset(config, progress=False, workers=0)
    record = dataset[dataset.splits["train"][0]]
    held = record.geometry.with_directional(1).to("cpu", [tuple(range(10))[::-1]])
    before = dict(held.operators[0]._devices)
    copy = held.copy_to("cpu")
    assert copy.operators[0] is not held.operators[0] and copy.directional[0].operator is copy.operators[0]
    assert copy.operators[0].pairs is held.operators[0].pairs  # host arrays shared, not copied
    assert held.operators[0]._devices == before
    x = torch.randn(held.n_vertices, 4)
    assert torch.equal(copy.operators[0].apply(x), held.operators[0].apply(x))
