"""Zernike convolution cost: harmonic form vs rotated kernels (the paper's Table 5 settings).

For s = 1, 4, 8, 16 on a 6,890-vertex surface (k = 21), in one run:

* the three convolution layers of the single-scale model (3->64, 64->128, 128->256), forward+backward,
  with the harmonic form (``ZernikeConv``) and with ``s`` rotated kernels (``RotatedKernelConv``), including
  the operator's sparse decomposition, and the dense contraction alone;
* the contraction's FLOP rate against this machine's own ``torch.mm`` rate for the same sizes;
* one training step (forward, cross-entropy over 6,890 classes, backward, Adam) of the whole single-scale
  correspondence model ``Conv64 -> Conv128 -> Conv256 -> Lin512 -> Lin6890``, in float32 and with the
  linear layers in bfloat16 (``train.precision: bfloat16``).

Timing: all configurations of one kind (layers, or whole-model steps) are built in one child process and
timed round by round, interleaved, so that load from other processes on the machine spreads over all of them
and the ratios between them hold; the tables give medians over rounds. Peak memory: one child process per
configuration runs its workload twice and reports the growth of its peak resident set (``ru_maxrss``) over
the resident set after setup (inputs, operator, parameters), so the number is what the computation itself
adds. With ``--real`` the operator is the real ``PatchOperator`` of the 6,880-vertex mannequin of
``bench_operator``, otherwise a random sparse stand-in with 57 non-zeros per row (the measured density of
the real one).

Usage::

    .venv/bin/python -m benchmarks.speed.bench_layers           # writes benchmarks/speed/results/bench_layers.json
    .venv/bin/python -m benchmarks.speed.bench_layers --quick   # fewer repetitions
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

from benchmarks.harness import REPO, SPEED_RESULTS, add_out, add_threads, arguments, result_file, write_json

N_VERTICES = 6890
K = 21
LAYERS = [(3, 64), (64, 128), (128, 256)]
ANGLES = (1, 4, 8, 16)
THREADS = [None]


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _median(values: list[float]) -> float:
    values = sorted(values)
    return values[len(values) // 2]


def _operator(real: bool):
    import torch  # noqa: F401

    if real:
        from benchmarks.speed.bench_operator import mannequin  # the 6,880-vertex body stand-in at area 15000
        from zernet.operators import PatchConfig, build_patch_operator

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


def layer_workload(op, s: int, impl: str) -> dict:
    """Closures for the three convolution layers at ``s``: whole layers, contraction alone, contraction +
    pooling (one closure per layer each), and the contraction's useful FLOPs per layer."""
    import torch

    from zernet.nn import RotatedKernelConv, ZernikeConv
    from zernet.nn.conv import harmonic_contraction, harmonic_plan
    from zernet.nn.reference import rotated_kernel_responses

    n = op.n_vertices
    cls = ZernikeConv if impl == "harmonic" else RotatedKernelConv
    layers = [cls(a, b, angular_resolution=s, pooling="max") for a, b in LAYERS]
    xs = [torch.randn(n, a, requires_grad=True) for a, _ in LAYERS]
    Fs = [op.apply(x.detach()).detach().requires_grad_() for x in xs]
    grads = [torch.randn(n, b) for _, b in LAYERS]
    plan = harmonic_plan(5, s)
    slabs = [torch.randn(2 * plan.degree + 1, n, b) for _, b in LAYERS]
    responses = [torch.randn(n, s, b) for _, b in LAYERS]  # rotated_kernel_responses: (N, s, C_out)

    def layer_step(i):
        layers[i](xs[i], op).backward(grads[i])

    def pooled_step(i):  # dense contraction + angular max pooling
        layers[i]._pooled_response(Fs[i]).backward(grads[i])

    def contraction_step(i):  # the dense products alone, no pooling
        if impl == "reference":
            rotated_kernel_responses(Fs[i], layers[i].weight, s).backward(responses[i])
        elif s == 1:
            (Fs[i].reshape(n, -1) @ layers[i].weight.reshape(-1, LAYERS[i][1])).backward(grads[i])
        else:
            harmonic_contraction(Fs[i], layers[i].weight, plan).backward(slabs[i])

    if impl == "harmonic":
        flops = [_plan_flops(s, a, b, n) for a, b in LAYERS]
    else:
        flops = [3 * 2.0 * n * K * a * b * s for a, b in LAYERS]
    return {
        "layer": [lambda i=i: layer_step(i) for i in range(3)],
        "contraction": [lambda i=i: contraction_step(i) for i in range(3)],
        "pooled": [lambda i=i: pooled_step(i) for i in range(3)],
        "flops": flops,
    }


