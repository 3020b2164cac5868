"""Test-wide settings.

BLAS is pinned to one thread before numpy loads: the products in this project are small,
and a threaded BLAS on a busy 2-core machine made them 4-20x slower (measured).
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
os.environ.setdefault("DEPTHAI_LEVEL", "error")
