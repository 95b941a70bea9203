"""Where the batch commands run their work: this process, a local process pool, or Ray.

``f2l estimate`` and ``f2l build-dataset`` share it. :func:`run_local` calls ``fn(*task)`` for
each task of a stream and yields the results in completion order: in this process when
``workers <= 1`` (tasks one at a time, in order), else in a pool of ``workers`` spawned processes
(spawn, not fork: forking a process whose torch/OpenMP threads run can deadlock) with at most
``2 * workers`` tasks in flight, so a stream of any length needs bounded memory. The task stream
is read lazily, between results: a generator may do work of its own (write a row for an item that
needs no task) as it yields. :func:`ray_session` starts (or joins) Ray for one run. Either
executor's missing optional dependency is one :class:`ExecutorUnavailable`.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager

EXECUTORS = ("local", "ray")
"""The executor names the CLI's ``--executor`` takes."""

RAY_MISSING = "--executor ray needs Ray: pip install 'f2l[ray]'"


class ExecutorUnavailable(RuntimeError):
    """The chosen executor's optional dependency is not installed."""


def check_executor(name: str) -> str:
    """``name`` if it is one of :data:`EXECUTORS`, else ValueError naming the choices."""
    if name not in EXECUTORS:
        raise ValueError(f"executor must be 'local' or 'ray', got {name!r}")
    return name


def run_local(fn: Callable, tasks: Iterable[tuple], workers: int, *, initializer: Callable | None = None,
              initargs: tuple = ()) -> Iterator:
    """``fn(*task)`` for every task, results as they finish. ``workers <= 1``: here, in order (the
    ``initializer`` is for pool workers only: this process is the caller's to set up); else a
    spawn pool whose workers each run ``initializer(*initargs)`` first. ``fn`` and the tasks must
    pickle in the pool. An exception raised by ``fn`` propagates (the pool is shut down)."""
    if workers <= 1:
        for task in tasks:
            yield fn(*task)
        return
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, initializer=initializer, initargs=initargs,
                             mp_context=context) as pool:
        pending: set[Future] = set()
        for task in tasks:
            pending.add(pool.submit(fn, *task))
            if len(pending) >= 2 * workers:
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in finished:
                    yield fut.result()
        while pending:
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                yield fut.result()


def import_ray():
    """The ``ray`` module, or :class:`ExecutorUnavailable` naming the extra to install."""
    try:
        import ray
    except ImportError as exc:  # pragma: no cover - depends on the installed extras
        raise ExecutorUnavailable(RAY_MISSING) from exc
    return ray


@contextmanager
def ray_session(address: str | None = None, workers: int = 2):
    """Ray for one run, as the ``ray`` module: the cluster at ``address`` (``ray://...`` or
    ``host:port``), or None: a new local cluster of ``workers`` CPUs of this run's own (never one a
    killed run left behind), shut down afterwards. A Ray this process already started is used
    as it is and left running."""
    ray = import_ray()
    started = False
    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(address="local", num_cpus=max(1, int(workers)), include_dashboard=False,
                     log_to_driver=False, configure_logging=False)
        started = True
    try:
        yield ray
    finally:
        if started:
            ray.shutdown()
