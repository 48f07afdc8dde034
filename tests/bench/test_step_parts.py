"""The stand-in of ``benchmarks/speed/bench_step_parts.py``: an operator that costs nothing still lets a model
compute the rest of its step (every layer, the head, the loss), so the benchmark times all but the operators."""

import torch
from meshes import icosphere

from benchmarks.speed.bench_step_parts import FreeOperator
from zernet.nn.models import build_model
from zernet.operators import Geometry, PatchConfig, build_patch_operator


def test_the_free_operator_gives_zero_coefficients_and_zero_input_gradients():
    x = torch.randn(12, 5, requires_grad=True)
    coefficients = FreeOperator(12, 21).apply(x, basis_order=tuple(range(21)))
    assert coefficients.shape == (12, 21, 5) and not coefficients.any()
    (coefficients.sum() + 3 * x.sum()).backward()  # only the direct path reaches x
    torch.testing.assert_close(x.grad, torch.full_like(x, 3.0))


def test_a_model_on_free_operators_runs_every_other_part_of_its_step():
    sphere = icosphere(subdivisions=2)
    operator = build_patch_operator(sphere, PatchConfig(r0=0.5, n_samples=800, n_max=3))
    torch.manual_seed(0)
    model = build_model("zernet", 4, 7, widths=(8, 16, 32), n_max=3, input_skip=True)
    x = torch.randn(sphere.n_vertices, 4)
    real = model(x, Geometry([operator]))
    free = model(x, Geometry([FreeOperator(sphere.n_vertices, operator.k)]))
    assert free.shape == real.shape and torch.isfinite(free).all()
    torch.nn.functional.cross_entropy(free, torch.randint(0, 7, (sphere.n_vertices,))).backward()
    # The convolutions' kernels see only zero coefficients; the head and the biases still learn.
    assert model.output.weight.grad.abs().sum() > 0
