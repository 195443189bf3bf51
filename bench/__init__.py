"""Benchmarks: scripts that print figures (``autocast bench NAME [--quick]``), and the hostile
peer (``python -m bench.hostile``) that attacks a run with the fuzz bench's payloads.

Every bench ends with one headline line, ``NAME: key=value key=value ...`` (medians).
``HEADLINE_KEYS`` is what each prints: README.md lists these keys, docs/performance.md
says what each means, and
tests/test_benches.py runs every bench with ``--quick`` and checks them, so a bench
that breaks or drops a key fails the suite instead of rotting.
"""

HEADLINE_KEYS: dict[str, tuple[str, ...]] = {
    "lidar": ("scan_ms", "tick40_ms"),
    "perception": ("dataplane_ms",),
    "scheduler": ("greedy_vs_optimal", "agnostic_vs_greedy", "greedy40_ms", "fptas_over_greedy_time"),
    "channel": ("disagreement_loss10_pct", "proxy40_ms"),
    "pipeline": ("agent_ms", "plan_ms", "rtf5", "rtf10", "rtf20", "rtf40", "startup40_s", "proc10_ms", "proc40_ms",
                 "sign40_pct"),
    "fuzz": ("inputs", "other_exceptions", "over_alloc_bound", "peak_kib", "peak_per_byte"),
}
# --quick keeps every key but the densities it skips: pipeline runs 5 and 10 vehicles only
QUICK_KEYS: dict[str, tuple[str, ...]] = dict(HEADLINE_KEYS, pipeline=("agent_ms", "plan_ms", "rtf5", "rtf10",
                                                                       "startup10_s", "proc10_ms", "sign5_pct"))
