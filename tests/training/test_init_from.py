"""``--init-from``: a new run starts from another run's weights (convolutions copied, a new output layer where
the classes differ), refuses what does not fit with an error naming the parameter, and keeps reporting it."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from meshes import ellipsoid, write_faust_layout
from tiny_configs import faust_run_config, tiny_config

from zernet.cli import main
from zernet.data import LoaderOptions, load_faust
from zernet.data.features import feature_channels
from zernet.geometry import Surface
from zernet.inference import build_model_from_spec, load_checkpoint, model_file, model_spec, predict
from zernet.inference.model_file import pretrained_names
from zernet.operators import PatchConfig
from zernet.training import ConfigError, load_config, parse_config, train
from zernet.training.config import apply_overrides
from zernet.training.init_from import export_backbone, initialise_from, load_init_source


@pytest.fixture(scope="module")
def source_run(tmp_path_factory, cache_dir):
    """A finished 2-epoch run on the tiny segmentation creatures (4 classes)."""
    run_dir = tmp_path_factory.mktemp("source")
    train(tiny_config(cache_dir), run_dir, progress=False, workers=0)
    return run_dir


def _spec(source_run, **changes) -> dict:
    spec = copy.deepcopy(load_checkpoint(source_run / "best.pt")["model_spec"])
    spec.update(changes)
    return spec


def test_copies_every_weight_when_the_model_is_the_same(source_run):
    source = load_init_source(source_run)  # a run folder means its best.pt
    assert source.path == source_run / "best.pt"
    model = build_model_from_spec(source.model_spec)
    info = initialise_from(model, source)
    assert info["reinitialised"] == [] and info["copied"] == len(model.state_dict())
    for name, value in model.state_dict().items():
        assert torch.equal(value, source.weights[name]), name


def test_new_output_layer_where_the_classes_differ(source_run):
    source = load_init_source(source_run / "best.pt")  # a checkpoint file is taken as it is
    torch.manual_seed(123)
    model = build_model_from_spec(_spec(source_run, out_channels=7))
    fresh_output = copy.deepcopy(model.output.state_dict())
    info = initialise_from(model, source)
    assert sorted(info["reinitialised"]) == ["output.bias", "output.weight"]
    assert model.output.weight.shape == (7, source.weights["output.weight"].shape[1])
    for name, value in model.output.state_dict().items():  # the head keeps its fresh initialisation
        assert torch.equal(value, fresh_output[name])
    for name, value in model.state_dict().items():
        if not name.startswith("output."):
            assert torch.equal(value, source.weights[name]), name


def test_other_widths_fail_naming_the_parameter(source_run):
    source = load_init_source(source_run)
    model = build_model_from_spec(_spec(source_run, options={**_spec(source_run)["options"], "widths": [8, 12, 16]}))
    with pytest.raises(ConfigError, match=r"parameter 'blocks\.1\.[\w.]+' has shape"):
        initialise_from(model, source)


def test_other_input_channels_fail_naming_the_parameter(source_run):
    source = load_init_source(source_run)
    model = build_model_from_spec(_spec(source_run, in_channels=6))
    with pytest.raises(ConfigError, match=r"parameter 'blocks\.0\.[\w.]+' has shape"):
        initialise_from(model, source)


def test_other_model_family_fails_naming_the_parameter(source_run):
    source = load_init_source(source_run)
    model = build_model_from_spec(_spec(source_run, name="feastnet", options={"widths": [8, 8, 16]}))
    with pytest.raises(ConfigError, match=r"parameter '[\w.]+' does not fit"):
        initialise_from(model, source)


def test_missing_source_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_init_source(tmp_path / "nowhere")
    with pytest.raises(FileNotFoundError, match="best.pt"):
        load_init_source(tmp_path)  # a folder that is no run


def test_run_starts_from_the_weights_and_reports_it(source_run, tmp_path, cache_dir):
    """Zero epochs: the selected model is the initial one, so it must equal the source's weights."""
    run_dir = tmp_path / "tuned"
    metrics = train(
        tiny_config(cache_dir, epochs=1, lr=1e-12), run_dir, progress=False, workers=0, init_from=source_run
    )
    source = load_checkpoint(source_run / "best.pt")["model"]
    tuned = load_checkpoint(run_dir / "best.pt")
    for name, value in tuned["model"].items():
        assert torch.allclose(value, source[name], atol=1e-6), name
    assert metrics["init_from"]["source"] == str(source_run / "best.pt")
    assert json.loads((run_dir / "metrics.json").read_text())["init_from"]["copied"] == len(source)
    assert "init-from:" in (run_dir / "train.log").read_text()
    assert tuned["state"]["init_from"]["reinitialised"] == []


def test_resumed_run_keeps_reporting_init_from(source_run, tmp_path, cache_dir):
    run_dir = tmp_path / "tuned"
    train(tiny_config(cache_dir, epochs=1), run_dir, progress=False, workers=0, init_from=source_run)
    metrics = train(tiny_config(cache_dir, epochs=2), run_dir, resume=True, progress=False, workers=0)
    assert metrics["epochs_trained"] == 2
    assert metrics["init_from"]["source"] == str(source_run / "best.pt")
    assert (run_dir / "train.log").read_text().count("init-from:") == 2


