"""Launching one run: its table of processes, its credentials, the numba warm-up, the launcher."""
