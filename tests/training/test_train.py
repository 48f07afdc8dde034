"""Training loop: run folder contents, learning, safe checkpoints, exact resume, early stopping, config errors.

Everything runs on a handful of tiny synthetic creatures (200 vertices, small patches, a small model) so the
whole module takes well under a minute on two cores. The preprocessed shapes are cached once per session.
"""

from __future__ import annotations

import copy
import json
import shutil
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from meshes import majority_fraction
from tiny_configs import SPHERE_LEARNT_EPOCHS, sphere_config, tiny_config

import zernet.training.loop as loop
from zernet.data.synthetic import make_creature
from zernet.geometry import Surface
from zernet.inference import build_model_from_spec, load_checkpoint, predict
from zernet.inference.batch import Batch, model_basis_orders
from zernet.inference.predict import predict_record
from zernet.inference.targets import feature_stats, standardise, target_stats, unstandardise
from zernet.metrics import regression_scores
from zernet.training import (
    ConfigError,
    apply_overrides,
    build_dataset,
    epoch_learning_rate,
    epoch_order,
    evaluate,
    parse_config,
    resolve_config,
    step_groups,
    train,
)
from zernet.training.config import TrainSection
from zernet.training.losses import compute_loss


@pytest.fixture(scope="session")
def finished_run(tmp_path_factory, cache_dir):
    """One complete 3-epoch run with plots, shared by the tests that only read a run folder."""
    run_dir = tmp_path_factory.mktemp("run")
    config = tiny_config(cache_dir, epochs=3)
    config["eval"]["plots"] = True
    metrics = train(config, run_dir, progress=False, workers=0)
    return run_dir, metrics


def test_run_folder_holds_everything(finished_run):
    run_dir, metrics = finished_run
    for name in ("config.yaml", "metrics.json", "last.pt", "best.pt", "train.log"):
        assert (run_dir / name).is_file(), name
    written = json.loads((run_dir / "metrics.json").read_text())
    assert written["kind"] == "segmentation" and written["split"] == "test"
    # The scores are those of the best model's answers on the test creatures, the baseline that of their labels.
    dataset = build_dataset(load_checkpoint(run_dir / "best.pt")["config"], progress=False)
    test = [dataset[i] for i in dataset.splits["test"]]
    labels = np.concatenate([record.target for record in test])
    answers = np.concatenate([predict(run_dir, record.surface) for record in test])
    assert written["summary"]["accuracy"] == pytest.approx(np.mean(answers == labels))
    assert written["baseline"]["majority_class_accuracy"] == pytest.approx(majority_fraction(labels))
    assert written["epochs_trained"] == 3 and 1 <= written["best_epoch"] <= 3
    plots = sorted(p.name for p in (run_dir / "plots").glob("*.png"))
    assert "training_curves.png" in plots and any(p.startswith("test_") for p in plots)
    log = (run_dir / "train.log").read_text()
    assert "epoch 3/3" in log and "test metrics" in log


def test_checkpoints_load_with_weights_only(finished_run):
    run_dir, _ = finished_run
    for name in ("last.pt", "best.pt"):
        checkpoint = torch.load(run_dir / name, map_location="cpu", weights_only=True)
        assert checkpoint["state"]["epoch"] >= 1
        assert isinstance(checkpoint["rng"]["torch"], torch.Tensor)
        assert set(checkpoint) >= {"model", "optimizer", "config", "state", "rng", "model_spec"}


def test_evaluate_and_predict_agree_with_training(finished_run, cache_dir):
    run_dir, metrics = finished_run
    again = evaluate(run_dir, progress=False)
    assert again["summary"]["accuracy"] == pytest.approx(metrics["summary"]["accuracy"])

    surface, labels, _ = make_creature(123, n_vertices=200)
    prediction, probabilities = predict(run_dir, surface, probabilities=True)
    assert prediction.shape == (200,) and prediction.dtype == np.int64
    assert probabilities.shape == (200, 4)
    np.testing.assert_allclose(probabilities.sum(axis=1), 1.0, rtol=1e-5)


