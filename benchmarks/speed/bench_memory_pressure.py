"""Does a FAUST training run survive another program taking memory beside it?

Starts ``zernet train configs/faust_single_scale.yaml`` on real FAUST registrations (``--data``: the folder
holding ``training/registrations/tr_reg_XXX.ply``; ``--scans`` training scans, two validation and one test
scan of other people, one epoch, ``data.residency auto``) and, once the run has chosen its residency and
started its first epoch, a second process that allocates ``--hog-gb`` GB and writes every page of it, then
holds it until the run ends. Reports whether the run finished, the residency ``auto`` chose and why, the
memory available before, the run's peak resident memory, and the epoch time; writes
``benchmarks/speed/results/bench_memory_pressure.json`` (``--out``). The run (and its cache, unless
``--cache-dir``) live under ``--runs`` (outside the repository); nothing of FAUST is written into the
repository.

    .venv/bin/python -m benchmarks.speed.bench_memory_pressure --data ~/data/MPI-FAUST --runs /tmp/pressure
"""

from __future__ import annotations

import re
import select
import subprocess
import sys
import time
from pathlib import Path

import torch

from benchmarks.harness import REPO, SPEED_RESULTS, add_data, add_out, add_threads, arguments, result_file, write_json
from zernet.training.residency import available_memory

CONFIG = REPO / "configs" / "faust_single_scale.yaml"

# The second program: allocate, write every page (untouched pages cost nothing), hold until killed.
HOG = """
import sys, time
import numpy as np
block = np.empty(int(float(sys.argv[1]) * 1e9), dtype=np.uint8)
block.fill(1)
print("held", flush=True)
time.sleep(86400)
"""


def resident_gb(pid: int) -> float:
    """The resident memory of process ``pid`` (GB), 0 once it has ended."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0.0
    match = re.search(r"VmRSS:\s+(\d+) kB", status)
    return int(match.group(1)) * 1024 / 1e9 if match else 0.0


def main() -> None:
    parser = arguments(__doc__)
    add_data(parser, None, "MPI-FAUST folder (training/registrations/tr_reg_XXX.ply)")
    parser.add_argument("--runs", type=Path, required=True, help="folder for the run and its cache (outside the repo)")
    parser.add_argument("--cache-dir", type=Path, default=None, help="operator cache (default: RUNS/cache)")
    parser.add_argument("--scans", type=int, default=20, help="training scans (tr_reg_000 on)")
    parser.add_argument("--hog-gb", type=float, default=8.0, help="memory the second program takes")
    add_threads(parser, default=2)
    add_out(parser, SPEED_RESULTS / "bench_memory_pressure")
    args = parser.parse_args()
    if args.data is None:
        raise SystemExit("--data DIR is required: the MPI-FAUST folder holding training/registrations")

    run_dir = args.runs / "run"
    overrides = [
        f"data.root={args.data}",
        f"data.train_indices=0:{args.scans}",
        "data.val_indices=60:62",
        "data.test_indices=70:71",
        f"train.threads={args.threads}",
        "train.epochs=1",
        "eval.renders=0",
        "eval.refine_rings=[0]",
        "eval.refine_spectral=[0]",
        f"cache_dir={args.cache_dir or args.runs / 'cache'}",
    ]
    command = [sys.executable, "-m", "zernet.cli", "train", str(CONFIG), "--run-dir", str(run_dir)]
    command += ["--overwrite", "--no-progress", "--set", *overrides]
    available_before = available_memory_gb()
    log_path = args.runs / "train.out"
    args.runs.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w") as log:
        train = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, cwd=REPO)
        residency, hog, peak, hog_held_at = None, None, 0.0, None
        started = time.perf_counter()
        while train.poll() is None:
            time.sleep(0.5)
            peak = max(peak, resident_gb(train.pid))
            text = log_path.read_text()
            if residency is None and "data residency:" in text:
                residency = re.search(r"data residency: (.*)", text).group(1)
                hog = subprocess.Popen([sys.executable, "-c", HOG, str(args.hog_gb)], stdout=subprocess.PIPE, text=True)
            if hog is not None and hog_held_at is None and select_ready(hog):
                hog.stdout.readline()
                hog_held_at = time.perf_counter() - started
        if hog is not None:
            hog.kill()
            hog.wait()
    text = log_path.read_text()
    epoch = re.search(r"epoch 1/1, .*?([\d.]+) s", text)
    result = {
        "survived": train.returncode == 0,
        "returncode": train.returncode,
        "hog_gb": args.hog_gb,
        "hog_held_after_s": hog_held_at,
        "residency": residency,
        "available_before_gb": available_before,
        "peak_resident_gb": peak,
        "epoch_s": float(epoch.group(1)) if epoch else None,
        "scans": args.scans,
        "threads": args.threads,
        # The run's last words on its scores (its other lines name folders on this machine).
        "test_line": next((line for line in text.splitlines() if line.startswith("test metrics")), None),
    }
    write_json(result_file(args.out, ".json"), result)
    print(
        f"survived: {result['survived']} (return code {train.returncode}); {args.hog_gb:.0f} GB taken beside it "
        f"{'' if hog_held_at is None else f'{hog_held_at:.0f} s after the start'}; residency: {residency}; "
        f"available before {available_before:.1f} GB, run's peak resident {peak:.2f} GB; epoch "
        f"{result['epoch_s']} s"
    )


def available_memory_gb() -> float:
    return available_memory(torch.device("cpu")) / 1e9


def select_ready(process) -> bool:
    """Whether the process has written its line (without blocking)."""
    ready, _, _ = select.select([process.stdout], [], [], 0)
    return bool(ready)


if __name__ == "__main__":
    main()
