"""Benchmarks: scripts that print figures (autocast bench NAME)."""
