"""Builds spread over threads (accel.threads): the thread count, the map, the runs of a
level, and every threaded builder's arrays byte for byte the same on one thread and on
several."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

import accel
import accel.threads as threads


def test_thread_count_from_the_environment(monkeypatch):
    monkeypatch.setenv("JRT_BUILD_THREADS", "3")
    assert threads.build_threads() == 3
    monkeypatch.delenv("JRT_BUILD_THREADS")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert threads.build_threads() == max(1, min(cores, threads.DEFAULT_MAX_THREADS))
    for bad in ("0", "-2", "two", "1.5"):
        monkeypatch.setenv("JRT_BUILD_THREADS", bad)
        with pytest.raises(ValueError,
                           match=rf"JRT_BUILD_THREADS must be a positive integer.*{bad!r}"):
            threads.build_threads()


def test_threads_for_small_passes(monkeypatch):
    monkeypatch.setenv("JRT_BUILD_THREADS", "4")
    per = threads.MIN_ROWS_PER_THREAD
    assert threads.threads_for(0) == 1
    assert threads.threads_for(per - 1) == 1
    assert threads.threads_for(2 * per) == 2
    assert threads.threads_for(100 * per) == 4


def test_thread_map_is_the_loop(monkeypatch):
    monkeypatch.setenv("JRT_BUILD_THREADS", "2")
    items = list(range(37))
    seen = set()

    def square(i):
        seen.add(threading.current_thread().name)
        return i * i

    assert threads.thread_map(square, items) == [i * i for i in items]
    assert any(name.startswith("accel-build") for name in seen)
    # One thread, or one item: the calling thread.
    seen.clear()
    assert threads.thread_map(square, items, 1) == [i * i for i in items]
    assert seen == {threading.current_thread().name}

    # A map started from a pooled pass runs in that pass (no wait on a full pool).
    def nested(i):
        return sum(threads.thread_map(lambda j: i * j, range(4)))

    assert threads.thread_map(nested, range(6)) == [6 * i for i in range(6)]

    def fails(i):
        if i == 5:
            raise KeyError(i)
        return i

    with pytest.raises(KeyError):
        threads.thread_map(fails, range(10))


@pytest.mark.parametrize("parts", [1, 2, 3, 8])
def test_node_chunks_cover_the_level(parts):
    rng = np.random.default_rng(parts)
    counts = rng.integers(1, 50, size=1000)
    counts[:3] = 5000  # a few large segments first, as on a tree's upper levels
    ends = np.cumsum(counts)
    runs = list(threads.node_chunks(counts, 128, parts))
    # Consecutive, covering, at most 128 segments each, rows matching the counts.
    assert runs[0][0] == 0 and runs[-1][1] == counts.size
    for (first, end, r0, r1), following in zip(runs, runs[1:] + [None], strict=True):
        assert 0 < end - first <= 128
        assert r0 == ends[first] - counts[first] and r1 == ends[end - 1]
        if following is not None:
            assert following[0] == end and following[2] == r1
    # Each 1/parts of the rows starts a run (at the segment holding it).
    starts = {first for first, _, _, _ in runs}
    for share in range(1, parts):
        at = int(np.searchsorted(ends, ends[-1] * share / parts, side="right"))
        assert at in starts or at == counts.size
    assert list(threads.node_chunks(np.zeros(0, np.int64), 128, parts)) == []
    # Without a size, only the shares cut: at most ``parts`` runs, covering the level.
    whole = list(threads.node_chunks(counts, parts=parts))
    assert len(whole) <= parts and whole[0][0] == 0 and whole[-1][1] == counts.size
    assert [first for first, _, _, _ in whole[1:]] == [end for _, end, _, _ in whole[:-1]]


@pytest.mark.parametrize("name", ["bvh", "kdtree", "bsp"])
def test_threaded_builds_are_the_serial_ones(name, camel19k, monkeypatch):
    """The structure's arrays and layout byte for byte, every level spread over threads
    (the row threshold lowered so that the 19k camel's levels are) or on one."""
    monkeypatch.setattr(threads, "MIN_ROWS_PER_THREAD", 64)
    pooled = []
    worker = threads._worker

    def counting(fn):
        pooled.append(fn)
        return worker(fn)

    monkeypatch.setattr(threads, "_worker", counting)
    built = {}
    for count in ("1", "3"):
        monkeypatch.setenv("JRT_BUILD_THREADS", count)
        built[count] = accel.build(name, camel19k.vertices, camel19k.faces)
    one, many = built["1"], built["3"]
    assert len(pooled) > 10  # the second build's passes went to the pool
    assert one.layout == many.layout
    assert sorted(one.arrays) == sorted(many.arrays)
    for key, value in one.arrays.items():
        a, b = np.asarray(value), np.asarray(many.arrays[key])
        assert a.dtype == b.dtype and a.shape == b.shape, key
        assert a.tobytes() == b.tobytes(), key
    assert one.stats["nodes"] > 1000  # a tree of many levels, not a leaf
