"""Distributed data-parallel training: shape sharding, and 2 gloo ranks under torchrun against one process.

The equivalence test launches the real command (``torchrun --standalone --nproc_per_node 2 -m zernet.cli
train``) on three tiny synthetic training creatures (so the shards need padding), for one epoch and then
``--resume`` for a second, and replays the same optimiser steps in this process: at every step the loss is
the mean of the per-rank losses of the shapes the two ranks saw at that step (DDP averages the ranks'
gradients). Dropout is off, so the two runs share every random number.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from tiny_configs import ddp_config

from zernet.distributed import DistributedContext, shard_indices
from zernet.inference import build_model_from_spec, load_checkpoint, model_spec
from zernet.inference.batch import Batch
from zernet.training import build_dataset, epoch_order, parse_config, step_groups
from zernet.training.losses import compute_loss
from zernet.training.schedule import seed_everything

pytestmark = pytest.mark.timeout(300)

REPO = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------------------------------- sharding
@pytest.mark.parametrize("n, world", [(3, 2), (7, 3), (8, 4), (2, 4), (1, 2)])
def test_pad_gives_equal_shares_covering_every_shape(n, world):
    order = list(torch.randperm(n, generator=torch.Generator().manual_seed(n)).tolist())
    shares = [shard_indices(order, r, world) for r in range(world)]
    assert len({len(s) for s in shares}) == 1, shares
    assert len(shares[0]) == -(-n // world)
    assert set().union(*map(set, shares)) == set(order)
    # rank r takes positions r, r + W, ... of the (cyclically padded) order
    assert shares[0][0] == order[0] and shares[-1][0] == order[(world - 1) % n]


def test_drop_leaves_out_the_remainder_and_refuses_too_few_shapes():
    order = [5, 1, 4, 0, 3, 2, 6]
    shares = [shard_indices(order, r, 3, remainder="drop") for r in range(3)]
    assert shares == [[5, 0], [1, 3], [4, 2]]
    with pytest.raises(ValueError, match="cannot be shared among 4 ranks"):
        shard_indices([1, 2], 0, 4, remainder="drop")
    with pytest.raises(ValueError, match="rank 2"):
        shard_indices(order, 2, 2)


def test_single_process_context_is_the_identity():
    ctx = DistributedContext()
    model = torch.nn.Linear(2, 2)
    assert ctx.wrap(model) is model and ctx.unwrap(model) is model
    assert ctx.shard([3, 1, 2]) == [3, 1, 2]
    assert ctx.sum_over_ranks(1, 2.5) == (1.0, 2.5)
    assert ctx.mean_over_shards(lambda part: {"m": float(sum(part)) / len(part)}, [1, 2, 3]) == {"m": 2.0}
    state = torch.get_rng_state()
    ctx.seed_epoch(0, 1)  # no reseeding on one process: single-process runs keep their checkpointed RNG
    assert torch.equal(state, torch.get_rng_state())
    with ctx.main_first():
        pass


# ------------------------------------------------------------------------------- DDP == one process
def _reference_weights(config: dict, world_size: int) -> dict:
    """Replay the distributed run's steps in one process: mean of the ranks' losses per step."""
    config = parse_config(config)
    tcfg = config.train
    dataset = build_dataset(config, progress=False, workers=0)
    train_idx = list(dataset.splits["train"])
    spec = model_spec(config.model, dataset.in_channels, dataset.num_classes, dataset.patch_configs)
    seed_everything(tcfg.seed)
    model = build_model_from_spec(spec)
    optimizer = torch.optim.Adam(model.parameters(), lr=tcfg.lr, weight_decay=tcfg.weight_decay)
    model.train()
    for epoch in range(1, tcfg.epochs + 1):
        order = [train_idx[i] for i in epoch_order(tcfg.seed, epoch, len(train_idx))]
        per_rank = [step_groups(shard_indices(order, r, world_size), tcfg.shapes_per_step) for r in range(world_size)]
        for step_groups_of_ranks in zip(*per_rank):
            optimizer.zero_grad(set_to_none=True)
            losses = []
            for group in step_groups_of_ranks:
                batch = Batch([dataset[i] for i in group], torch.device("cpu"), None)
                losses.append(compute_loss("cross_entropy", model(batch.features, batch.geometry), batch.target))
            torch.stack(losses).mean().backward()
            optimizer.step()
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def _free_env() -> dict:
    env = dict(os.environ)
    for name in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(name, None)
    env["OMP_NUM_THREADS"] = "1"
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def test_two_gloo_ranks_match_one_process_with_averaged_losses(tmp_path):
    config = ddp_config(tmp_path / "cache")
    # Fill the cache here, so the ranks only read it (and the reference sees identical operators).
    reference = _reference_weights(config, world_size=2)

    # The distributed run is cut after epoch 1 and resumed (every rank loads last.pt) for epoch 2.
    run_dir = tmp_path / "run"
    for epochs, extra in ((1, []), (2, ["--resume"])):
        config_path = tmp_path / f"ddp{epochs}.yaml"
        config_path.write_text(yaml.safe_dump({**config, "train": {**config["train"], "epochs": epochs}}))
        command = [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--standalone",
            "--nproc_per_node",
            "2",
            "-m",
            "zernet.cli",
            "train",
            str(config_path),
            "--run-dir",
            str(run_dir),
            "--no-progress",
            "--workers",
            "0",
            *extra,
        ]
        result = subprocess.run(command, cwd=tmp_path, env=_free_env(), capture_output=True, text=True, timeout=240)
        assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]

    # Rank 0 alone wrote the run folder and printed the report.
    assert result.stdout.count("test metrics (") == 1, result.stdout
    log = (run_dir / "train.log").read_text()
    assert log.count("2 ranks, gloo") == 2 and "resumed after epoch 1" in log and log.count("epoch 2/2") == 1

    checkpoint = load_checkpoint(run_dir / "last.pt")
    assert checkpoint["state"]["epoch"] == 2
    assert set(checkpoint["model"]) == set(reference)  # saved without DDP's "module." prefix
    for key, value in reference.items():
        torch.testing.assert_close(checkpoint["model"][key], value, rtol=1e-5, atol=1e-6, msg=key)
    # ...and the weights really moved away from the initialisation during those 4 steps.
    seed_everything(config["train"]["seed"])
    initial = build_model_from_spec(checkpoint["model_spec"]).state_dict()
    assert any(not torch.allclose(initial[k], reference[k]) for k in reference)
