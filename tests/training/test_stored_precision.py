"""A trained run's predictions with its patch operators held in each stored precision
(``benchmarks/speed/bench_stored_precision.py``): the precision is what the checkpoint's patch settings say,
and a half precision gives the same answers as float32 on a task the run has learnt."""

from __future__ import annotations

import numpy as np
from meshes import majority_fraction

from benchmarks.speed.bench_stored_precision import checkpoint_in
from zernet.inference import predict
from zernet.inference.model_file import load_checkpoint
from zernet.operators import PatchOperator


def test_each_stored_precision_predicts_what_float32_does(learnt_sphere_run, labelled_spheres, tmp_path):
    run_dir, _ = learnt_sphere_run
    truth = np.loadtxt(labelled_spheres / "test" / "shape5.txt", dtype=np.int64)
    checkpoint = load_checkpoint(run_dir / "best.pt")
    answers = {}
    for precision in ("float32", "float16", "bfloat16"):
        model_file = checkpoint_in(precision, checkpoint, tmp_path)
        settings = load_checkpoint(model_file)["preprocess"]["patch_configs"]
        assert [config["precision"] for config in settings] == [precision] * len(settings)
        cache = tmp_path / f"cache-{precision}"
        answers[precision] = predict(model_file, labelled_spheres / "test" / "shape5.obj", cache_dir=cache)
        (operator_file,) = cache.glob("*.zop")
        assert PatchOperator.load(operator_file).pairs.precision == precision  # held as the settings say
    assert (answers["float32"] == truth).mean() > majority_fraction(truth) + 0.3  # a run that has learnt
    for precision in ("float16", "bfloat16"):
        assert (answers[precision] == answers["float32"]).mean() >= 0.99
