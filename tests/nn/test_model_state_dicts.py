"""State-dict keys and shapes of every registered model, pinned: checkpoints written by earlier versions
load only while these stay the same (``widths=(8, 16, 32)``, 3 inputs, 5 outputs, default options)."""

import pytest
import torch

from zernet.nn.models import available_models, build_model, directional_order

PINNED = {
    "feastnet": [
        ("input.weight", (16, 3)),
        ("input.bias", (16,)),
        ("convs.0.c", (8,)),
        ("convs.0.bias", (8,)),
        ("convs.0.lin.weight", (64, 16)),
        ("convs.0.u.weight", (8, 16)),
        ("convs.1.c", (8,)),
        ("convs.1.bias", (16,)),
        ("convs.1.lin.weight", (128, 8)),
        ("convs.1.u.weight", (8, 8)),
        ("hidden.weight", (32, 16)),
        ("hidden.bias", (32,)),
        ("output.weight", (5, 32)),
        ("output.bias", (5,)),
    ],
    "paper-zernet": [
        ("blocks.0.convs.0.weight", (21, 3, 8)),
        ("blocks.0.convs.0.bias", (8,)),
        ("blocks.1.convs.0.weight", (21, 8, 16)),
        ("blocks.1.convs.0.bias", (16,)),
        ("hidden.weight", (32, 16)),
        ("hidden.bias", (32,)),
        ("output.weight", (5, 32)),
        ("output.bias", (5,)),
    ],
    "zernet": [
        ("blocks.0.convs.0.weight", (21, 3, 8)),
        ("blocks.0.convs.0.bias", (8,)),
        ("blocks.1.convs.0.weight", (21, 8, 16)),
        ("blocks.1.convs.0.bias", (16,)),
        ("hidden.weight", (32, 16)),
        ("hidden.bias", (32,)),
        ("output.weight", (5, 32)),
        ("output.bias", (5,)),
    ],
    "zernet-directional": [
        ("convs.0.weight", (21, 1, 3, 8)),
        ("convs.0.bias", (8,)),
        ("convs.1.weight", (21, 3, 8, 16)),
        ("convs.1.bias", (16,)),
        ("hidden.weight", (32, 16)),
        ("hidden.bias", (32,)),
        ("output.weight", (5, 32)),
        ("output.bias", (5,)),
    ],
    "zernet-multiscale": [
        ("blocks.0.convs.0.weight", (21, 3, 3)),
        ("blocks.0.convs.0.bias", (3,)),
        ("blocks.0.convs.1.weight", (21, 3, 3)),
        ("blocks.0.convs.1.bias", (3,)),
        ("blocks.0.convs.2.weight", (21, 3, 2)),
        ("blocks.0.convs.2.bias", (2,)),
        ("blocks.1.convs.0.weight", (21, 8, 6)),
        ("blocks.1.convs.0.bias", (6,)),
        ("blocks.1.convs.1.weight", (21, 8, 5)),
        ("blocks.1.convs.1.bias", (5,)),
        ("blocks.1.convs.2.weight", (21, 8, 5)),
        ("blocks.1.convs.2.bias", (5,)),
        ("hidden.weight", (32, 16)),
        ("hidden.bias", (32,)),
        ("output.weight", (5, 32)),
        ("output.bias", (5,)),
    ],
}


def test_every_registered_model_is_pinned():
    assert sorted(PINNED) == available_models()


@pytest.mark.parametrize("name", sorted(PINNED))
def test_state_dict_keys_and_shapes_are_unchanged(name):
    model = build_model(name, 3, 5, widths=(8, 16, 32))
    assert [(key, tuple(value.shape)) for key, value in model.state_dict().items()] == PINNED[name]


@pytest.mark.parametrize("name", sorted(PINNED))
def test_directional_order_is_known_before_the_model_is_built(name):
    for options in ({}, {} if name == "feastnet" else {"angular_resolution": 8}):
        model = build_model(name, 3, 5, widths=(8, 16, 32), **options)
        assert model.directional_order == directional_order(name, **options)
    expected = 1 if name == "zernet-directional" else None
    assert build_model(name, 3, 5, widths=(8, 16, 32)).directional_order == expected


def test_same_seed_same_initial_weights():
    for name in sorted(PINNED):
        torch.manual_seed(3)
        first = build_model(name, 3, 5, widths=(8, 16, 32)).state_dict()
        torch.manual_seed(3)
        second = build_model(name, 3, 5, widths=(8, 16, 32)).state_dict()
        assert all(torch.equal(first[key], second[key]) for key in first)
