"""A Dask cluster for `lino-loc map build --engine dask`: a LocalCluster, or an existing one.

:func:`dask_client` is a context manager yielding a ``distributed.Client`` that is the
default Dask scheduler inside the block, so :mod:`lino_loc.pca_dask` (which sets up no
cluster) computes on it:

- ``scheduler=None``: a ``LocalCluster`` of ``workers`` worker processes with
  ``threads_per_worker`` threads each (one thread by default: PNG decoding, OpenCV and the
  BLAS products each want a core), no dashboard, closed on exit;
- ``scheduler="tcp://host:8786"``: connect to a running scheduler (``dask scheduler`` +
  ``dask worker``); unreachable within ``timeout_s`` is a one-line LinoLocError. Its workers
  must have lino-loc installed and see the dataset at the same path.

A missing ``dask``/``distributed`` is a one-line LinoLocError naming the extra to install.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from typing import Any

from lino_loc.errors import LinoLocError
from lino_loc.pca_dask import CLUSTER_EXTRA_HINT

log = logging.getLogger("lino_loc.map")

DEFAULT_WORKERS = 2


def _distributed() -> Any:
    try:
        import dask.array  # noqa: F401  (the engine needs it too)
        import distributed
    except ImportError:
        raise LinoLocError(f"the dask engine needs Dask and distributed: {CLUSTER_EXTRA_HINT}") from None
    return distributed


@contextlib.contextmanager
def dask_client(
    scheduler: str | None = None,
    *,
    workers: int = DEFAULT_WORKERS,
    threads_per_worker: int = 1,
    timeout_s: float = 10.0,
    memory_limit: str | float | None = "auto",
) -> Iterator[Any]:
    """A ``distributed.Client`` on a new LocalCluster (``scheduler`` None) or on the scheduler
    at ``scheduler``, set as the default scheduler until the block exits; closed then (the
    LocalCluster shut down; an existing cluster left running)."""
    distributed = _distributed()
    if workers < 1 or threads_per_worker < 1:
        raise LinoLocError(f"dask: workers and threads per worker must be >= 1, got {workers}, {threads_per_worker}")
    if scheduler is None:
        import dask

        # the workers' statistical profiler (a thread sampling every task's stack) and the
        # nannies' and workers' memory and system monitors (every 0.1 s / 0.5 s) cost CPU the
        # build wants on a small machine; the worker processes inherit these from their nannies
        with dask.config.set({"distributed.worker.profile.enabled": False,
                              "distributed.worker.memory.monitor-interval": "1s",
                              "distributed.admin.system-monitor.interval": "2s"}):
            cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=threads_per_worker,
                                               processes=True, dashboard_address=None, memory_limit=memory_limit)
        try:
            with distributed.Client(cluster) as client:
                log.info("dask: LocalCluster of %d workers x %d threads", workers, threads_per_worker)
                yield client
        finally:
            cluster.close()
        return
    try:
        client = distributed.Client(scheduler, timeout=f"{timeout_s}s")
    except (OSError, TimeoutError, ValueError, TypeError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise LinoLocError(f"--scheduler {scheduler}: cannot reach the Dask scheduler within {timeout_s:g} s "
                           f"({reason})") from None
    with client:
        n = len(client.nthreads())
        if n == 0:
            raise LinoLocError(f"--scheduler {scheduler}: the Dask scheduler has no workers")
        log.info("dask: scheduler %s with %d workers", scheduler, n)
        yield client