def torch_mm_workload(n: int) -> list:
    """torch's own matmul for the same sizes as each layer: forward X W, backward dY W^T and X^T dY."""
    import torch

    closures = []
    for a, b in LAYERS:
        X, W, dY = torch.randn(n, K * a), torch.randn(K * a, b), torch.randn(n, b)

        def mm3(X=X, W=W, dY=dY):
            X @ W
            dY @ W.t()
            X.t() @ dY

        closures.append(mm3)
    return closures


def model_workload(op, s: int, impl: str):
    """One training step (forward, cross-entropy over N classes, backward, Adam) of the single-scale model.

    ``impl``: ``harmonic`` (ZernikeConv), ``reference`` (rotated kernels) or ``harmonic-bf16`` (ZernikeConv,
    linear layers in bfloat16 under ``torch.autocast``, as ``train.precision: bfloat16`` trains)."""
    import torch

    from zernet.inference import precision_autocast
    from zernet.nn import Geometry, RotatedKernelConv, build_model

    n = op.n_vertices
    model = build_model("zernet", 3, n, widths=(64, 128, 256, 512), angular_resolution=s)
    precision = "bfloat16" if impl == "harmonic-bf16" else "float32"
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

    def step():
        opt.zero_grad(set_to_none=True)
        with precision_autocast(precision, x.device.type):
            output = model(x, geometry)
        torch.nn.functional.cross_entropy(output.float(), y).backward()
        opt.step()

    return step


def _setup(real: bool):
    import warnings

    import torch

    from zernet.inference import keep_freed_memory

    warnings.filterwarnings("ignore")
    keep_freed_memory()  # as the zernet command does
    torch.manual_seed(0)
    op = _operator(real)
    op.apply(torch.zeros(op.n_vertices, 3))  # build the lazy operator tensors before measuring anything
    return op


def time_all(kind: str, configs: list[tuple[int, str]], repeats: int, real: bool) -> list[dict]:
    """Time every configuration in this process, round by round (configurations interleaved, so that load
    from other processes spreads over all of them and the ratios stay comparable); medians over rounds."""
    op = _setup(real)
    n = op.n_vertices
    if kind == "layers":
        work = {c: layer_workload(op, *c) for c in configs}
        closures = {
            (c, part, i): fn
            for c, w in work.items()
            for part in ("layer", "contraction", "pooled")
            for i, fn in enumerate(w[part])
        }
        closures.update({("mm", "mm", i): fn for i, fn in enumerate(torch_mm_workload(n))})
    else:
        closures = {(c, "step", 0): model_workload(op, *c) for c in configs}
    for fn in closures.values():  # warm-up: allocator, caches, Adam state
        fn()
    times = {key: [] for key in closures}
    for _ in range(repeats):
        for key, fn in closures.items():
            t0 = time.perf_counter()
            fn()
            times[key].append(time.perf_counter() - t0)
    med = {key: _median(v) for key, v in times.items()}
    rows = []
    for c in configs:
        s, impl = c
        row = {"kind": kind, "s": s, "impl": impl, "n_vertices": n}
        if kind == "layers":
            flops = work[c]["flops"]
            mm_flops = [3 * 2.0 * n * K * a * b for a, b in LAYERS]
            row["layer_s"] = [med[(c, "layer", i)] for i in range(3)]
            row["contraction_s"] = [med[(c, "contraction", i)] for i in range(3)]
            row["pooled_s"] = [med[(c, "pooled", i)] for i in range(3)]
            row["layers_total_s"] = sum(row["layer_s"])
            row["contraction_total_s"] = sum(row["contraction_s"])
            row["pooled_total_s"] = sum(row["pooled_s"])
            row["contraction_gflops"] = [f / t / 1e9 for f, t in zip(flops, row["contraction_s"])]
            row["torch_mm_gflops"] = [f / med[("mm", "mm", i)] / 1e9 for i, f in enumerate(mm_flops)]
        else:
            row["step_s"] = med[(c, "step", 0)]
            row["output_layer_gflop"] = 3 * 2.0 * n * 512 * n / 1e9
        rows.append(row)
    return rows


def peak_memory(kind: str, s: int, impl: str, real: bool) -> float:
    """Growth of the peak resident set over the resident set after setup, for two rounds of the workload."""
    op = _setup(real)
    if kind == "layers":
        w = layer_workload(op, s, impl)
        fns = w["layer"]
    else:
        fns = [model_workload(op, s, impl)]
    base = _rss_mb()
    peak0 = _peak_mb()
    for _ in range(2):
        for fn in fns:
            fn()
    return max(_peak_mb(), peak0) - base


