"""The simulator's forked worker map: order, a shared object that cannot be pickled, errors."""

import os
import threading

import pytest

from vlsforest.sim.workers import WorkerDied, fork_map


class _Unpicklable:
    """Holds a lock (pickling it raises) and a value the workers read."""

    def __init__(self, value):
        self.lock = threading.Lock()
        self.value = value


def _scaled(shared, item):
    return (item * shared.value, os.getpid())


def _fails_on_five(shared, item):
    if item == 5:
        raise ValueError(f"item {item} is bad")
    return item


def _dies_on_three(shared, item):
    if item == 3:
        os._exit(7)
    return item


def test_results_come_in_item_order_from_several_processes():
    shared = _Unpicklable(3)
    out = list(fork_map(_scaled, shared, range(40), 3))
    assert [r[0] for r in out] == [3 * i for i in range(40)]
    assert os.getpid() not in {r[1] for r in out}


def test_an_error_in_a_worker_is_raised_in_the_parent():
    it = fork_map(_fails_on_five, None, range(10), 2)
    assert [next(it) for _ in range(5)] == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="item 5 is bad"):
        next(it)


def test_a_worker_that_dies_is_reported():
    with pytest.raises(WorkerDied, match="exit code 7"):
        list(fork_map(_dies_on_three, None, range(8), 2))


def test_no_items_no_results():
    assert list(fork_map(_scaled, _Unpicklable(1), range(0), 2)) == []
