"""The ``autocast`` command and what it runs: one run, a run over hosts, its log, sweeps of runs."""

import processes  # noqa: F401  (one BLAS thread per process, before anything loads numpy)
