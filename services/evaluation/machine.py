"""The machine a benchmark ran on, and the single-thread setting of the numeric libraries.

Benchmarks run with one BLAS/OpenMP thread: the thread count is fixed when numpy is loaded,
so a caller checks :func:`single_threaded` first and re-runs itself with :data:`THREAD_VARS`
set to 1 when it is not.
"""

from __future__ import annotations

import os
from typing import Any

THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def single_threaded() -> bool:
    """True when every variable of :data:`THREAD_VARS` is set to 1."""
    return all(os.environ.get(v) == "1" for v in THREAD_VARS)


def machine() -> dict[str, Any]:
    """Platform, cpu model and count, load average, python and numpy versions, thread variables."""
    import platform

    import numpy as np

    try:
        load = [round(v, 2) for v in os.getloadavg()]
    except OSError:
        load = None
    model = platform.processor()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "platform": platform.platform(),
        "cpu": model,
        "cpu_count": os.cpu_count(),
        "load_average": load,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "threads": {v: os.environ.get(v) for v in THREAD_VARS},
    }
