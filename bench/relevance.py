"""When does the collider become relevant to the ego? Measured from runs' MCAPs.

The paper (5.1): an object is relevant to vehicle j when their trajectories could
collide at some point in the future. For each V2V run this reads every sender's
control message (``net/ctrl/tx``: its object map with centroids and r per receiver),
the world's ground truth (``world/truth``: where the collider really is) and the data
bundles (``net/data/rx``: who decoded what), and reports, in sim seconds:

- ``seen``: the first tick a sender other than the ego has an object on the collider
  (its centroid within ``MATCH_M`` of the collider's true position),
- ``relevant``: the first tick such an object has r > 0 for the ego,
- ``delivered``: the first tick the ego decoded a payload of such an object.

Usage: ``python -m bench.relevance runs/sweeps/NAME`` (a sweep directory, its
``results.jsonl``) or ``python -m bench.relevance runs/RUN/run.mcap ...``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deploy.experiments.load import EGO, MATCH_M  # how a run's collider object is found: the same as the load's

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class ColliderRelevance:
    seen_s: float | None
    relevant_s: float | None
    delivered_s: float | None
    first_sharer: int | None


def collider_relevance(mcap_path: Path) -> ColliderRelevance:
    from mcap.reader import make_reader

    from protocol import keys
    from protocol.codec import decode
    from protocol.messages import ControlMsg, DataBundle, WorldTruth

    truth: dict[int, np.ndarray] = {}
    msgs: list[ControlMsg] = []
    bundles: list[DataBundle] = []
    with open(mcap_path, "rb") as f:
        reader = make_reader(f)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        collider = int(meta["autocast"]["vehicles"])  # the passive collider's vid
        parts = {ch.topic: keys.net_part(ch.topic) for ch in reader.get_summary().channels.values()}
        topics = [t for t, part in parts.items()  # every domain's control messages and data bundles
                  if part.startswith("ctrl/tx/") or part == "data/rx" or t.endswith("/world/truth")]
        for _, _, message in reader.iter_messages(topics=topics):
            try:
                msg = decode(message.data)
            except Exception:  # a malformed payload the recorder kept
                continue
            if isinstance(msg, WorldTruth):
                hit = np.flatnonzero(msg.vids == collider)
                if len(hit):
                    truth[msg.tick] = msg.pose[hit[0], :2].astype(np.float64)
            elif isinstance(msg, ControlMsg) and msg.vid != EGO:
                msgs.append(msg)
            elif isinstance(msg, DataBundle):
                bundles.append(msg)
    seen = relevant = None
    sharer = None
    on_collider: set[tuple[int, int]] = set()  # (sender, object id) ever matched to the collider
    for m in sorted(msgs, key=lambda m: (m.tick, m.vid)):
        where = truth.get(m.tick)
        o = m.objects
        if where is None or len(o.object_id) == 0:
            continue
        d = np.hypot(*(o.centroid_xy.astype(np.float64) - where).T)
        k = int(np.argmin(d))
        if d[k] > MATCH_M:
            continue
        on_collider.add((m.vid, int(o.object_id[k])))
        if seen is None:
            seen, sharer = m.t_sim_s, m.vid
        col = np.flatnonzero(o.receivers == EGO)
        if relevant is None and len(col) and o.relevance[k, col[0]] > 0:
            relevant = m.t_sim_s
    delivered = None
    for b in sorted(bundles, key=lambda b: b.tick):
        got = b.received_by(EGO) or []
        if any((r.sender, r.object_id) in on_collider for r in got):
            delivered = b.t_sim_s
            break
    return ColliderRelevance(seen, relevant, delivered, sharer)


def _runs(paths: list[str]) -> list[tuple[str, Path]]:
    out = []
    for p in map(Path, paths):
        if p.suffix == ".mcap":
            out.append((p.parent.name, p))
            continue
        for line in (p / "results.jsonl").read_text().splitlines():
            try:
                r = json.loads(line)
            except json.JSONDecodeError:
                continue
            if r.get("scheme") not in ("single", "emp") and r.get("mcap") and Path(r["mcap"]).exists():
                out.append((r["run_key"], Path(r["mcap"])))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="+", help="sweep directories or run.mcap files")
    args = ap.parse_args(argv)

    def fmt(x: float | None) -> str:
        return "-" if x is None else f"{x:.1f}"

    print("| run | first seen by a sharer (s) | relevant to the ego (s) | lag (s) | delivered to the ego (s) |")
    print("|---|---|---|---|---|")
    for name, mcap in _runs(args.paths):
        r = collider_relevance(mcap)
        lag = None if r.seen_s is None or r.relevant_s is None else r.relevant_s - r.seen_s
        print(f"| {name} | {fmt(r.seen_s)} (v{r.first_sharer}) | {fmt(r.relevant_s)} | {fmt(lag)} | "
              f"{fmt(r.delivered_s)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
