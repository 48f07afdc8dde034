"""Start-up time of the ``zernet`` command against ``import torch`` (issue 34): medians of repeated runs.

    .venv/bin/python -m benchmarks.speed.bench_startup [--repeats 5]   # writes benchmarks/speed/results/bench_startup.json

Each command runs in a fresh interpreter, alternating with the reference so that a busy machine slows both
alike; wall time and the child's CPU time (user + system, less sensitive to other jobs on a shared machine)
are both reported. The target is ``zernet --help`` <= 1.5x ``python -c "import torch"``.
"""

from __future__ import annotations

import resource
import statistics
import subprocess
import sys
import time

from benchmarks.harness import SPEED_RESULTS, add_out, arguments, result_file, write_json

COMMANDS = {
    "import torch": [sys.executable, "-c", "import torch"],
    "zernet --help": [sys.executable, "-m", "zernet.cli", "--help"],
    "zernet predict --help": [sys.executable, "-m", "zernet.cli", "predict", "--help"],
}


def run_once(command: list[str]) -> tuple[float, float]:
    """(wall seconds, CPU seconds of the child) of one run."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return seconds, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    parser = arguments(__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    add_out(parser, SPEED_RESULTS / "bench_startup")
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
    result = {"median_wall_s": wall, "median_cpu_s": cpu, "wall_s": walls, "cpu_s": cpus}
    write_json(result_file(args.out, ".json"), result)


if __name__ == "__main__":
    main()
