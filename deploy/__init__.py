"""Launcher: the table of processes, starting/stopping them, the autocast CLI."""
