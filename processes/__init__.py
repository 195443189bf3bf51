"""A run's OS processes: the manager that starts, watches and stops them, and the warm factory they fork from."""

import os

# One BLAS thread per process, set before anything loads numpy: a run is tens of
# processes on a few cores, and OpenBLAS's idle worker threads spin after each call
# (the proxy's one matrix product per interval burnt ~50 ms of CPU per tick at 40
# vehicles in them). Every process of a run is forked from, or started by, this
# package's manager, and inherits it; a value the user set is kept.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
