"""Running compiled kernels that release the GIL (``numba.njit(nogil=True)``, numpy's linear algebra) on
several threads: the cores available to this process and an order-keeping map over them."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor

__all__ = ["available_cores", "thread_map"]


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
