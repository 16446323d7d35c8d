"""Running the build's tasks on a Ray cluster (the ``[cluster]`` extra): :class:`RayExecutor`.

The only module that uses Ray, imported only when a cluster is asked for (:func:`open_executor`).
Stages see the :class:`prt.train.executor.Executor` interface; here ``shared`` goes into the
object store once (each node fetches it once), every item becomes a task, and results come back
to the driver, which writes the caches, so a run resumes across local and cluster runs.

Guarantees:

- Bytes: a task runs the same function on the same inputs as a local run, with the same BLAS
  and torch thread counts (``task_threads``), so results equal a local run's bit for bit where
  the nodes run the same package versions on the same kind of CPU.
- Faults: a task whose worker process or node dies is retried (``max_retries``); the driver
  takes each item's result once, so nothing is lost or written twice.
- Interruption: Ctrl-C cancels the tasks not yet finished; finished ones are already cached.
"""

from __future__ import annotations

import logging
import socket
import sys

from threadpoolctl import threadpool_limits

from ..runtime.errors import PRTError
from .executor import Executor, LocalExecutor

__all__ = ["open_executor", "RayExecutor", "import_ray", "INSTALL_HINT"]

INSTALL_HINT = 'pip install "prt-runtime[cluster]"'
MAX_RETRIES = 5  # per task, on a worker or node that died (not on an exception of ours)


def open_executor(cluster: str | None = None, threads: int | None = None) -> Executor:
    """Threads of this process (``cluster`` None) or a Ray cluster (``"auto"`` or an address).

    Raises :class:`prt.runtime.errors.PRTError` (one line) when Ray is not installed or the
    cluster cannot be reached.
    """
    return RayExecutor(cluster) if cluster else LocalExecutor(threads)


def import_ray():
    """The ``ray`` module, or a one-line PRTError saying how to install it."""
    try:
        import ray
    except ImportError as exc:
        raise PRTError(f"--cluster needs Ray, which is not installed ({exc}); install it with: {INSTALL_HINT}") from None
    return ray


def _run_task(fn, shared, item, threads: int):
    """One task on a worker: ``fn(shared, item)`` under the thread counts of a local run."""
    torch = sys.modules.get("torch")  # imported with fn's module where fn trains
    before = torch.get_num_threads() if torch is not None else None
    with threadpool_limits(limits=threads, user_api="blas"):
        if torch is not None:
            torch.set_num_threads(threads)
        try:
            return fn(shared, item)
        finally:
            if torch is not None:
                torch.set_num_threads(before)


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """A one-line PRTError now where nothing listens at ``[ray://]HOST:PORT`` (Ray itself retries for minutes)."""
    if address == "auto":
        return
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise PRTError(f"--cluster {address}: expected auto, HOST:PORT or ray://HOST:PORT")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as exc:
        raise PRTError(f"--cluster {address}: no Ray cluster answers there ({exc.strerror or exc})") from None


class RayExecutor(Executor):
    """Tasks on the Ray cluster at ``address`` (``"auto"``: the one this machine belongs to).

    ``address`` is what :func:`ray.init` takes: ``auto``, ``HOST:PORT`` of a head node (the
    driver runs on a cluster node) or ``ray://HOST:10001`` (Ray Client, from outside).
    """

    local = False

    def __init__(self, address: str, max_retries: int = MAX_RETRIES):
        ray = import_ray()
        self._ray = ray
        self.max_retries = max_retries
        self._owns_connection = not ray.is_initialized()
        if self._owns_connection:
            _check_reachable(address)
            try:
                ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                raise PRTError(f"--cluster {address}: cannot connect to a Ray cluster ({str(exc).splitlines()[0]})") from None
        self._task = ray.remote(_run_task)

    def cpus(self) -> tuple[int, int]:
        """(CPUs of the whole cluster, CPUs of its largest node)."""
        nodes = [n for n in self._ray.nodes() if n.get("Alive")]
        per_node = [int(n.get("Resources", {}).get("CPU", 0)) for n in nodes] or [1]
        return max(1, sum(per_node)), max(1, max(per_node))

    def map(self, fn, shared, items, *, task_threads: int = 1, exclusive: bool = False):
        # exclusive needs nothing more here: a Ray worker process runs one task at a time.
        ray = self._ray
        items = list(items)
        if not items:
            return
        total_cpus, node_cpus = self.cpus()
        task = self._task.options(num_cpus=min(max(1, task_threads), node_cpus), max_retries=self.max_retries, retry_exceptions=False)
        shared_ref = ray.put(shared)  # once; every node fetches it once
        window = max(8, 2 * total_cpus)  # tasks in flight: enough to keep every CPU busy
        upcoming = iter(range(len(items)))
        pending: dict = {}
        try:
            while True:
                for i in upcoming:
                    pending[task.remote(fn, shared_ref, items[i], max(1, task_threads))] = i
                    if len(pending) >= window:
                        break
                if not pending:
                    return
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    try:
                        value = ray.get(ref)
                    except ray.exceptions.RayTaskError:
                        raise  # an error of the task's own code: its type, as in a local run
                    except ray.exceptions.RayError as exc:  # a lost worker, node or object, past its retries
                        raise PRTError(f"cluster: a task failed {self.max_retries + 1} times ({str(exc).splitlines()[0]})") from None
                    yield items[pending.pop(ref)], value
        finally:
            for ref in pending:  # Ctrl-C, an error or a consumer that stops
                ray.cancel(ref)

    def close(self) -> None:
        if self._owns_connection and self._ray.is_initialized():
            self._ray.shutdown()