def test_init_from_with_resume_is_refused(source_run, tmp_path, cache_dir):
    with pytest.raises(ConfigError, match="cannot be combined with --resume"):
        train(None, tmp_path, resume=True, init_from=source_run)


def test_cli_init_from(source_run, tmp_path, cache_dir, capsys):
    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(tiny_config(cache_dir, epochs=1)))
    run_dir = tmp_path / "run"
    assert main(["train", str(config), "--run-dir", str(run_dir), "--no-progress", "--init-from", str(source_run)]) == 0
    assert "init_from" in json.loads((run_dir / "metrics.json").read_text())
    capsys.readouterr()
    # With --resume: refused by the command, exit 2, one line naming both options.
    assert main(["train", "--resume", "--run-dir", str(run_dir), "--init-from", str(source_run)]) == 2
    err = capsys.readouterr().err
    assert "--init-from" in err and "--resume" in err and len(err.strip().splitlines()) == 1
    # A model that does not fit: exit 2, the parameter named.
    assert (
        main(
            [
                "train",
                str(config),
                "--run-dir",
                str(tmp_path / "other"),
                "--no-progress",
                "--init-from",
                str(source_run),
                "--set",
                "model.widths=[8,12,16]",
            ]
        )
        == 2
    )
    assert "parameter 'blocks.1." in capsys.readouterr().err
    # A missing source fails before any preprocessing.
    assert main(["train", str(config), "--run-dir", str(tmp_path / "x"), "--init-from", str(tmp_path / "nope")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_a_backbone_starts_every_weight_but_a_fresh_output_layer(source_run, tmp_path, cache_dir):
    """Shipped weights hold no output layer: it starts fresh even where its shape agrees (another template
    of the same size must not take the source's classes), from the configuration's ``train.init_from``."""
    info = export_backbone(source_run, tmp_path / "backbone.pt")
    stored = load_checkpoint(tmp_path / "backbone.pt")
    assert "optimizer" not in stored and not any(name.startswith("output.") for name in stored["model"])
    assert all(value.dtype == torch.float16 for value in stored["model"].values() if value.is_floating_point())
    assert info["tensors"] == len(stored["model"])

    config = tiny_config(cache_dir, epochs=1, lr=1e-12)
    config["train"]["init_from"] = str(tmp_path / "backbone.pt")
    train(config, tmp_path / "tuned", progress=False, workers=0)
    tuned = load_checkpoint(tmp_path / "tuned" / "best.pt")
    source = load_checkpoint(source_run / "best.pt")["model"]
    assert sorted(tuned["state"]["init_from"]["reinitialised"]) == ["output.bias", "output.weight"]
    for name, value in tuned["model"].items():
        if name.startswith("output."):  # same shape as the source's, yet fresh
            assert not torch.allclose(value, source[name], atol=1e-3), name
        else:  # float16 storage: equal to the source's weights to half precision
            assert torch.allclose(value, source[name], rtol=1e-3, atol=1e-3), name


def test_shipped_weights_are_found_by_name_and_unknown_names_listed(source_run, tmp_path, monkeypatch):
    monkeypatch.setattr(model_file, "PRETRAINED", tmp_path)
    export_backbone(source_run, tmp_path / "creatures.pt")
    assert model_file.pretrained_names(("backbone",)) == ["creatures"]
    assert load_init_source("pretrained:creatures").path == tmp_path / "creatures.pt"
    with pytest.raises(FileNotFoundError, match="no weights named 'bodies'.*shipped: pretrained:creatures"):
        load_init_source("pretrained:bodies")


def test_the_shipped_weights_load():
    """Every shipped file is a backbone (no output layer) or a correspondence model with its template, whose
    output layer can follow another template."""
    for name in pretrained_names(("backbone",)):
        source = load_init_source(f"pretrained:{name}")
        head = [key for key in source.weights if key.startswith("output.")]
        assert source.weights and (not head or source.template is not None), name
        if head:
            vertices, faces = source.template
            assert source.weights["output.weight"].shape[0] == len(vertices) and faces.max() == len(vertices) - 1


def test_the_generated_start_fits_the_faust_config_with_its_inputs():
    """The shipped generated-body model is a start for configs/faust_single_scale.yaml with its inputs
    (xyz + hks + template, input skip; the overrides of the real-people benchmark's ``generated-start``):
    the model takes every weight from it, its 6,890-way output layer included (carried by the model's vote
    when the run's template has another vertex order: tested above)."""
    root = Path(__file__).resolve().parents[2]
    overrides = yaml.safe_load((root / "configs" / "recipes" / "faust_people.yaml").read_text())["recipes"]
    config = load_config(root / "configs" / "faust_single_scale.yaml")
    assert config["train"]["init_from"] is None  # the shipped recipe starts from scratch
    config = parse_config(apply_overrides(config, overrides["generated-start"]))
    assert config.train.init_from == "pretrained:bodies-faust-template"
    degrees = [int(scale["n_max"]) for scale in config.patch.scales]
    in_channels = feature_channels(config.data.options["features"], degrees)
    spec = model_spec(config.model, in_channels, 6890, [PatchConfig(r0=1.0, n_max=n) for n in degrees])
    model = build_model_from_spec(spec)
    source = load_init_source(config.train.init_from)
    info = initialise_from(model, source)
    assert info["reinitialised"] == [] and info["copied"] == len(model.state_dict())
    assert source.template is not None and len(source.template[0]) == 6890


def test_a_template_model_file_is_a_start_to_fine_tune(source_run, tmp_path):
    """zernet match's classifier, fine-tuned on bodies of one's own: its network is taken whole."""
    import numpy as np

    from zernet.matching.template import save_template_model

    checkpoint = load_checkpoint(source_run / "best.pt")
    provenance = {"command": "test", "commit": "abc", "config": {}, "training_area": 100.0}
    path = save_template_model(checkpoint, np.zeros((checkpoint["num_classes"], 3)), tmp_path / "t.pt", provenance)
    source = load_init_source(path)
    assert source.task == "classification" and source.num_classes == checkpoint["num_classes"]
    model = build_model_from_spec(source.model_spec)
    info = initialise_from(model, source)
    assert info["reinitialised"] == [] and info["copied"] == len(model.state_dict())
    for name, value in model.state_dict().items():  # stored in float16
        torch.testing.assert_close(value, checkpoint["model"][name].half().float(), msg=name)
    (tmp_path / "other.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable zernet checkpoint"):
        load_init_source(tmp_path / "other.pt")


def test_the_output_layer_follows_the_template_to_another_vertex_order(ellipsoid_faust_root, tmp_path):
    """Between correspondence runs whose templates differ, each new template vertex takes the output row of
    the class the source model gives it on the new training shapes (softmax summed over them): the carried
    model predicts on renumbered shapes what the source predicts, renumbered, where the vote is unanimous."""
    patch = {"r0": 1.2, "n_samples": 1500, "patch_size": 30, "n_max": 2}
    # 150 epochs: the source names nearly every vertex of its 2 training shapes.
    config = faust_run_config(ellipsoid_faust_root, 642, patch, train={"epochs": 150})
    train(config, tmp_path / "source", progress=False)
    source = load_init_source(tmp_path / "source")
    # The same ellipsoids with their vertices in another order: new vertex i is the old vertex order[i].
    order = np.random.default_rng(0).permutation(642)
    renumbered = np.empty_like(order)
    renumbered[order] = np.arange(642)
    shapes = [ellipsoid(noise=0.01, seed=i) for i in range(5)]
    write_faust_layout(tmp_path / "new", [Surface(s.vertices[order], renumbered[s.faces]) for s in shapes])
    options = LoaderOptions(
        patch_configs=[PatchConfig(**patch)], cache_dir=tmp_path / "cache", n_val=1, workers=0, progress=False
    )
    dataset = load_faust(tmp_path / "new", range(3), [3, 4], n_vertices=None, area=100.0, options=options)
    voters = [dataset[i] for i in dataset.splits["train"]]
    template = (shapes[0].vertices[order], renumbered[shapes[0].faces])

    model = build_model_from_spec(source.model_spec)
    info = initialise_from(model, source, template, voters)
    assert info["reinitialised"] == [] and "vote on 2 training shapes; 0 vertices without a vote" in info["head"]
    # The vote, recomputed from the source model's own predictions on the renumbered training shapes.
    summed = sum(
        predict(tmp_path / "source", record.surface, probabilities=True, refine_rings=0)[1] for record in voters
    )
    rows = summed.argmax(axis=1)
    assert (rows == order).mean() > 0.95  # the source learnt its 2 shapes: the vote undoes the renumbering
    carried = model.output.weight.detach()
    same = (carried == source.weights["output.weight"][torch.as_tensor(rows)]).all(dim=1)
    assert same.float().mean() > 0.99, same.float().mean()
    # On a renumbered test shape the carried model names vertex i where the source named old vertex order[i].
    test_shape = Surface(shapes[3].vertices[order], renumbered[shapes[3].faces])
    before = predict(tmp_path / "source", shapes[3], refine_rings=0)[order]
    torch.save({**load_checkpoint(tmp_path / "source" / "best.pt"), "model": model.state_dict()}, tmp_path / "c.pt")
    after = predict(tmp_path / "c.pt", test_shape, refine_rings=0)
    unanimous = np.bincount(rows, minlength=642)[before] == 1
    assert unanimous.mean() > 0.9
    assert (rows[after] == before)[unanimous].mean() > 0.95
    # A run does the same with its own training shapes, and says so.
    config = faust_run_config(tmp_path / "new", 642, patch, train={"epochs": 1, "init_from": str(tmp_path / "source")})
    metrics = train(config, tmp_path / "run", progress=False)
    assert "vote on 2 training shapes; 0 vertices without a vote" in metrics["init_from"]["head"]
    # The same connectivity: the rows are copied as they are.
    info = initialise_from(model, source, (shapes[0].vertices, shapes[0].faces), voters)
    assert info["head"] == "copied" and torch.equal(model.output.weight, source.weights["output.weight"])
