"""The scheduler bench runs in quick mode, draws its plot and ends with the headline line."""

from __future__ import annotations

import re

from bench import scheduler as bench


def test_quick_bench_prints_headline_and_saves_plot(tmp_path, capsys):
    assert bench.main(["--quick", "--out", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    last = lines[-1]
    wc = re.fullmatch(r"work-conserving: autocast40_ms=([\d.]+) autocast_over_agnostic_bytes=([\d.]+)", lines[-2])
    assert wc, lines[-2]
    assert float(wc.group(1)) > 0.0 and float(wc.group(2)) >= 1.0  # congested instances: autocast fills the channel
    m = re.fullmatch(
        r"scheduler: greedy_vs_optimal=([\d.]+) agnostic_vs_greedy=([\d.]+) greedy40_ms=([\d.]+) fptas_over_greedy_time=(\d+)",
        last,
    )
    assert m, last
    greedy_vs_optimal, agnostic_vs_greedy, greedy40_ms, _ = map(float, m.groups())
    assert 0.0 < greedy_vs_optimal <= 1.0 and 0.0 < agnostic_vs_greedy < 1.0 and greedy40_ms > 0.0
    assert (tmp_path / "scheduler.png").stat().st_size > 10_000
