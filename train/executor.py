"""Where independent work runs: threads of this process, or tasks on a Ray cluster.

Precompute chunks and per-segment fits are pure functions of their inputs, so they can run
anywhere.  Both stages hand them to an executor and consume the results on the calling thread
(the driver), which alone writes the caches::

    with open_executor(cluster, threads) as executor:  # prt.train.cluster
        for item, result in executor.map(fn, shared, items, task_threads=1):
            ...  # fn(shared, item) ran somewhere; results come in completion order

``shared`` is sent once (Ray: one object in the object store), each item with its task.  A
task runs with ``task_threads`` BLAS (and torch) threads wherever it runs, because those counts
can change the bytes of a result.  :class:`LocalExecutor` is the default; the Ray executor and
:func:`prt.train.cluster.open_executor`, which picks one, live in :mod:`prt.train.cluster`
(Ray is imported only when a cluster is asked for).
"""

from __future__ import annotations

import os
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from typing import Any, Callable, Iterable, Iterator

from threadpoolctl import threadpool_limits

__all__ = ["Executor", "LocalExecutor", "add_cluster_argument"]


class Executor:
    """Runs ``fn(shared, item)`` for many items; the interface both stages use."""

    #: True where tasks run in this process (they may log and draw progress bars themselves,
    #: and see this machine's files); False where they run elsewhere and only return values.
    local: bool = True

    def map(self, fn: Callable[[Any, Any], Any], shared, items: Iterable, *, task_threads: int = 1,
            exclusive: bool = False) -> Iterator[tuple]:  # fmt: skip
        """``(item, fn(shared, item))`` for every item, in completion order.

        ``fn`` must be a module-level function (a cluster imports it by name).  ``task_threads``:
        the BLAS and torch threads one task uses.  ``exclusive``: a task needs its process to
        itself (it seeds process-wide state such as torch's global generator).
        """
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class LocalExecutor(Executor):
    """A thread pool of ``threads`` (default: all cores) shared among tasks of ``task_threads`` each.

    Embree and numpy release the GIL, so chunk tasks scale over threads; a fit of
    ``task_threads = threads`` runs alone, as one torch computation over all threads.
    """

    local = True

    def __init__(self, threads: int | None = None):
        self.threads = max(1, int(threads or os.cpu_count() or 1))

    def map(self, fn, shared, items, *, task_threads: int = 1, exclusive: bool = False):
        items = list(items)
        if not items:
            return
        workers = 1 if exclusive else max(1, min(len(items), self.threads // max(1, task_threads)))
        # Our threads already fill the cores; BLAS threads spinning beside Embree cost ~25 %.
        limits = threadpool_limits(limits=max(1, task_threads), user_api="blas")
        if workers == 1:  # on this thread: Ctrl-C stops a long fit at once
            try:
                for item in items:
                    yield item, fn(shared, item)
            finally:
                limits.restore_original_limits()
            return
        pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="prt-task")
        try:
            pending = {pool.submit(fn, shared, item): item for item in items}
            while pending:
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    yield pending.pop(future), future.result()
        finally:
            # Ctrl-C, an error or a consumer that stops: start nothing more, let running tasks end.
            pool.shutdown(wait=True, cancel_futures=True)
            limits.restore_original_limits()


def add_cluster_argument(parser) -> None:
    """The ``--cluster auto|ADDRESS`` option, the same on every command that runs long work."""
    parser.add_argument(
        "--cluster", default=None, metavar="auto|ADDRESS",
        help="run the work as tasks on a Ray cluster: 'auto' (the cluster this machine is part of), a head node's "
             "HOST:PORT or ray://HOST:10001; same results and cache as a local run (needs the [cluster] extra)",
    )  # fmt: skip
