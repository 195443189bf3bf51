"""The channel bench drives a real proxy with synthetic agents and ends with its headline line."""

from __future__ import annotations

import re

from bench import channel as bench


def test_small_bench_runs_through_the_proxy_and_prints_the_headline(capsys):
    assert bench.main(["--vehicles", "8", "--losses", "0", "10", "--intervals", "3"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    m = re.fullmatch(r"channel: disagreement_loss10_pct=([\d.]+) proxy40_ms=([\d.]+)", out[-1])
    assert m, out[-1]
    assert float(m.group(1)) == 0.0 and float(m.group(2)) > 0.0  # the grouped rule never collides
    rows = [line.split() for line in out if line.startswith("   8 ")]
    assert [(r[1], r[2]) for r in rows] == [("heard", "0"), ("grouped", "0"), ("heard", "10"), ("grouped", "10")]
    assert all(float(r[11]) == 0 for r in rows)  # the control pool never overflowed
    assert all(r[5] == "0" for r in rows if r[1] == "grouped")  # not even in its worst interval
