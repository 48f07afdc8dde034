"""Zernike convolution cost: harmonic form vs rotated kernels (the paper's Table 5 settings).

For s = 1, 4, 8, 16 on a 6,890-vertex surface (k = 21), in one run:

* the three convolution layers of the single-scale model (3->64, 64->128, 128->256), forward+backward,
  with the harmonic form (``ZernikeConv``) and with ``s`` rotated kernels (``RotatedKernelConv``), including
  the operator's sparse decomposition, and the dense contraction alone;
* the contraction's FLOP rate against this machine's own ``torch.mm`` rate for the same sizes;
* one training step (forward, cross-entropy over 6,890 classes, backward, Adam) of the whole single-scale
  correspondence model ``Conv64 -> Conv128 -> Conv256 -> Lin512 -> Lin6890``.

Peak memory: every configuration runs in its own subprocess and reports the growth of its peak resident set
(``ru_maxrss``) over the resident set after setup (inputs, operator, parameters), so the number is what the
computation itself adds. With ``--real`` the operator is the real ``PatchOperator`` of the 6,880-vertex
mannequin of ``bench_operator.py``, otherwise a random sparse stand-in with 57 non-zeros
per row (the measured density of the real one, ../shared/GUIDE.md section 5).

Usage::

    python benchmarks/bench_layers.py            # full run, writes benchmarks/results/bench_layers.json
    python benchmarks/bench_layers.py --quick    # fewer repetitions
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

N_VERTICES = 6890
K = 21
LAYERS = [(3, 64), (64, 128), (128, 256)]
ANGLES = (1, 4, 8, 16)
THREADS = [None]
RESULTS = Path(__file__).resolve().parent / "results" / "bench_layers.json"


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _timeit(fn, repeats: int) -> float:
    fn()  # warm-up (allocator, caches, lazy operator tensors)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    times.sort()
    return times[len(times) // 2]


def _operator(real: bool):
    import torch  # noqa: F401

    if real:
        from zernet.patches import PatchConfig, build_patch_operator

        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_operator import mannequin  # the 6,880-vertex body stand-in at area 15000

        return build_patch_operator(mannequin(), PatchConfig(r0=5.5, n_samples=12000, patch_size=50, n_max=5))
    from zernet.nn.reference import MatrixOperator

    return MatrixOperator.random(N_VERTICES, K, nnz_per_row=57, seed=0)


def _plan_flops(s: int | None, c_in: int, c_out: int, n: int) -> float:
    """Dense multiply-add FLOPs of the harmonic contraction, forward + backward (3 products)."""
    from zernet.nn.conv import harmonic_plan

    if s == 1:
        units = K
    else:
        p = harmonic_plan(5, s)
        units = sum((b - a) * (2 if (f > 0 and p.has_sin[f]) else 1) for f, (a, b) in enumerate(p.groups))
    return 3 * 2.0 * n * units * c_in * c_out


def run_config(kind: str, s: int, impl: str, repeats: int, real: bool) -> dict:
    """One configuration, in this process. kind: 'layers' | 'model'."""
    import torch
    import warnings

    warnings.filterwarnings("ignore")
    from zernet.nn import Geometry, RotatedKernelConv, ZernikeConv, build_model
    from zernet.nn.conv import harmonic_contraction, harmonic_plan
    from zernet.nn.reference import rotated_kernel_responses
    from zernet.train import keep_freed_memory

    keep_freed_memory()  # as the zernet command does

    torch.manual_seed(0)
    op = _operator(real)
    n = op.n_vertices
    result = {"kind": kind, "s": s, "impl": impl, "n_vertices": n}
    if kind == "layers":
        cls = ZernikeConv if impl == "harmonic" else RotatedKernelConv
        layers = [cls(a, b, angular_resolution=s, pooling="max") for a, b in LAYERS]
        xs = [torch.randn(n, a, requires_grad=True) for a, _ in LAYERS]
        Fs = [op.apply(x.detach()).detach().requires_grad_() for x in xs]
        grads = [torch.randn(n, b) for _, b in LAYERS]
        op.apply(xs[0])  # build lazy operator tensors before measuring memory
        base = _rss_mb()
        peak0 = _peak_mb()

        def layer_step(i):
            out = layers[i](xs[i], op)
            out.backward(grads[i])

        def pooled_step(i):  # dense contraction + angular max pooling
            out = layers[i]._pooled_response(Fs[i])
            out.backward(grads[i])

        plan = harmonic_plan(5, s)
        slabs = [torch.randn(2 * plan.degree + 1, n, b) for _, b in LAYERS]
        responses = [torch.randn(n, s, b) for _, b in LAYERS]  # rotated_kernel_responses: (N, s, C_out)

        def contraction_step(i):  # the dense products alone, no pooling
            if impl == "reference":
                rotated_kernel_responses(Fs[i], layers[i].weight, s).backward(responses[i])
            elif s == 1:
                (Fs[i].reshape(n, -1) @ layers[i].weight.reshape(-1, LAYERS[i][1])).backward(grads[i])
            else:
                harmonic_contraction(Fs[i], layers[i].weight, plan).backward(slabs[i])

        per_layer = [_timeit(lambda i=i: layer_step(i), repeats) for i in range(3)]
        per_contraction = [_timeit(lambda i=i: contraction_step(i), repeats) for i in range(3)]
        per_pooled = [_timeit(lambda i=i: pooled_step(i), repeats) for i in range(3)]
        result["layer_s"] = per_layer
        result["pooled_s"] = per_pooled
        result["pooled_total_s"] = sum(per_pooled)
        result["layers_total_s"] = sum(per_layer)
        result["contraction_s"] = per_contraction
        result["contraction_total_s"] = sum(per_contraction)
        if impl == "harmonic":
            flops = [_plan_flops(s, a, b, n) for a, b in LAYERS]
        else:
            flops = [3 * 2.0 * n * K * a * b * s for a, b in LAYERS]
        result["contraction_gflops"] = [f / t / 1e9 for f, t in zip(flops, per_contraction)]
        # torch's own matmul rate for the same sizes: forward X W, backward dY W^T and X^T dY
        mm_rates = []
        for (a, b) in LAYERS:
            X = torch.randn(n, K * a)
            W = torch.randn(K * a, b)
            dY = torch.randn(n, b)

            def mm3():
                X @ W
                dY @ W.t()
                X.t() @ dY

            mm_rates.append(3 * 2.0 * n * K * a * b / _timeit(mm3, repeats) / 1e9)
        result["torch_mm_gflops"] = mm_rates
        result["peak_extra_mb"] = max(_peak_mb(), peak0) - base
    else:
        model = build_model("zernet", 3, n, widths=(64, 128, 256, 512), angular_resolution=s)
        if impl == "reference":
            for block in model.blocks:
                conv = block.convs[0]
                ref = RotatedKernelConv(conv.in_channels, conv.out_channels, angular_resolution=s)
                ref.load_state_dict(conv.state_dict())
                block.convs[0] = ref
        geometry = Geometry([op])
        x = torch.randn(n, 3)
        y = torch.randperm(n)
        opt = torch.optim.Adam(model.parameters(), lr=1e-3)
        op.apply(x)
        base = _rss_mb()

        def step():
            opt.zero_grad(set_to_none=True)
            loss = torch.nn.functional.cross_entropy(model(x, geometry), y)
            loss.backward()
            opt.step()

        step()  # Adam state allocated: part of the model's steady-state footprint
        result["step_s"] = _timeit(step, repeats)
        result["peak_extra_mb"] = _peak_mb() - base
        out_layer = 3 * 2.0 * n * 512 * n
        result["output_layer_gflop"] = out_layer / 1e9
    return result


def _subprocess(kind, s, impl, repeats, real) -> dict:
    cmd = [sys.executable, __file__, "--child", kind, str(s), impl, str(repeats)] + (["--real"] if real else [])
    if THREADS[0]:
        cmd += ["--threads", str(THREADS[0])]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="3 repetitions instead of 7, s in (1, 16) for the reference model")
    parser.add_argument("--real", action="store_true", help="use the real PatchOperator of the mannequin body instead of the random operator")
    parser.add_argument("--threads", type=int, default=None, help="torch threads per configuration (default: torch's)")
    parser.add_argument("--output", type=Path, default=RESULTS)
    parser.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    THREADS[0] = args.threads
    if args.threads:
        __import__("torch").set_num_threads(args.threads)
    if args.child:
        kind, s, impl, repeats = args.child
        print(json.dumps(run_config(kind, int(s), impl, int(repeats), args.real)))
        return 0
    repeats = 3 if args.quick else 7
    rows = []
    for s in ANGLES:
        for impl in ("harmonic", "reference"):
            rows.append(_subprocess("layers", s, impl, repeats, args.real))
            print(f"layers s={s:2d} {impl:9s} done", file=sys.stderr)
    model_angles = (1, 4, 16) if args.quick else ANGLES
    for s in model_angles:
        for impl in ("harmonic", "reference"):
            if impl == "reference" and args.quick and s != 4:
                continue
            rows.append(_subprocess("model", s, impl, max(2, repeats // 2), args.real))
            print(f"model  s={s:2d} {impl:9s} done", file=sys.stderr)

    def find(kind, s, impl):
        return next((r for r in rows if r["kind"] == kind and r["s"] == s and r["impl"] == impl), None)

    print(f"\nZernike convolution, N = {rows[0]['n_vertices']}, k = {K}, forward+backward, median of {repeats}")
    print(f"load average at start of report: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores\n")
    print("three conv layers (3->64, 64->128, 128->256): whole layers incl. sparse decomposition; the dense")
    print("contraction alone; contraction + angular max pooling; peak = extra RSS")
    print(f"{'s':>3} | {'harmonic layers':>15} {'contraction':>11} {'+pooling':>9} {'peak MB':>8} |"
          f" {'rotated layers':>14} {'contraction':>11} {'+pooling':>9} {'peak MB':>8} | {'speed-up':>8}")
    h1 = find("layers", 1, "harmonic")
    for s in ANGLES:
        h, r = find("layers", s, "harmonic"), find("layers", s, "reference")
        print(
            f"{s:3d} | {h['layers_total_s'] * 1e3:13.0f}ms {h['contraction_total_s'] * 1e3:9.0f}ms"
            f" {h['pooled_total_s'] * 1e3:7.0f}ms {h['peak_extra_mb']:8.0f} |"
            f" {r['layers_total_s'] * 1e3:12.0f}ms {r['contraction_total_s'] * 1e3:9.0f}ms"
            f" {r['pooled_total_s'] * 1e3:7.0f}ms {r['peak_extra_mb']:8.0f} |"
            f" {r['layers_total_s'] / h['layers_total_s']:7.1f}x"
        )
    h16 = find("layers", 16, "harmonic")
    r1, r16 = find("layers", 1, "reference"), find("layers", 16, "reference")
    print(
        f"\nratio s=16 / s=1: harmonic layers {h16['layers_total_s'] / h1['layers_total_s']:.2f}x (target <= 2.0),"
        f" contraction {h16['contraction_total_s'] / h1['contraction_total_s']:.2f}x,"
        f" contraction + pooling {h16['pooled_total_s'] / h1['pooled_total_s']:.2f}x;"
        f" rotated kernels {r16['layers_total_s'] / r1['layers_total_s']:.1f}x"
    )
    print("\ndense contraction FLOP rate (forward + backward, no pooling) vs torch.mm for the same sizes"
          " (GFLOP/s, per layer; target >= 60 %)")
    for s in ANGLES:
        h = find("layers", s, "harmonic")
        pct = [100 * a / b for a, b in zip(h["contraction_gflops"], h["torch_mm_gflops"])]
        print(
            f"s={s:2d}: layer " + " ".join(f"{g:6.1f}" for g in h["contraction_gflops"])
            + " | torch.mm " + " ".join(f"{g:6.1f}" for g in h["torch_mm_gflops"])
            + " | " + " ".join(f"{p:4.0f}%" for p in pct)
        )
    print(f"\nwhole single-scale model Conv64-Conv128-Conv256-Lin512-Lin{N_VERTICES}, one training step (Adam)")
    print(f"(the 512->{rows[0]['n_vertices']} output layer alone: {find('model', model_angles[0], 'harmonic')['output_layer_gflop']:.0f} GFLOP per step)")
    for s in model_angles:
        for impl in ("harmonic", "reference"):
            r = find("model", s, impl)
            if r:
                print(f"s={s:2d} {impl:9s}: {r['step_s']:.2f} s/step, peak +{r['peak_extra_mb']:.0f} MB")
    payload = {
        "n_vertices": rows[0]["n_vertices"],
        "k": K,
        "repeats": repeats,
        "operator": "PatchOperator (mannequin, 6880 vertices)" if args.real else "random sparse, 57 nnz/row",
        "torch_threads": int(__import__("torch").get_num_threads()),
        "load_average_1min": os.getloadavg()[0],
        "machine": platform.processor() or platform.machine(),
        "rows": rows,
    }
    payload["command"] = " ".join([Path(sys.executable).name, "benchmarks/bench_layers.py"] + list(argv or sys.argv[1:]))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.output.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(payload, indent=1))
    os.replace(tmp, args.output)
    print(f"\nwritten {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
