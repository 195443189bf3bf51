"""Per-domain statistics of a run with several scheduler domains (docs/domains.md):
members per interval, handovers, data-channel load and collisions, from the proxy's
``ChannelStats`` in the run's log.

    python -m channel_proxy.domain_stats runs/<id> [--json]

A domain's **load** in an interval is the bytes its members put on the air there (the
proxy's ``data.offered_bytes`` of the domain: every transmission, a repeated copy
again) over what the data channel carries in an interval, B x N x T_n / 8 of the run's
channel profile (``lte-direct``: 90,000 bytes). Domains on one channel share its
medium: the channel's load is the sum of theirs. An interval in which a domain had no
member counts 0 members and 0 bytes for it. A domain's control messages **dropped**
are those the channel's control pool had no room for (the proxy's ``ctrl.overflow_msgs``
of the domain): the pool is per channel, shared by the domains on it.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter, defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import make_reader

from protocol import keys
from protocol.codec import MalformedMessage, decode
from protocol.messages import ChannelStats

DEFAULT_PROFILE = "lte-direct"  # the run's radio when its log does not name one


@dataclass
class DomainStats:
    intervals: int = 0
    members: dict[str, list[int]] = field(default_factory=dict)  # per interval, 0 where it had none
    offered_bytes: dict[str, list[int]] = field(default_factory=dict)  # per interval: its data on the air
    transmissions: dict[str, int] = field(default_factory=Counter)
    collided: dict[str, int] = field(default_factory=Counter)
    delivered_bytes: dict[str, int] = field(default_factory=Counter)
    ctrl_sent: dict[str, int] = field(default_factory=Counter)  # control messages sent in the domain
    ctrl_dropped: dict[str, int] = field(default_factory=Counter)  # ... that the channel's control pool had no room for
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
        i = out.intervals
        out.intervals += 1
        now: dict[int, set[str]] = defaultdict(set)
        for d, ds in s["domains"].items():
            out.channel[d] = ds["channel"]
            data, ctrl = ds.get("data", {}), ds.get("ctrl", {})
            out.members.setdefault(d, [0] * i).append(len(ds["members"]))
            out.offered_bytes.setdefault(d, [0] * i).append(data.get("offered_bytes", 0))
            for v in ds["members"]:
                now[v].add(d)
            out.transmissions[d] += data.get("transmissions", 0)
            out.collided[d] += data.get("collided_tx", 0)
            out.delivered_bytes[d] += data.get("delivered_bytes", 0)
            out.ctrl_sent[d] += ctrl.get("senders", 0)
            out.ctrl_dropped[d] += ctrl.get("overflow_msgs", 0)
        for d in out.members:
            if len(out.members[d]) == i:  # no member this interval
                out.members[d].append(0)
                out.offered_bytes[d].append(0)
        out.in_two += sum(len(ds) > 1 for ds in now.values())
        for v, ds in now.items():
            if v in before:
                out.joins.update(ds - before[v])
                out.leaves.update(before[v] - ds)
        before = dict(now)
    return out


def run_summary(s: DomainStats, capacity_bytes: int) -> dict[str, Any]:
    """A run's per-domain figures as JSON, per-interval series kept so that runs pool
    exactly (``autocast report``'s per-domain table)."""
    return {"intervals": s.intervals, "capacity_bytes": capacity_bytes, "in_two": s.in_two,
            "domains": {d: {"channel": s.channel[d], "members": s.members[d], "offered_bytes": s.offered_bytes[d],
                            "joined": s.joins[d], "left": s.leaves[d], "transmissions": s.transmissions[d],
                            "collided": s.collided[d], "delivered_bytes": s.delivered_bytes[d],
                            "ctrl_sent": s.ctrl_sent[d], "ctrl_dropped": s.ctrl_dropped[d]}
                        for d in sorted(s.members, key=int)}}


def table(s: DomainStats, capacity_bytes: int) -> str:
    rows = ["| domain | channel | members per interval, mean (min-max) | joined | left | load per interval, "
            "median (max) | transmissions | collided | delivered kB per interval | control messages dropped |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for d in sorted(s.members, key=int):
        m = np.array(s.members[d])
        load = np.array(s.offered_bytes[d]) / capacity_bytes
        rows.append(f"| {d} | {s.channel[d]} | {m.mean():.1f} ({m.min()}-{m.max()}) | {s.joins[d]} | {s.leaves[d]} | "
                    f"{np.median(load):.2f} ({load.max():.2f}) | "
                    f"{s.transmissions[d]} | {s.collided[d]} ({s.collided[d] / max(s.transmissions[d], 1):.0%}) | "
                    f"{s.delivered_bytes[d] / 1e3 / max(len(m), 1):.1f} | "
                    f"{s.ctrl_dropped[d]} ({s.ctrl_dropped[d] / max(s.ctrl_sent[d], 1):.0%}) |")
    rows.append(f"\n{s.intervals} intervals; vehicle-intervals in two domains at once: {s.in_two}; "
                f"load: bytes on the air over {capacity_bytes} bytes an interval; control messages dropped: "
                f"no room in the channel's control pool, of those sent in the domain")
    return "\n".join(rows)


def read_stats(mcap_path: Path) -> Iterable[dict]:
    """The ``ChannelStats.stats`` of a run's log, in order; undecodable ones (the
    recorder's JSON mirror, a malformed payload) skipped."""
    suffix = keys.net_stats("x").removeprefix("ac/x")
    with open(mcap_path, "rb") as f:
        reader = make_reader(f)
        topics = [ch.topic for ch in reader.get_summary().channels.values() if ch.topic.endswith(suffix)]
        if not topics:
            return
        for _, _, message in reader.iter_messages(topics=topics):
            try:
                yield decode(message.data, ChannelStats).stats
            except MalformedMessage:
                continue


def capacity_of(mcap_path: Path) -> int:
    """The data channel's bytes per interval of the run's channel profile (its log's
    ``autocast`` metadata, ``lte-direct`` when it names none)."""
    from channel_proxy.profiles import get_profile

    with open(mcap_path, "rb") as f:
        meta = next((m.metadata for m in make_reader(f).iter_metadata() if m.name == "autocast"), {})
    return get_profile(meta.get("channel_profile") or DEFAULT_PROFILE).data_capacity_bytes


def read_summary(mcap_path: Path) -> dict[str, Any]:
    """``run_summary`` of a run's log."""
    return run_summary(summarise(read_stats(mcap_path)), capacity_of(mcap_path))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m channel_proxy.domain_stats", description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", type=Path, help="a run's directory (holding run.mcap)")
    ap.add_argument("--json", action="store_true", help="print the per-run summary (per-interval series) as JSON")
    args = ap.parse_args(argv)
    mcap = args.run_dir / "run.mcap"
    if not mcap.is_file():
        print(f"error: run_dir: {mcap} is not a file", file=sys.stderr)
        return 2
    s, capacity = summarise(read_stats(mcap)), capacity_of(mcap)
    print(json.dumps(run_summary(s, capacity)) if args.json else table(s, capacity))
    return 0


if __name__ == "__main__":
    sys.exit(main())
