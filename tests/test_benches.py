"""Every bench runs as a user runs it (``autocast bench NAME --quick``), exits 0 and ends
with its headline line carrying every documented key with a number."""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import pytest

from bench import HEADLINE_KEYS, QUICK_KEYS
from tests.conftest import free_port

README = Path(__file__).resolve().parent.parent / "README.md"


def headline(name: str, stdout: str) -> dict[str, float]:
    last = stdout.strip().splitlines()[-1]
    prefix = f"{name}: "
    assert last.startswith(prefix), last
    pairs = [item.partition("=") for item in last.removeprefix(prefix).split()]
    assert all(sep == "=" for _, sep, _ in pairs), last
    return {key: float(value) for key, _, value in pairs}


@pytest.mark.heavy
@pytest.mark.parametrize("name", list(HEADLINE_KEYS))
def test_each_bench_prints_its_headline_in_quick_mode(name, tmp_path):
    res = subprocess.run([sys.executable, "-m", "deploy.cli", "bench", name, "--quick"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    figures = headline(name, res.stdout)
    assert tuple(figures) == QUICK_KEYS[name]
    assert all(math.isfinite(v) and v >= 0.0 for v in figures.values()), figures
    if name == "scheduler":
        assert 0.0 < figures["greedy_vs_optimal"] <= 1.0 and 0.0 < figures["agnostic_vs_greedy"] <= 1.0
        assert (tmp_path / "runs" / "bench_scheduler" / "scheduler.png").stat().st_size > 10_000
        wc = re.fullmatch(r"work-conserving: autocast40_ms=([\d.]+) autocast_over_agnostic_bytes=([\d.]+)",
                          res.stdout.strip().splitlines()[-2])
        assert wc and float(wc.group(1)) > 0.0 and float(wc.group(2)) >= 1.0, res.stdout[-500:]
    if name == "pipeline":
        assert figures["rtf5"] > 0.0 and figures["agent_ms"] > 0.0
        lines = res.stdout.splitlines()
        at = next(i for i, line in enumerate(lines) if line.startswith("the whole machine:"))
        assert lines[at + 1].split() == ["vehicles", "agents", "world", "proxy", "recorder", "launcher", "all",
                                         "tick", "ms", "busy"]
        for row, density in zip(lines[at + 2:at + 5], ("5", "10", "5+sign")):  # each run's figures, not a blank
            cells = row.split()
            assert cells[0] == density and len(cells) == 9 and cells[-1].endswith("%"), row
            assert float(cells[6]) == pytest.approx(sum(map(float, cells[1:6])), abs=0.3), row  # the parts add up


def test_the_zenoh_sample_bench_measures_a_subscriber_through_a_hub():
    """``python -m bench.zenoh_sample`` (not an ``autocast bench``: it compares nothing)
    starts its hub and publisher, receives every sample and prints a figure."""
    res = subprocess.run([sys.executable, "-m", "bench.zenoh_sample", "--gaps", "1", "--sizes", "4000", "--count", "5",
                          "--rounds", "1", "--port", str(free_port())], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    figures = headline("zenoh_sample", res.stdout)
    assert figures["samples"] == 5 and figures["rounds"] == 1 and figures["max_us"] > 0.0, figures


def test_the_readme_documents_every_headline_key():
    documented = dict(re.findall(r"`(\w+): ((?:\w+=\.\.\. ?)+)`", README.read_text()))
    assert set(documented) == set(HEADLINE_KEYS)
    for name, keys in HEADLINE_KEYS.items():
        assert tuple(k.removesuffix("=...") for k in documented[name].split()) == keys, name


def test_the_autocast_command_names_every_bench():
    """``autocast --help`` lists the benches without importing them: the same names."""
    from deploy.cli import BENCHES

    assert BENCHES == tuple(HEADLINE_KEYS)


def test_the_phase_marks_of_a_run_are_ordered_as_its_messages(tmp_path):
    """``bench.critical_path``'s run: every process marks every phase of every tick it
    plays (a mark before a send, one after the receive), so each receive comes after the
    send it waited for, on the one clock of the host; then the bench's own summary."""
    from bench import critical_path
    from bench.critical_path import EVENTS, read_marks, run_marked, summarize

    marks_dir = tmp_path / "marks"
    marks_dir.mkdir()
    outcome = run_marked(3, "autocast", "left_turn", 1.5, tmp_path / "runs", marks_dir)
    marks = read_marks(marks_dir)
    ticks = [k for k in sorted(marks) if any("world.stepped" in e for e in marks[k].values())]
    assert len(ticks) == outcome["ticks"] == 15

    def times(k: int, event: str) -> list[float]:
        return [e[event][0] for e in marks[k].values() if event in e]

    for k in ticks:
        assert len(times(k, "agent.scan")) == len(times(k, "agent.cmd_sent")) == 3
        for send, receive in [("world.tick", "agent.scan"), ("agent.ctrl_sent", "proxy.ctrl_closed"),
                              ("proxy.ctrl_bundle_sent", "agent.ctrl_bundle"), ("agent.data_sent", "proxy.data_closed"),
                              ("proxy.data_bundle_sent", "agent.data_bundle"), ("agent.cmd_sent", "world.commands_in")]:
            if times(k, receive):  # an agent that fuses nothing takes no data bundle
                assert max(times(k, send)) <= min(times(k, receive)), (k, send, receive)
    summary = summarize(marks, skip=1)
    assert set(summary["events"]) <= set(EVENTS) and "proxy.ctrl_closed" in summary["events"]
    assert summary["tick_ms"] > 0
    assert critical_path.main(["--vehicles", "3", "--duration", "1", "--skip", "1", "--out", str(tmp_path / "runs")]) == 0


def test_the_cold_wake_bench_times_the_work_after_each_sleep_and_stops_what_it_started():
    """``python -m bench.cold_wake`` (not an ``autocast bench``: a finding, not a figure of
    ours) prints a median per sleep and per neighbour, and its spinners are gone after."""
    res = subprocess.run([sys.executable, "-m", "bench.cold_wake", "--sleeps", "0,1", "--repeat", "5",
                          "--beside", "idle", "--beside", "spin"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    figures = headline("cold_wake", res.stdout)
    assert list(figures) == ["idle_after0ms_us", "idle_after1ms_us", "spin_after0ms_us", "spin_after1ms_us"]
    assert all(v > 0.0 for v in figures.values()), figures
    from bench.cold_wake import _BESIDE

    left = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if _BESIDE["spin"].encode() in cmdline.read_bytes():
                left.append(cmdline.parent.name)
        except OSError:  # gone meanwhile
            pass
    assert left == [], left  # killed and waited for
