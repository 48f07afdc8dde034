"""Start-up time of the ``zernet`` command against ``import torch`` (issue 34): medians of repeated runs.

    .venv/bin/python benchmarks/bench_startup.py [--repeats 5]   # writes benchmarks/results/bench_startup.json

Each command runs in a fresh interpreter, alternating with the reference so that a busy machine slows both
alike; wall time and the child's CPU time (user + system, less sensitive to other jobs on a shared machine)
are both reported. The target is ``zernet --help`` <= 1.5x ``python -c "import torch"``.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

COMMANDS = {
    "import torch": [sys.executable, "-c", "import torch"],
    "zernet --help": [sys.executable, "-m", "zernet.cli", "--help"],
    "zernet predict --help": [sys.executable, "-m", "zernet.cli", "predict", "--help"],
}
RESULTS = Path(__file__).resolve().parent / "results" / "bench_startup.json"


def run_once(command: list[str]) -> tuple[float, float]:
    """(wall seconds, CPU seconds of the child) of one run."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return seconds, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default=str(RESULTS), help="write the medians as JSON here (default: %(default)s)")
    args = parser.parse_args()
    walls = {name: [] for name in COMMANDS}
    cpus = {name: [] for name in COMMANDS}
    for command in COMMANDS.values():  # warm the file cache once
        run_once(command)
    for _ in range(args.repeats):
        for name, command in COMMANDS.items():
            seconds, cpu = run_once(command)
            walls[name].append(round(seconds, 3))
            cpus[name].append(round(cpu, 3))
    wall = {name: statistics.median(values) for name, values in walls.items()}
    cpu = {name: statistics.median(values) for name, values in cpus.items()}
    for name in COMMANDS:
        print(
            f"{name:24s} wall {wall[name]:5.2f} s ({wall[name] / wall['import torch']:4.2f}x)   "
            f"cpu {cpu[name]:5.2f} s ({cpu[name] / cpu['import torch']:4.2f}x)   medians of {args.repeats}"
        )
    if args.out:
        Path(args.out).write_text(
            json.dumps({"median_wall_s": wall, "median_cpu_s": cpu, "wall_s": walls, "cpu_s": cpus}, indent=1) + "\n"
        )


if __name__ == "__main__":
    main()
