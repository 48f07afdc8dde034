"""The preprocessing worker pool: processes started safely, bounded work in flight, survival of a dead worker.

:func:`run_jobs` runs ``work(job)`` for every job — in this process (``workers`` 0 or 1) or in a process pool
with at most ``max_in_flight`` jobs submitted at once, so memory stays at a few shapes per worker. ``work``
returns ``(name, error or None)``. If the pool breaks (a worker killed, e.g. by the out-of-memory killer, or
crashed in native code), each remaining job runs in its own one-worker pool (:func:`run_isolated`), so the job
that kills its worker is reported by name (:data:`WORKER_DIED`) and the others go on.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import sys
import warnings
from collections.abc import Callable, Mapping
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import torch

__all__ = ["WORKER_DIED", "pool_context", "worker_init", "run_pool", "run_isolated", "run_jobs"]

logger = logging.getLogger(__name__)

#: Reason recorded for a shape whose worker process died while working on it.
WORKER_DIED = (
    "the worker process died while preprocessing this shape (killed, e.g. by the out-of-memory "
    "killer, or crashed in native code)"
)

#: What a job does: ``work(job) -> (name, error message or None)``; module level, so workers can unpickle it.
Work = Callable[[Any], tuple[str, str | None]]
#: Called once per finished job with its name and error (None: success).
Record = Callable[[str, str | None], None]


def worker_init() -> None:
    """Initialiser of every pool worker."""
    # Several workers share few cores: one thread each avoids oversubscription.
    torch.set_num_threads(1)
    # A warning in a worker (e.g. unused vertices) prints as one line, without the source line that would
    # read like a crash, as the command line does in the main process.
    warnings.showwarning = _one_line_warning


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    text = "; ".join(part.strip() for part in str(message).splitlines() if part.strip())
    print(f"warning: {text}", file=file or sys.stderr)


def pool_context():
    """Start method for the worker pool.

    forkserver (or spawn) starts workers from a fresh interpreter, never a fork of a process that may
    already run torch/OpenMP threads. Both re-import the main script in each worker, which is impossible
    when the main module is not a real file (``python - < script``); fork is used there.
    """
    methods = multiprocessing.get_all_start_methods()
    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    if main_file is not None and not os.path.isfile(main_file) and "fork" in methods:
        return multiprocessing.get_context("fork")
    if "forkserver" not in methods:
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    # The fork server imports torch and zernet once; every worker forked from it starts with them loaded
    # instead of spending seconds importing them itself (which dominated the time for small shapes).
    context.set_forkserver_preload(["zernet.data.preprocess"])
    return context


def run_pool(work: Work, jobs: Mapping[str, Any], workers: int, max_in_flight: int, record: Record) -> set[str]:
    """Run ``jobs`` ({name: job}) in a process pool with at most ``max_in_flight`` submitted at once;
    returns the names finished (all of them unless the pool broke)."""
    finished: set[str] = set()

    def collect(futures) -> None:
        for future in futures:
            name, error = future.result()
            finished.add(name)
            record(name, error)

    try:
        with ProcessPoolExecutor(workers, mp_context=pool_context(), initializer=worker_init) as pool:
            running: set = set()
            for job in jobs.values():
                running.add(pool.submit(work, job))
                if len(running) >= max_in_flight:
                    done, running = wait(running, return_when=FIRST_COMPLETED)
                    collect(done)
            collect(running)
    except BrokenProcessPool as error:
        logger.warning("preprocessing pool broke: %s", error)
    return finished


def run_isolated(work: Work, name: str, job) -> tuple[str, str | None] | None:
    """Run one job in a fresh one-worker pool; (name, WORKER_DIED) if that worker dies, None if no pool starts."""
    try:
        with ProcessPoolExecutor(1, mp_context=pool_context(), initializer=worker_init) as pool:
            return pool.submit(work, job).result()
    except BrokenProcessPool:
        return name, WORKER_DIED
    except OSError:  # no processes can be started here at all
        return None


def run_jobs(work: Work, jobs: Mapping[str, Any], workers: int, max_in_flight: int, record: Record) -> None:
    """Run every job once, in this process (``workers`` <= 1) or in a pool; see the module docstring."""
    if workers <= 1:
        for job in jobs.values():
            record(*work(job))
        return
    done_names = run_pool(work, jobs, workers, max_in_flight, record)
    leftover = {name: job for name, job in jobs.items() if name not in done_names}
    if not leftover:
        return
    # The pool broke: a worker was killed (e.g. out of memory) or crashed, or workers cannot start here.
    # Each remaining job then runs in its own one-worker pool, so a job that kills its worker is reported by
    # name instead of taking this process down when retried here. Only if no worker ever finished a job (a
    # start-up problem) are the jobs run in this process.
    warnings.warn(
        f"preprocessing worker pool failed; processing the remaining {len(leftover)} shapes "
        "one at a time in fresh worker processes",
        RuntimeWarning,
        stacklevel=3,
    )
    outcomes = {name: run_isolated(work, name, job) for name, job in leftover.items()}
    workers_work = bool(done_names) or any(o is not None and o[1] != WORKER_DIED for o in outcomes.values())
    for name, outcome in outcomes.items():
        if outcome is None or (outcome[1] == WORKER_DIED and not workers_work):
            outcome = work(leftover[name])
        record(*outcome)
