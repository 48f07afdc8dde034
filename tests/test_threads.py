"""zernet.threads: the order-keeping map is the plain list comprehension, on any number of threads; the
prefetch keeps the order and hands errors back at their item."""

import threading

import pytest

from zernet.threads import available_cores, prefetched, thread_map


def test_available_cores_is_positive():
    assert available_cores() >= 1


def test_thread_map_keeps_the_order_of_the_items():
    items = list(range(50))
    for n_threads in (None, 1, 2, 8):
        assert thread_map(lambda x: x * x, items, n_threads) == [x * x for x in items]


def test_one_thread_runs_in_the_calling_thread():
    caller = threading.get_ident()
    assert thread_map(lambda _: threading.get_ident(), range(3), 1) == [caller] * 3
    assert thread_map(lambda _: threading.get_ident(), [0], 4) == [caller]


def test_prefetched_yields_every_result_in_order_and_works_one_item_ahead():
    caller = threading.get_ident()
    third_started = threading.Event()

    def work(x):
        assert threading.get_ident() != caller  # on the background thread
        if x == 2:
            third_started.set()
        return 10 * x

    results = prefetched(work, range(5))
    assert next(results) == 0
    assert next(results) == 10
    assert third_started.wait(timeout=10)  # under way before the caller asks for it
    assert list(results) == [20, 30, 40]
    assert list(prefetched(work, [])) == []


def test_prefetched_raises_at_the_failing_item():
    def work(x):
        if x == 2:
            raise ValueError("bad item 2")
        return x

    results = prefetched(work, range(4))
    assert [next(results), next(results)] == [0, 1]
    with pytest.raises(ValueError, match="bad item 2"):
        next(results)