def test_batches_prepare_the_operators_the_model_reads(finished_run):
    # Batches are built on the read-ahead thread; whatever the convolutions' products read must be prepared
    # there too, so a training step adds nothing to what an operator holds.
    run_dir, _ = finished_run
    checkpoint = load_checkpoint(run_dir / "best.pt")
    model = build_model_from_spec(checkpoint["model_spec"])
    orders = model_basis_orders(model)
    convs = [m for m in model.modules() if hasattr(m, "operator_basis_order")]
    assert convs and orders == (convs[0].operator_basis_order(),) and orders[0] is not None
    dataset = build_dataset(checkpoint["config"], progress=False)
    batch = Batch([dataset[0]], torch.device("cpu"), None, checkpoint.get("feature_stats"), None, orders)
    operator = batch.geometry.operators[0]
    prepared = operator.prepared_nbytes
    model(batch.features, batch.geometry).sum().backward()
    assert operator.prepared_nbytes == prepared


def test_ensemble_averages_the_members_probabilities(finished_run, cache_dir, tmp_path):
    run_a, _ = finished_run
    run_b = tmp_path / "b"
    train(tiny_config(cache_dir, epochs=2, seed=1), run_b, progress=False, workers=0)
    dataset = build_dataset(load_checkpoint(run_a / "best.pt")["config"], progress=False)
    # The same run twice is that run.
    single = evaluate(run_a, dataset=dataset, progress=False)
    assert evaluate([run_a, run_a], dataset=dataset, progress=False)["per_shape"] == single["per_shape"]
    # Two runs: the argmax of their mean probabilities, shape by shape.
    ensemble = evaluate([run_a, run_b], dataset=dataset, progress=False)
    assert ensemble["checkpoint"] == [str(run_a / "best.pt"), str(run_b / "best.pt")]
    for i in dataset.splits["test"]:
        record = dataset[i]
        mean = (
            predict(run_a, record.surface, probabilities=True)[1]
            + predict(run_b, record.surface, probabilities=True)[1]
        ) / 2
        expected = float(np.mean(mean.argmax(axis=1) == record.target))
        assert ensemble["per_shape"][record.name]["accuracy"] == pytest.approx(expected)


def test_regression_ensemble_of_log_targets_is_a_geometric_mean(finished_run):
    run_dir, _ = finished_run
    record = build_dataset(load_checkpoint(run_dir / "best.pt")["config"], progress=False)[0]

    class Constant(torch.nn.Module):
        def __init__(self, value):
            super().__init__()
            self.value = value

        def forward(self, x, geometry):
            return torch.full((x.shape[0], 1), self.value)

    stats = {"mean": 1.0, "std": 2.0, "transform": "log"}
    members = [(Constant(v), {"task": "regression", "target_stats": stats}) for v in (0.0, 1.0)]
    values, _ = predict_record(members, record, torch.device("cpu"))
    # Members predict exp(1) and exp(3): the ensemble exp(2) (their geometric mean, not their mean).
    np.testing.assert_allclose(values, np.exp(2.0), rtol=1e-6)
    single, _ = predict_record(members[1:], record, torch.device("cpu"))
    np.testing.assert_allclose(single, np.exp(3.0), rtol=1e-6)


def test_ensemble_members_must_match(finished_run, cache_dir, tmp_path):
    run_a, _ = finished_run
    other = tiny_config(cache_dir, epochs=1)
    other["data"]["seed"] = 5  # another train/val/test split
    train(other, tmp_path / "other", progress=False, workers=0)
    with pytest.raises(ConfigError, match=r"data section differs \(seed: 5 vs 0\)"):
        evaluate([run_a, tmp_path / "other"], progress=False)


def test_loss_decreases_on_an_overfittable_task(tmp_path, cache_dir):
    config = tiny_config(cache_dir, epochs=8, patience=None, lr=1e-2)
    metrics = train(config, tmp_path / "run", progress=False, workers=0)
    history = load_checkpoint(tmp_path / "run" / "last.pt")["state"]["history"]
    assert len(history) == 8
    assert history[-1]["train_loss"] < 0.8 * history[0]["train_loss"]
    assert metrics["epochs_trained"] == 8


def test_keep_epochs_keeps_every_epochs_weights_for_evaluation(tmp_path, cache_dir):
    run_dir = tmp_path / "run"
    train(tiny_config(cache_dir, epochs=2, patience=None, keep_epochs=True), run_dir, progress=False, workers=0)
    kept = sorted((run_dir / "epochs").glob("*.pt"))
    assert [path.name for path in kept] == ["epoch_001.pt", "epoch_002.pt"]
    last, second = load_checkpoint(run_dir / "last.pt"), load_checkpoint(kept[1])
    assert "optimizer" not in second and all(torch.equal(last["model"][k], second["model"][k]) for k in last["model"])
    first = load_checkpoint(kept[0])
    assert any(not torch.equal(first["model"][k], second["model"][k]) for k in first["model"])
    scores = evaluate(kept[1], progress=False)["summary"]["accuracy"]
    assert scores == pytest.approx(evaluate(run_dir / "last.pt", progress=False)["summary"]["accuracy"])


