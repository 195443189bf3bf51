"""Per-domain statistics of a run with several scheduler domains (docs/domains.md):
members per interval, handovers, data-channel load and collisions, from the proxy's
``ChannelStats`` in the run's log.

    python -m channel_proxy.domain_stats runs/<id>
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter, defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from protocol import keys
from protocol.codec import MalformedMessage, decode
from protocol.messages import ChannelStats


@dataclass
class DomainStats:
    intervals: int = 0
    members: dict[str, list[int]] = field(default_factory=lambda: defaultdict(list))
    transmissions: dict[str, int] = field(default_factory=Counter)
    collided: dict[str, int] = field(default_factory=Counter)
    delivered_bytes: dict[str, int] = field(default_factory=Counter)
    channel: dict[str, int] = field(default_factory=dict)
    joins: Counter = field(default_factory=Counter)  # domain -> vehicles that joined it
    leaves: Counter = field(default_factory=Counter)
    in_two: int = 0  # (vehicle, interval) pairs in more than one domain


def summarise(stats: Iterable[dict]) -> DomainStats:
    """Fold the ``stats`` dicts of consecutive intervals (those with ``domains``)."""
    out, before = DomainStats(), {}
    for s in stats:
        if "domains" not in s:
            continue
        out.intervals += 1
        now: dict[int, set[str]] = defaultdict(set)
        for d, ds in s["domains"].items():
            out.channel[d] = ds["channel"]
            out.members[d].append(len(ds["members"]))
            for v in ds["members"]:
                now[v].add(d)
            data = ds.get("data", {})
            out.transmissions[d] += data.get("transmissions", 0)
            out.collided[d] += data.get("collided_tx", 0)
            out.delivered_bytes[d] += data.get("delivered_bytes", 0)
        out.in_two += sum(len(ds) > 1 for ds in now.values())
        for v, ds in now.items():
            if v in before:
                out.joins.update(ds - before[v])
                out.leaves.update(before[v] - ds)
        before = dict(now)
    return out


def table(s: DomainStats) -> str:
    rows = ["| domain | channel | members per interval, mean (min-max) | joined | left | transmissions | "
            "collided | delivered kB per interval |", "|---|---|---|---|---|---|---|---|"]
    for d in sorted(s.members, key=int):
        m = np.array(s.members[d])
        rows.append(f"| {d} | {s.channel[d]} | {m.mean():.1f} ({m.min()}-{m.max()}) | {s.joins[d]} | {s.leaves[d]} | "
                    f"{s.transmissions[d]} | {s.collided[d]} ({s.collided[d] / max(s.transmissions[d], 1):.0%}) | "
                    f"{s.delivered_bytes[d] / 1e3 / max(len(m), 1):.1f} |")
    rows.append(f"\n{s.intervals} intervals; vehicle-intervals in two domains at once: {s.in_two}")
    return "\n".join(rows)


def read_stats(mcap_path: Path) -> Iterable[dict]:
    """The ``ChannelStats.stats`` of a run's log, in order; undecodable ones skipped."""
    with open(mcap_path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            if channel.topic.endswith(keys.net_stats("x").removeprefix("ac/x")):
                try:
                    yield decode(message.data, ChannelStats).stats
                except MalformedMessage:
                    continue


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m channel_proxy.domain_stats", description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", type=Path, help="a run's directory (holding run.mcap)")
    args = ap.parse_args(argv)
    print(table(summarise(read_stats(args.run_dir / "run.mcap"))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
