"""Golden outcomes: lock-step runs are deterministic per seed, so a change that only
makes the code faster must give every run exactly the same result. This records, for
a small matrix (every scenario x every scheme, 4 vehicles, seed 0), what a run of
``autocast run`` ends with: the judged outcome, the ticks, the closest distance, the
ego's view of the collider, a digest of the whole ego-collider distance series, and
what the channel carried (summed from the proxy's ``net/stats`` in the run's MCAP).

    python tests/golden_outcomes.py --check            # re-run every entry, diff against the file
    python tests/golden_outcomes.py --check --sign     # the same with V2X signing on (or --no-sign)
    python tests/golden_outcomes.py --check --only left_turn/autocast/20s
    python tests/golden_outcomes.py --record           # re-record (only for a change meant to alter results)
    python tests/golden_outcomes.py --check --scans all --out runs/golden   # keep the scans: then
    for r in runs/golden/*/; do python -m vehicle_agent.replay $r; done     # replay every agent of each

tests/test_golden_outcomes.py re-runs the entries marked ``quick``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

GOLDEN = Path(__file__).resolve().parent / "data" / "golden_outcomes.json"
SCENARIOS = ("left_turn", "red_light", "overtaking")
SCHEMES = ("single", "agnostic", "emp", "autocast")
VEHICLES = 4
FULL_S = 20.0
# short runs (30 ticks): the sharing pipeline's results tick by tick, cheap enough for the suite
QUICK = (("left_turn", "autocast", 3.0), ("overtaking", "emp", 3.0))
# fields of the outcome record kept as they are
OUTCOME_FIELDS = ("outcome", "ticks", "t_end_s", "closest_distance_m", "closest_t_s", "reaction_time_s",
                  "collider_visible_share", "collider_points_mean", "collider_visible_share_own",
                  "collider_points_mean_own", "crash_with", "dead_agents")
CHANNEL_SUMS = {"ctrl": ("delivered_pairs", "offered_bytes"),
                "data": ("transmissions", "delivered_pairs", "delivered_bytes", "collided_tx"),
                "emp": ("uploads", "delivered_pairs", "delivered_bytes")}


def entry_name(scenario: str, scheme: str, duration_s: float) -> str:
    return f"{scenario}/{scheme}/{duration_s:g}s"


def matrix() -> list[tuple[str, str, float]]:
    """(scenario, scheme, sim-time limit) of every entry: 20 s (a safe passage ends the
    run at 11-19 s, a crash at 7), and the short runs."""
    return [(sc, scheme, FULL_S) for sc in SCENARIOS for scheme in SCHEMES] + list(QUICK)


def channel_totals(mcap_path: Path) -> dict[str, int]:
    """The proxy's per-interval statistics summed over the run."""
    from mcap.reader import make_reader

    from protocol.codec import decode
    from protocol.messages import ChannelStats

    totals = {f"{phase}_{k}": 0 for phase, ks in CHANNEL_SUMS.items() for k in ks}
    with open(mcap_path, "rb") as f:
        reader = make_reader(f)
        topics = [ch.topic for ch in reader.get_summary().channels.values()
                  if ch.topic.startswith("ac/") and ch.topic.endswith("/net/stats")]  # not the JSON mirror
        for _, _, message in reader.iter_messages(topics=topics):
            stats = decode(message.data, ChannelStats).stats
            for phase, ks in CHANNEL_SUMS.items():
                for k in ks:
                    totals[f"{phase}_{k}"] += int((stats.get(phase) or {}).get(k, 0))
    return totals


def run_entry(scenario: str, scheme: str, duration_s: float, out: Path, scans: str = "none",
              extra: tuple[str, ...] = ()) -> dict[str, Any]:
    """``extra``: more ``autocast run`` flags (``--sign``, ``--no-sign``: the results must not change)."""
    cmd = [sys.executable, "-m", "deploy.cli", "run", "--scenario", scenario, "--scheme", scheme,
           "--vehicles", str(VEHICLES), "--seed", "0", "--json", "--out", str(out), "--scans", scans,
           "--log-level", "WARNING", "--agent-timeout-s", "300", "--duration", f"{duration_s:g}", *extra]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    lines = proc.stdout.strip().splitlines()
    if not lines or not lines[-1].startswith("{"):
        raise RuntimeError(f"{entry_name(scenario, scheme, duration_s)} failed (exit {proc.returncode}):\n"
                           f"{proc.stderr[-3000:]}")
    rec = json.loads(lines[-1])
    got = {k: rec.get(k) for k in OUTCOME_FIELDS}
    got["distance_series_sha256"] = hashlib.sha256(json.dumps(rec["distance_series_m"]).encode()).hexdigest()
    got.update(channel_totals(Path(rec["mcap"])))
    return got


def load() -> dict[str, dict[str, Any]]:
    return json.loads(GOLDEN.read_text())["entries"]


def differences(expected: dict[str, Any], got: dict[str, Any]) -> list[str]:
    return [f"{k}: expected {expected.get(k)!r}, got {got.get(k)!r}"
            for k in sorted(set(expected) | set(got)) if expected.get(k) != got.get(k)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--record", action="store_true", help="run every entry and write the golden file")
    mode.add_argument("--check", action="store_true", help="run every entry and compare with the golden file")
    ap.add_argument("--only", default=None, help="comma-separated entry names (scenario/scheme/Ns)")
    ap.add_argument("--out", default="runs/golden", help="where the runs go")
    ap.add_argument("--scans", default="none", help="scans the runs' logs keep: none (default) or all, to replay "
                                                    "every agent from them (python -m vehicle_agent.replay)")
    ap.add_argument("--sign", action=argparse.BooleanOptionalAction, default=None,
                    help="run every entry with V2X signing on (or off); default: autocast run's default")
    args = ap.parse_args(argv)
    only = set(args.only.split(",")) if args.only else None
    todo = [e for e in matrix() if only is None or entry_name(*e) in only]
    golden = load() if args.check or GOLDEN.exists() else {}
    failed = 0
    for scenario, scheme, duration in todo:
        name = entry_name(scenario, scheme, duration)
        extra = () if args.sign is None else ("--sign",) if args.sign else ("--no-sign",)
        got = run_entry(scenario, scheme, duration, Path(args.out), args.scans, extra)
        if args.record:
            golden[name] = got
            print(f"{name}: {got['outcome']} ticks={got['ticks']} closest={got['closest_distance_m']}", flush=True)
            continue
        diff = differences(golden.get(name, {}), got)
        failed += bool(diff)
        print(f"{name}: {'SAME' if not diff else 'DIFFERENT'}", *diff, sep="\n  ", flush=True)
    if args.record:
        GOLDEN.parent.mkdir(parents=True, exist_ok=True)
        GOLDEN.write_text(json.dumps({"vehicles": VEHICLES, "seed": 0, "entries": golden}, indent=1,
                                     sort_keys=True) + "\n")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