def test_training_flushes_denormals_while_it_optimises(tmp_path, cache_dir, monkeypatch):
    """Denormal floats (late softmax gradients) would run through the CPU's slow path: the epochs read them as
    0, and the flag is off again afterwards (the geometry code is not run under it)."""
    if not torch.set_flush_denormal(False):
        pytest.skip("this CPU has no flush-to-zero mode")
    denormals = torch.from_numpy(np.full(8, 1e-39, dtype=np.float32))
    seen, fit = [], loop._fit

    def watched_fit(*args, **kwargs):
        seen.append((denormals * 1.0).abs().max().item())
        return fit(*args, **kwargs)

    monkeypatch.setattr(loop, "_fit", watched_fit)
    train(tiny_config(cache_dir, epochs=1, patience=None), tmp_path / "run", progress=False, workers=0)
    assert seen == [0.0]
    assert (denormals * 1.0).abs().max().item() > 0


def test_resume_gives_the_same_weights_as_an_uninterrupted_run(tmp_path, cache_dir):
    full = tiny_config(cache_dir, epochs=4, patience=None)
    train(full, tmp_path / "full", progress=False, workers=0)

    # Same run cut after two epochs, then resumed with the full budget.
    train(tiny_config(cache_dir, epochs=2, patience=None), tmp_path / "cut", progress=False, workers=0)
    train(full, tmp_path / "cut", resume=True, progress=False, workers=0)

    a = load_checkpoint(tmp_path / "full" / "last.pt")
    b = load_checkpoint(tmp_path / "cut" / "last.pt")
    assert b["state"]["epoch"] == 4
    for key in a["model"]:
        torch.testing.assert_close(b["model"][key], a["model"][key], rtol=1e-6, atol=1e-7)
    losses_a = [h["train_loss"] for h in a["state"]["history"]]
    losses_b = [h["train_loss"] for h in b["state"]["history"]]
    np.testing.assert_allclose(losses_b, losses_a, rtol=1e-6)
    assert "resumed after epoch 2" in (tmp_path / "cut" / "train.log").read_text()


def test_early_stopping_triggers(tmp_path, cache_dir):
    # A learning rate far too small to change the predictions: validation never improves after epoch 1.
    config = tiny_config(cache_dir, epochs=20, patience=2, lr=1e-12)
    metrics = train(config, tmp_path / "run", progress=False, workers=0)
    assert metrics["epochs_trained"] == 3
    assert metrics["best_epoch"] == 1
    assert metrics["stop_reason"].startswith("early stopping")


def test_existing_run_is_not_clobbered(finished_run, cache_dir):
    run_dir, _ = finished_run
    with pytest.raises(ConfigError, match="--resume"):
        train(tiny_config(cache_dir), run_dir, progress=False, workers=0)


def test_config_errors_name_the_key(cache_dir):
    base = tiny_config(cache_dir)
    bad_train = copy.deepcopy(base)
    bad_train["train"]["epoch"] = 3
    with pytest.raises(ConfigError, match="train.epoch"):
        resolve_config(bad_train)
    bad_section = dict(base, optimiser={})
    with pytest.raises(ConfigError, match="optimiser"):
        resolve_config(bad_section)
    bad_scale = copy.deepcopy(base)
    bad_scale["patch"]["scales"][0]["radius"] = 2
    with pytest.raises(ConfigError, match="patch.scales.0.radius"):
        resolve_config(bad_scale)
    with pytest.raises(ConfigError, match="train.lr"):
        resolve_config(apply_overrides(base, ["train.lr=fast"]))


def test_overrides_are_parsed_as_yaml():
    config = {"train": {"epochs": 200}, "patch": {"scales": [{"r0": 5.5}]}}
    out = apply_overrides(
        config, ["train.epochs=5", "model.name=feastnet", "model.widths=[8, 16]", "patch.scales.0.r0=4.5"]
    )
    assert out["train"]["epochs"] == 5 and out["model"] == {"name": "feastnet", "widths": [8, 16]}
    assert out["patch"]["scales"][0]["r0"] == 4.5
    assert config["train"]["epochs"] == 200  # the input is not modified
    # Plain YAML 1.1 would read 1e-3 as a string; a config means the number.
    numbers = apply_overrides({}, ["train.weight_decay=1e-3", "train.lr=2E+2", "data.root=1e3x"])
    assert numbers["train"] == {"weight_decay": 1e-3, "lr": 200.0} and numbers["data"]["root"] == "1e3x"
    with pytest.raises(ConfigError):
        apply_overrides(config, ["train.epochs"])
    with pytest.raises(ConfigError, match="index"):
        apply_overrides(config, ["patch.scales.3.r0=1"])


