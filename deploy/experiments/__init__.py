"""Experiments: sweeps of runs (on this machine or a Dask cluster), their offered load, and the paper's report."""
