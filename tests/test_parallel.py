"""Work run side by side (:mod:`autoalign.runtime.parallel`): in order, at once, drjit's pool shared
out and given back, the first error raised and nothing more started after it."""

from __future__ import annotations

import threading
import time

import pytest

from autoalign.runtime.backend import drjit
from autoalign.runtime.parallel import side_by_side


def test_items_run_two_at_once_and_come_back_in_order(pool_of_two):
    both = threading.Barrier(2, timeout=10)  # broken unless two items run at the same time
    seen_pool = []

    def work(k: int) -> int:
        if k < 2:
            both.wait()
        seen_pool.append(drjit().thread_count())
        return 10 * k

    assert side_by_side(work, range(6)) == [0, 10, 20, 30, 40, 50]
    assert set(seen_pool) == {1}  # each of the two renders on one of the pool's two threads
    assert drjit().thread_count() == 2  # and the pool is whole again after


def test_the_first_error_is_raised_and_no_item_after_it_starts(pool_of_two):
    started = []
    release = threading.Event()

    def work(k: int) -> int:
        started.append(k)
        if k == 0:
            release.wait(10)  # the first item is still running when the second fails
        if k == 1:
            release.set()
            raise ValueError("item 1 failed")
        time.sleep(0.5)  # an item takes a while, as an instance's refinement does
        return k

    with pytest.raises(ValueError, match="item 1 failed"):
        side_by_side(work, range(20))
    # item 1's thread may take the next item before the failure is seen, but nothing after that
    assert set(started) <= {0, 1, 2} and {0, 1} <= set(started), started
    assert drjit().thread_count() == 2


def test_called_from_an_item_it_runs_one_after_the_other(pool_of_two):
    def inner(k: int) -> tuple[int, int]:
        return k, threading.get_ident()

    both = threading.Barrier(2, timeout=10)  # broken unless the two items run at the same time

    def outer(k: int) -> tuple[int, list[tuple[int, int]]]:
        both.wait()
        return threading.get_ident(), side_by_side(inner, [k, k + 1])

    done = side_by_side(outer, [0, 10])
    assert [[k for k, _ in ran] for _, ran in done] == [[0, 1], [10, 11]]
    assert all(t == mine for mine, ran in done for _, t in ran)  # in the item's own thread
    assert done[0][0] != done[1][0]


def test_with_a_pool_of_one_the_items_run_in_the_calling_thread():
    me = threading.get_ident()
    assert drjit().thread_count() >= 1
    dr = drjit()
    before = dr.thread_count()
    dr.set_thread_count(1)
    try:
        assert side_by_side(lambda k: (k, threading.get_ident() == me), range(3)) == [(0, True), (1, True), (2, True)]
    finally:
        dr.set_thread_count(before)


def test_rendering_on_the_gpu_the_items_run_in_the_calling_thread(pool_of_two, monkeypatch):
    # drjit's CUDA backend refuses a variable made on one thread and used on another (seen on an H200:
    # the joint stage's depth casts failed with "jitc_assemble(): ... split across a parent/child thread")
    me = threading.get_ident()
    monkeypatch.setenv("AUTOALIGN_DEVICE", "cuda")
    assert side_by_side(lambda k: (k, threading.get_ident() == me), range(3)) == [(0, True), (1, True), (2, True)]
    monkeypatch.setenv("AUTOALIGN_DEVICE", "cpu")
    both = threading.Barrier(2, timeout=10)  # on the CPU, two at once again
    assert side_by_side(lambda k: both.wait() if k < 2 else k, range(3))[2] == 2