def test_epoch_order_depends_only_on_seed_and_epoch():
    assert epoch_order(0, 3, 10) == epoch_order(0, 3, 10)
    assert sorted(epoch_order(0, 3, 10)) == list(range(10))
    assert epoch_order(0, 3, 10) != epoch_order(0, 4, 10)
    assert step_groups([4, 2, 0, 1, 3], 2) == [[4, 2], [0, 1], [3]]


class _Targets:
    """The two things target standardisation reads from a data set: targets by index and shape names."""

    def __init__(self, targets):
        self.targets = targets
        self.names = [f"shape{i}" for i in range(len(targets))]

    def target(self, i):
        return self.targets[i]


def test_log_target_transform_round_trips_and_is_standardised():
    rng = np.random.default_rng(0)
    data = _Targets([rng.uniform(0.004, 0.3, size=n) for n in (50, 80)])
    stats = target_stats(data, [0, 1], transform="log")
    assert stats["transform"] == "log"
    logs = np.log(np.concatenate(data.targets))
    assert stats["mean"] == pytest.approx(logs.mean()) and stats["std"] == pytest.approx(logs.std())
    target = torch.from_numpy(data.targets[1])
    trained = standardise(target, stats)
    torch.testing.assert_close(
        trained.double(), torch.from_numpy((np.log(data.targets[1]) - logs.mean()) / logs.std()), rtol=1e-5, atol=1e-5
    )
    torch.testing.assert_close(unstandardise(trained, stats).double(), target, rtol=1e-5, atol=0)
    # Without standardisation the network is trained on log y itself.
    plain = target_stats(data, [0, 1], transform="log", standardize=False)
    torch.testing.assert_close(standardise(target, plain).double(), torch.log(target), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("transform", ["log", "none"])
def test_relative_l1_loss_is_the_mape_of_the_predictions(transform):
    rng = np.random.default_rng(1)
    data = _Targets([rng.uniform(0.004, 0.3, size=n) for n in (50, 80)])
    stats = target_stats(data, [0, 1], transform=transform)
    target = standardise(torch.from_numpy(data.targets[1]), stats).double()
    output = (target + 0.3 * torch.randn(80, dtype=torch.float64)).reshape(80, 1).requires_grad_()
    loss = compute_loss("relative_l1", output, target, stats)
    prediction = unstandardise(output.detach().reshape(-1), stats).numpy()
    assert loss.item() == pytest.approx(regression_scores(prediction, data.targets[1])["MAPE"], rel=1e-6)
    # Its gradient pushes every prediction towards its target.
    loss.backward()
    assert torch.all(torch.sign(output.grad.reshape(-1)) == torch.sign(output.detach().reshape(-1) - target))


def test_relative_l1_loss_refuses_zero_targets(tmp_path, cache_dir, monkeypatch):
    build = loop.build_dataset

    def with_a_zero(*args, **kwargs):  # the first training shape gets a zero target at vertex 3
        dataset = build(*args, **kwargs)
        first, target = dataset.splits["train"][0], dataset.target

        def patched(i):
            values = np.array(target(i), dtype=np.float64).reshape(-1)
            if i == first:
                values[3] = 0.0
            return values

        dataset.target = patched
        return dataset

    monkeypatch.setattr(loop, "build_dataset", with_a_zero)
    config = tiny_config(cache_dir, loss="relative_l1", epochs=1)
    config["data"]["task"] = "regression"
    with pytest.raises(ConfigError, match=r"relative_l1 divides by the target, but shape \S+ has 0 at vertex 3"):
        train(config, tmp_path / "run", progress=False, workers=0)


def _test_sphere_labels(spheres) -> np.ndarray:
    return np.loadtxt(spheres / "test" / "shape5.txt", dtype=np.int64)


def test_bfloat16_precision_trains_and_is_validated(tmp_path, cache_dir, labelled_spheres):
    config = sphere_config(labelled_spheres, cache_dir, epochs=SPHERE_LEARNT_EPOCHS)
    config["train"]["precision"] = "bfloat16"
    config["eval"] = {"renders": 0, "plots": False}
    metrics = train(config, tmp_path / "run", progress=False, workers=0)
    history = load_checkpoint(tmp_path / "run" / "best.pt")["state"]["history"]
    assert all(np.isfinite(h["train_loss"]) for h in history)
    # It learns the labelling as float32 does (measured: every test vertex right, the majority class 60 %).
    assert metrics["summary"]["accuracy"] > majority_fraction(_test_sphere_labels(labelled_spheres)) + 0.3
    with pytest.raises(ConfigError, match="train.precision must be one of float32, bfloat16"):
        resolve_config(tiny_config(cache_dir, precision="float16"))


def test_log_target_transform_trains_and_predicts_positive_values(tmp_path, cache_dir):
    config = tiny_config(cache_dir, target_transform="log", loss="l1", epochs=2)
    config["data"]["task"] = "regression"  # mean curvature, positive on these blobby creatures
    metrics = train(config, tmp_path / "run", progress=False, workers=0)
    assert np.isfinite(metrics["summary"]["MAPE"])
    assert load_checkpoint(tmp_path / "run" / "best.pt")["target_stats"]["transform"] == "log"
    surface, _, curvature = make_creature(123, n_vertices=200)
    prediction = predict(tmp_path / "run", surface)
    assert prediction.shape == (200,) and np.all(prediction > 0)
    # Predictions come in the surface's own units: curvature is 1/length, so twice the size, half the value.
    larger = Surface(surface.vertices * 2.0, surface.faces, name="larger")
    np.testing.assert_allclose(predict(tmp_path / "run", larger), prediction / 2.0, rtol=1e-4)


def test_log_target_transform_rejects_non_positive_targets(cache_dir):
    with pytest.raises(ConfigError, match=r"shape1 has -0\.5 at vertex 2"):
        target_stats(_Targets([np.ones(3), np.array([1.0, 2.0, -0.5])]), [0, 1], transform="log")
    with pytest.raises(ConfigError, match="train.target_transform"):
        resolve_config(tiny_config(cache_dir, target_transform="sqrt"))


def test_cosine_schedule_and_resume_from_mid_schedule(tmp_path, cache_dir):
    tcfg = TrainSection(lr=0.1, lr_schedule="cosine", epochs=4)
    rates = [epoch_learning_rate(tcfg, e) for e in range(1, 5)]
    assert rates[0] == pytest.approx(0.1) and rates[2] == pytest.approx(0.05)
    assert all(a > b > 0 for a, b in zip(rates, rates[1:]))
    assert epoch_learning_rate(TrainSection(lr=0.1, epochs=4), 3) == 0.1  # constant by default
    # A run trained in pieces (epochs 1, 2, ... with resume) keeps the schedule of its whole span.
    pieces = [
        epoch_learning_rate(TrainSection(lr=0.1, lr_schedule="cosine", epochs=e, lr_schedule_epochs=4), e)
        for e in range(1, 5)
    ]
    assert pieces == pytest.approx(rates)
    assert epoch_learning_rate(
        TrainSection(lr=0.1, lr_schedule="cosine", epochs=6, lr_schedule_epochs=4), 6
    ) == pytest.approx(rates[-1])  # past the span: the last epoch's rate

    config = tiny_config(cache_dir, epochs=4, patience=None, lr_schedule="cosine")
    train(config, tmp_path / "full", progress=False, workers=0)
    saved = load_checkpoint(tmp_path / "full" / "last.pt")["optimizer"]["param_groups"][0]["lr"]
    assert saved == pytest.approx(epoch_learning_rate(parse_config(config).train, 4))  # the last epoch's lr
    # The checkpoint of epoch 3 (previous.pt), resumed with the same config, must land on the same weights.
    shutil.copytree(tmp_path / "full", tmp_path / "cut")
    (tmp_path / "cut" / "metrics.json").unlink()
    shutil.copy(tmp_path / "cut" / "previous.pt", tmp_path / "cut" / "last.pt")
    assert load_checkpoint(tmp_path / "cut" / "last.pt")["state"]["epoch"] == 3
    train(config, tmp_path / "cut", resume=True, progress=False, workers=0)
    a = load_checkpoint(tmp_path / "full" / "last.pt")["model"]
    b = load_checkpoint(tmp_path / "cut" / "last.pt")["model"]
    for key in a:
        torch.testing.assert_close(b[key], a[key], rtol=1e-6, atol=1e-7)


def test_feature_standardisation_is_stored_and_used_by_predict(tmp_path, cache_dir):
    # Statistics over every training vertex, per channel; a constant channel keeps std 1.
    records = [
        SimpleNamespace(features=np.c_[np.arange(4.0), np.full(4, 3.0)]),
        SimpleNamespace(features=np.c_[np.arange(4.0, 8.0), np.full(4, 3.0)]),
    ]
    stats = feature_stats(records, [0, 1])
    np.testing.assert_allclose(stats["mean"], [3.5, 3.0])
    np.testing.assert_allclose(stats["std"], [np.arange(8.0).std(), 1.0])

    config = tiny_config(cache_dir, standardize_features=True)
    train(config, tmp_path / "run", progress=False, workers=0)
    checkpoint = load_checkpoint(tmp_path / "run" / "best.pt")
    assert len(checkpoint["feature_stats"]["mean"]) == 3  # xyz
    surface, _, _ = make_creature(123, n_vertices=200)
    _, probabilities = predict(tmp_path / "run", surface, probabilities=True)
    assert probabilities.shape == (200, 4) and np.isfinite(probabilities).all()
    # What every batch (training, validation, predict) feeds the model: (x - mean) / std per channel.
    raw = np.asarray(surface.vertices, np.float32)
    record = SimpleNamespace(
        features=raw, name="x", target=None, geometry=SimpleNamespace(to=lambda device, basis_orders=(): None)
    )
    batch = Batch([record], torch.device("cpu"), None, checkpoint["feature_stats"])
    expected = (raw - np.array(checkpoint["feature_stats"]["mean"])) / np.array(checkpoint["feature_stats"]["std"])
    np.testing.assert_allclose(batch.features.numpy(), expected, rtol=1e-5, atol=1e-5)


def test_directional_model_trains_and_predicts_with_operators_built_before_the_network(
    tmp_path, cache_dir, labelled_spheres
):
    # The direction-preserving model reads directional operators from the geometry; training and
    # prediction build them per shape before the forward (the layers never do).
    config = sphere_config(labelled_spheres, cache_dir, epochs=SPHERE_LEARNT_EPOCHS)
    config["model"] = {"name": "zernet-directional", "widths": [4, 4], "angular_resolution": 3, "dropout": 0.0}
    config["eval"] = {"renders": 0, "plots": False}
    metrics = train(config, tmp_path / "run", progress=False, workers=0)
    # Measured: every test vertex right, against 60 % for the majority class.
    labels = _test_sphere_labels(labelled_spheres)
    assert metrics["summary"]["accuracy"] > majority_fraction(labels) + 0.3
    again = evaluate(tmp_path / "run", progress=False)
    assert again["summary"]["accuracy"] == pytest.approx(metrics["summary"]["accuracy"])
    answers = predict(tmp_path / "run", labelled_spheres / "test" / "shape5.obj")
    assert np.mean(answers == labels) == pytest.approx(metrics["summary"]["accuracy"])


def test_a_fixed_scale_is_kept_in_the_checkpoint_and_applied_by_predict(tmp_path, cache_dir):
    """patch.scale: every shape is multiplied by the factor (not normalised to an area), the checkpoint
    keeps it, and predict applies it to a new surface, so a partial one keeps its size."""
    config = tiny_config(cache_dir, epochs=1)
    config["patch"]["scale"] = 1.5
    train(config, tmp_path / "run", progress=False, workers=0)
    checkpoint = load_checkpoint(tmp_path / "run" / "best.pt")
    assert checkpoint["preprocess"]["unit_scale"] == 1.5 and checkpoint["preprocess"]["area"] is None
    dataset = build_dataset(checkpoint["config"], progress=False)
    assert all(dataset[i].scale == 1.5 for i in range(len(dataset)))
    surface, _, _ = make_creature(123, n_vertices=200)
    kept = surface.faces[surface.vertices[surface.faces].mean(axis=1)[:, 0] > 0]
    used, faces = np.unique(kept, return_inverse=True)
    half = Surface(surface.vertices[used], faces.reshape(-1, 3))  # one side, renumbered
    _, default = predict(tmp_path / "run", half, probabilities=True)
    _, explicit = predict(tmp_path / "run", half, probabilities=True, scale=1.5)
    np.testing.assert_array_equal(default, explicit)
    with pytest.raises(ConfigError, match="patch.area .* and patch.scale .* both set"):
        parse_config({**config, "patch": {**config["patch"], "area": 100.0}})
