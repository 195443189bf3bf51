"""The scheduler bench runs in quick mode, draws its plot and ends with the headline line."""

from __future__ import annotations

import re

from bench import scheduler as bench


def test_quick_bench_prints_headline_and_saves_plot(tmp_path, capsys):
    assert bench.main(["--quick", "--out", str(tmp_path)]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    m = re.fullmatch(
        r"scheduler: greedy_vs_optimal=([\d.]+) agnostic_vs_greedy=([\d.]+) greedy40_ms=([\d.]+) fptas_over_greedy_time=(\d+)",
        last,
    )
    assert m, last
    greedy_vs_optimal, agnostic_vs_greedy, greedy40_ms, _ = map(float, m.groups())
    assert 0.0 < greedy_vs_optimal <= 1.0 and 0.0 < agnostic_vs_greedy < 1.0 and greedy40_ms > 0.0
    assert (tmp_path / "scheduler.png").stat().st_size > 10_000