def _child(args: list[str], real: bool) -> object:
    cmd = [sys.executable, "-m", "benchmarks.speed.bench_layers", "--child", *args] + (["--real"] if real else [])
    if THREADS[0]:
        cmd += ["--threads", str(THREADS[0])]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True, cwd=REPO)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = arguments(__doc__)
    parser.add_argument(
        "--quick", action="store_true", help="3 repetitions instead of 7, s in (1, 16) for the reference model"
    )
    parser.add_argument(
        "--real",
        action="store_true",
        help="use the real PatchOperator of the mannequin body instead of the random operator",
    )
    add_threads(parser)
    add_out(parser, SPEED_RESULTS / "bench_layers")
    parser.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    THREADS[0] = args.threads
    if args.threads:
        __import__("torch").set_num_threads(args.threads)
    if args.child:  # ("time", kind, repeats, "s:impl,...") or ("memory", kind, s, impl)
        mode, kind, a, b = args.child
        if mode == "time":
            configs = [(int(c.split(":")[0]), c.split(":")[1]) for c in b.split(",")]
            print(json.dumps(time_all(kind, configs, int(a), args.real)))
        else:
            print(json.dumps(peak_memory(kind, int(a), b, args.real)))
        return 0
    repeats = 3 if args.quick else 7
    layer_configs = [(s, impl) for s in ANGLES for impl in ("harmonic", "reference")]
    model_angles = (1, 4, 16) if args.quick else ANGLES
    model_configs = [
        (s, impl)
        for s in model_angles
        for impl in ("harmonic", "reference", "harmonic-bf16")
        if not (impl == "reference" and args.quick and s != 4)
    ]
    encode = lambda configs: ",".join(f"{s}:{impl}" for s, impl in configs)  # noqa: E731
    rows = _child(["time", "layers", str(repeats), encode(layer_configs)], args.real)
    print("layers timed", file=sys.stderr)
    rows += _child(["time", "model", str(repeats), encode(model_configs)], args.real)
    print("model steps timed", file=sys.stderr)
    for row in rows:
        row["peak_extra_mb"] = _child(["memory", row["kind"], str(row["s"]), row["impl"]], args.real)
        print(f"memory {row['kind']:6s} s={row['s']:2d} {row['impl']:9s} done", file=sys.stderr)

    def find(kind, s, impl):
        return next((r for r in rows if r["kind"] == kind and r["s"] == s and r["impl"] == impl), None)

    print(
        f"\nZernike convolution, N = {rows[0]['n_vertices']}, k = {K}, forward+backward, median of {repeats} "
        "rounds (configurations interleaved within each round)"
    )
    print(f"load average at start of report: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores\n")
    print("three conv layers (3->64, 64->128, 128->256): whole layers incl. sparse decomposition; the dense")
    print("contraction alone; contraction + angular max pooling; peak = extra RSS")
    print(
        f"{'s':>3} | {'harmonic layers':>15} {'contraction':>11} {'+pooling':>9} {'peak MB':>8} |"
        f" {'rotated layers':>14} {'contraction':>11} {'+pooling':>9} {'peak MB':>8} | {'speed-up':>8}"
    )
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
    print(
        "\ndense contraction FLOP rate (forward + backward, no pooling) vs torch.mm for the same sizes"
        " (GFLOP/s, per layer; target >= 60 %)"
    )
    for s in ANGLES:
        h = find("layers", s, "harmonic")
        pct = [100 * a / b for a, b in zip(h["contraction_gflops"], h["torch_mm_gflops"])]
        print(
            f"s={s:2d}: layer "
            + " ".join(f"{g:6.1f}" for g in h["contraction_gflops"])
            + " | torch.mm "
            + " ".join(f"{g:6.1f}" for g in h["torch_mm_gflops"])
            + " | "
            + " ".join(f"{p:4.0f}%" for p in pct)
        )
    print(f"\nwhole single-scale model Conv64-Conv128-Conv256-Lin512-Lin{N_VERTICES}, one training step (Adam)")
    print(
        f"(the 512->{rows[0]['n_vertices']} output layer alone: {find('model', model_angles[0], 'harmonic')['output_layer_gflop']:.0f} GFLOP per step)"
    )
    for s in model_angles:
        for impl in ("harmonic", "reference", "harmonic-bf16"):
            r = find("model", s, impl)
            if r:
                print(f"s={s:2d} {impl:13s}: {r['step_s']:.2f} s/step, peak +{r['peak_extra_mb']:.0f} MB")
    print(
        "(harmonic-bf16: linear layers in bfloat16 under torch.autocast, convolutions in float32 = "
        "train.precision: bfloat16; accuracy: benchmarks.speed.bench_precision)"
    )
    payload = {
        "n_vertices": rows[0]["n_vertices"],
        "k": K,
        "repeats": repeats,
        "operator": "PatchOperator (mannequin, 6880 vertices)" if args.real else "random sparse, 57 nnz/row",
        "rows": rows,
    }
    write_json(result_file(args.out, ".json"), payload)
    return 0


if __name__ == "__main__":
    sys.exit(main())
