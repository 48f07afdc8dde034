"""One model-file format: every shipped model is in it, holds what shipped before it, old files still load,
and a file of another kind is refused by name."""

import hashlib

import numpy as np
import pytest
import torch

from zernet.data import prepare_record
from zernet.inference.model_file import (
    MODEL_FILE_FORMAT,
    MODEL_FILE_VERSION,
    PRETRAINED,
    load_checkpoint,
    model_file,
    read_model_file,
)
from zernet.matching.model import PRETRAINED_MODEL, load_matching_model
from zernet.matching.template import PRETRAINED_TEMPLATE_MODEL, load_template_model

#: Digest (:func:`_contents_digest`) of each shipped file's contents, measured on the files as first
#: shipped, before they were converted to the one format: the conversion changed nothing but the format
#: fields, so the models give the same outputs as before (files shipped later: as shipped).
SHIPPED = {
    "bodies": ("backbone", "bddb43d85a04c75f7cf473665787052a2830a5c37351edb59723180db90d24b9"),
    "bodies-xyz-hks": ("backbone", "5c208c321aa12e8d981146a814db23f9ff41bd8558b4fbc07e842442ef91b40c"),
    "bodies-faust-template": ("backbone", "d99ea255e159f581967961f161187d18af6ed040f0600d92076d423d24688eb4"),
    # The first template model, shipped as bodies-match-template until the wide-pose fine-tune replaced it.
    "bodies-template-part": ("template", "da27941060f2544601d7afd8cc570c9eae2ba82417905c99de0e138391205544"),
    "bodies-match-template": ("template", "4880a82eab19cbf3324b43704761bc50900b26c8a668797280a78a715927ce1f"),
    "bodies-match-descriptors": ("descriptors", "9845dfdc97550815ecae94fac6f31b36ea14669970a0f2bb5d02d486839bd996"),
}

FORMAT_FIELDS = ("format", "version", "kind")


def _contents_digest(value, digest=None) -> str | None:
    """sha256 over a file's contents: every tensor's dtype, shape and bytes, every plain value, in key order."""
    top = digest is None
    digest = digest or hashlib.sha256()
    if isinstance(value, torch.Tensor):
        tensor = value.contiguous()
        digest.update(f"tensor {tensor.dtype} {tuple(tensor.shape)}".encode())
        digest.update(tensor.view(torch.uint8).numpy().tobytes())
    elif isinstance(value, dict):
        digest.update(f"dict {len(value)}".encode())
        for key in sorted(value, key=str):
            digest.update(repr(key).encode())
            _contents_digest(value[key], digest)
    elif isinstance(value, (list, tuple)):
        digest.update(f"{type(value).__name__} {len(value)}".encode())
        for item in value:
            _contents_digest(item, digest)
    else:
        digest.update(repr(value).encode())
    return digest.hexdigest() if top else None


def _contents(stored: dict) -> dict:
    return {key: value for key, value in stored.items() if key not in FORMAT_FIELDS}


def test_every_shipped_model_is_in_one_folder_and_format_with_the_contents_it_shipped_with():
    assert sorted(path.stem for path in PRETRAINED.glob("*.pt")) == sorted(SHIPPED)
    for name, (kind, digest) in SHIPPED.items():
        path = PRETRAINED / f"{name}.pt"
        raw = torch.load(path, map_location="cpu", weights_only=True)
        assert (raw["format"], raw["version"], raw["kind"]) == (MODEL_FILE_FORMAT, MODEL_FILE_VERSION, kind), name
        assert _contents_digest(_contents(raw)) == digest, name
        assert (PRETRAINED / f"{name}.json").is_file(), name
    assert PRETRAINED_MODEL.parent == PRETRAINED_TEMPLATE_MODEL.parent == PRETRAINED


@pytest.mark.parametrize("old_format, kind", [("zernet-template-1", "template"), ("zernet-matching-1", "descriptors")])
def test_a_file_of_an_old_format_reads_as_its_kind(tmp_path, old_format, kind):
    shipped = PRETRAINED_TEMPLATE_MODEL if kind == "template" else PRETRAINED_MODEL
    contents = _contents(read_model_file(shipped))
    torch.save({"format": old_format, **contents}, tmp_path / "old.pt")
    old = read_model_file(tmp_path / "old.pt")
    assert old["kind"] == kind and old["version"] == 0
    assert _contents_digest(_contents(old)) == _contents_digest(contents)


def test_a_descriptor_model_of_the_old_format_gives_the_same_outputs(tmp_path, sphere_surface):
    torch.save({"format": "zernet-matching-1", **_contents(read_model_file(PRETRAINED_MODEL))}, tmp_path / "old.pt")
    (new, _), (old, _) = load_matching_model(), load_matching_model(tmp_path / "old.pt")
    spec = new.spec
    record = prepare_record(
        sphere_surface, spec.patch_config_objects(), None, target_area=spec.area, feature_kind="xyz"
    )
    features = torch.from_numpy(np.random.default_rng(0).normal(size=(162, spec.in_channels)).astype(np.float32))
    with torch.no_grad():
        expected = new(features, record.geometry)
        assert torch.equal(old(features, record.geometry), expected)
    assert expected.shape == (162, spec.descriptor_size) and torch.isfinite(expected).all()


def test_the_template_model_of_the_old_format_loads_the_same_network(tmp_path):
    torch.save(
        {"format": "zernet-template-1", **_contents(read_model_file(PRETRAINED_TEMPLATE_MODEL))}, tmp_path / "old.pt"
    )
    new, old = load_template_model(), load_template_model(tmp_path / "old.pt")
    for (name, value), (old_name, old_value) in zip(new.network.state_dict().items(), old.network.state_dict().items()):
        assert name == old_name and torch.equal(value, old_value), name
    np.testing.assert_array_equal(new.template_positions, old.template_positions)


def test_a_file_of_another_kind_is_refused_by_name(tmp_path):
    with pytest.raises(ValueError, match="not a zernet checkpoint: it holds a template model"):
        load_checkpoint(PRETRAINED_TEMPLATE_MODEL)
    with pytest.raises(ValueError, match="not a zernet template model: it holds a descriptors model"):
        load_template_model(PRETRAINED_MODEL)
    torch.save({"format": "something-else"}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not a zernet model file"):
        read_model_file(tmp_path / "other.pt")
    torch.save(model_file("backbone", {"model": {}}) | {"version": MODEL_FILE_VERSION + 1}, tmp_path / "newer.pt")
    with pytest.raises(ValueError, match="newer than this zernet reads"):
        read_model_file(tmp_path / "newer.pt")
    with pytest.raises(ValueError, match="unknown model file kind"):
        model_file("weights", {})
    with pytest.raises(FileNotFoundError):
        read_model_file(tmp_path / "missing.pt")
