"""zernet.threads: the order-keeping map is the plain list comprehension, on any number of threads."""

import threading

from zernet.threads import available_cores, thread_map


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
