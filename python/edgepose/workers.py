"""Threads that share a list of independent jobs: the objects of
:func:`edgepose.estimate_many` and :func:`edgepose.track_many`, the chunks
of a batch the encoder runs (:meth:`edgepose.Encoder.encode`). The jobs
release the GIL (the Rust core, onnxruntime), so the threads use the cores;
each job's own work in the core stays on its thread.
"""

from __future__ import annotations

import itertools
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

from edgepose import _core

T = TypeVar("T")


def each(work: Callable[[int], T], count: int, workers: int) -> list[T]:
    """``[work(i) for i in range(count)]``, shared by this thread and
    ``workers - 1`` pool threads, each taking the next ``i`` when done with
    its last (the work releases the GIL in the core). This thread starts at
    once, and a pool thread that has not woken by the time the work is done
    is not waited for: waking one can take longer than a tracked object.
    The first exception is raised once every thread is done.

    With more than one thread, each keeps the core's parallel loops and
    handed-over searches of its jobs to itself: the threads already use the
    cores, and sharing the core's threads too would only make them wait on
    one another (the results are the same)."""
    results: list[Any] = [None] * count
    indices = itertools.count()  # next() is atomic: each i is taken once
    sharing = min(workers, count) > 1

    def take() -> None:
        before = _core.keep_work_on_this_thread(sharing)
        try:
            while (i := next(indices)) < count:
                results[i] = work(i)
        finally:
            _core.keep_work_on_this_thread(before)

    helpers = [pool(workers - 1).submit(take) for _ in range(min(workers, count) - 1)]
    try:
        take()
    finally:
        running = [helper for helper in helpers if not helper.cancel()]
        for helper in running:
            helper.exception()  # waits for it
    for helper in running:
        helper.result()
    return results


_POOLS: dict[tuple[int, int], ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def pool(threads: int) -> ThreadPoolExecutor:
    """A pool of ``threads`` threads that every :func:`each` call of this
    process shares: started once, as the Rust core's threads are, since
    starting and joining threads for each frame costs a tracked frame's
    share of a millisecond. A forked child, whose parent's threads are not
    there, starts its own."""
    key = (os.getpid(), threads)
    with _POOLS_LOCK:
        if key not in _POOLS:
            _POOLS[key] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="edgepose")
        return _POOLS[key]
