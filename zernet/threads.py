"""Running compiled kernels that release the GIL (``numba.njit(nogil=True)``, numpy's linear algebra) on
several threads: the cores available to this process, an order-keeping map over them, and a one-ahead
prefetch of work items (reading cached operators while the previous training step computes)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor

__all__ = ["available_cores", "thread_map", "prefetched"]


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the platform tells it)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def thread_map(function: Callable, items: Iterable, n_threads: int | None = None) -> list:
    """``[function(item) for item in items]``, on ``n_threads`` threads (``None``: :func:`available_cores`).

    Only worth it when ``function`` spends its time without the GIL; runs in this thread when there is
    one thread or one item.
    """
    items = list(items)
    n_threads = available_cores() if n_threads is None else n_threads
    if n_threads <= 1 or len(items) <= 1:
        return [function(item) for item in items]
    with ThreadPoolExecutor(max_workers=min(n_threads, len(items))) as pool:
        return list(pool.map(function, items))


def prefetched(function: Callable, items: Iterable) -> Iterator:
    """``function(item)`` for each item in order, the next one computed on a background thread while the
    caller works on the current one.

    For loading: reading and checking a cached FAUST-sized operator takes seconds, mostly in file reads,
    checksums and numpy copies that release the GIL, so it overlaps a training step. An exception raised by
    ``function`` reaches the caller at the item it belongs to.
    """
    items = list(items)
    if not items:
        return
    with ThreadPoolExecutor(max_workers=1) as pool:
        upcoming = pool.submit(function, items[0])
        for following in items[1:]:
            result = upcoming.result()
            upcoming = pool.submit(function, following)
            yield result
        yield upcoming.result()
