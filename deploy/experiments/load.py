"""Offered load and the collider's delivery, per decision interval of a run's MCAP.

``python -m deploy.experiments.load RUN.mcap [--json]`` prints a run's summary and a few of its
intervals; ``autocast report`` puts the summaries of a sweep's runs in a table and in
``load_vs_density.png`` (docs/experiments.md, "Offered load and the collider's delivery").

For interval (tick) k of a V2V run:

- **objects offered**: the objects of every sender's control message of tick k
  (``net/ctrl/tx/<vid>``, ``ControlMsg.objects``), the ego's included: the scheduler's
  candidate pool. One vehicle seen by several senders counts once per sender; on a map
  of several scheduler domains, every domain's control messages count
  (``net/c<channel>/d<domain>/ctrl/tx/<vid>``), a sender in two domains once in each.
  **Wanted**: those some receiver would gain from, (1 - v) r > 0 (the reward's terms).
- **bytes offered**: the sum of their ``size_bytes``; **load** = bytes offered over the
  data channel's capacity in an interval, B x N x T_n / 8 of the run's channel profile
  (``lte-direct``: 7.2 Mbps x 10 x 10 ms / 8 = 90,000 bytes), times the number of
  domains with a control message in the run (each domain's schedule fills its own
  interval; ``python -m channel_proxy.domain_stats`` gives each domain's load alone).
- **share sent**: what the senders put on the air in interval k (the proxy's
  ``net/stats``, ``stats["data"]["offered_bytes"]``; a repeated copy counts again) over
  the bytes offered; NaN when nothing was offered.
- **collider offered**: a sender other than the ego offered an object on the collider:
  the object of its map whose centroid is nearest the collider's true position
  (``world/truth`` at tick k), if within ``MATCH_M`` (3 m), as ``bench.relevance`` matches.
- **collider to the ego**: the ego decoded (``DataBundle.decoded[ego row]`` on
  ``net/data/rx``, in any domain) a reception of tick k that is such an object (sender
  and object id).

The ego is the vehicle whose ``Mission`` says role "ego" (vid 0 when none is recorded; of
a scenario of several events, the first event's: the lowest such vid); the collider's vid
is the run's vehicle count (metadata ``autocast`` -> ``vehicles``), the first event's.

EMP runs have no control messages and their uploads go over the 50 Mbps V2I relay, not
the V2V channel: their load fields are NaN, and only the collider's delivery is given,
by its points: **offered** when a vehicle other than the ego uploaded (``net/emp/up``)
at least ``MIN_POINTS`` (5) points on the collider's footprint (its true box plus the
judge's 0.25 m margin, counted by the judge's own ``count_in_box``), **to the ego** when
the ego's ``EmpBundle`` (``net/emp/down/<ego>``) holds a segment of another vehicle with
that many.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

MATCH_M = 3.0  # an object whose centroid is this close to the collider's true centre is the collider
EGO = 0  # the ego's vid when no mission says which vehicle is the ego

MIN_POINTS = 5  # EMP: a segment with this many points on the collider carries it (the judge's "visible")
FOOTPRINT_MARGIN_M = 0.25  # the judge's margin around the collider's body (world_server.judge)
DEFAULT_PROFILE = "lte-direct"  # the run's default radio, for a log without the metadata
SUMMARY_VERSION = 2  # bump when these figures change meaning: summaries cached or kept are computed again
KEPT = "load.json"  # in a run's directory: its summary, kept when a sweep deletes its MCAP for its size


@dataclass(frozen=True, slots=True)
class IntervalLoad:
    tick: int
    objects_offered: int  # in every sender's control message, copies from several senders each
    objects_wanted: int  # of them, those with (1 - v) r > 0 for some receiver
    bytes_offered: int  # sum of their size_bytes
    capacity_bytes: int  # B N T_n / 8 of the run's channel profile
    load: float  # bytes_offered / capacity_bytes (NaN for EMP)
    bytes_sent: int  # the proxy's data offered_bytes: what went on the air
    share_sent: float  # bytes_sent / bytes_offered (NaN when nothing was offered)
    collider_to_ego: bool  # the ego decoded a copy of the collider this interval
    collider_offered: bool  # a sender other than the ego offered the collider this interval


# ---------------------------------------------------------------------------- reading a run's log


def raw_messages(mcap_path: Path, keep: Callable[[str], bool]) -> Iterator[tuple[str, bytes]]:
    """(topic, payload) of the run's msgpack channels whose topic ``keep`` accepts, in log
    order: not the JSON mirror (its payloads are JSON, not messages)."""
    from mcap.reader import make_reader

    from deploy.record.recorder import JSON_PREFIX

    with open(mcap_path, "rb") as f:
        reader = make_reader(f)
        topics = sorted({ch.topic for ch in reader.get_summary().channels.values()
                         if not ch.topic.startswith(JSON_PREFIX) and keep(ch.topic)})
        if not topics:
            return
        for _, channel, message in reader.iter_messages(topics=topics):
            yield channel.topic, message.data


def run_metadata(mcap_path: Path) -> dict[str, str]:
    """The recorder's ``autocast`` metadata record (run id, scenario, vehicles, scheme, ...)."""
    from mcap.reader import make_reader

    with open(mcap_path, "rb") as f:
        return next((m.metadata for m in make_reader(f).iter_metadata() if m.name == "autocast"), {})


def capacity_bytes(profile_name: str) -> int:
    """Bytes the data channel carries in one decision interval: B x N x T_n / 8."""
    from channel_proxy.profiles import get_profile

    return get_profile(profile_name).data_capacity_bytes


def _control_objects(payload: bytes):
    """(tick, vid, ObjectMap) of a control message, signed or not; only those fields decoded."""
    from protocol.codec import MalformedMessage, decode, decode_fields
    from protocol.messages import ControlMsg
    from protocol.security import opened

    try:
        return decode_fields(payload, ControlMsg, ("tick", "vid", "objects"))
    except MalformedMessage:
        msg = opened(decode(payload))  # a signed control message: its body
        if not isinstance(msg, ControlMsg):
            raise
        return msg.tick, msg.vid, msg.objects


@dataclass(slots=True)
class _Offer:
    """What one sender offered in one interval, kept to match the collider afterwards."""

    object_id: np.ndarray
    centroid_xy: np.ndarray


def interval_load(mcap_path: Path) -> list[IntervalLoad]:
    """One row per decision interval of the run (its ``world/tick`` ticks), by tick; empty
    for a run without a channel (``single``, ``lane``). Messages this build cannot read
    are left out and counted in a warning."""
    from protocol import keys
    from protocol.codec import decode
    from protocol.messages import ChannelStats, DataBundle, EmpBundle, EmpUpload, Mission, Tick, WorldTruth

    mcap_path = Path(mcap_path)
    meta = run_metadata(mcap_path)
    collider = int(meta["vehicles"])  # the passive collider's vid (bench.relevance)
    profile = meta.get("channel_profile") or DEFAULT_PROFILE
    ego = EGO
    egos: list[int] = []  # the vids whose missions say "ego"
    ticks: set[int] = set()
    truth: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # tick -> (x, y, yaw), (length, width)
    offered, wanted, size = defaultdict(int), defaultdict(int), defaultdict(int)
    offers: dict[int, list[tuple[int, _Offer]]] = defaultdict(list)  # tick -> (sender, its map)
    sent: dict[int, int] = {}
    ego_rx: dict[int, list[tuple[int, int]]] = defaultdict(list)  # tick -> (sender, object id) the ego decoded
    emp_up: dict[int, list[tuple[int, np.ndarray]]] = defaultdict(list)  # tick -> (uploader, points xy)
    emp_down: dict[int, list[tuple[int, int, np.ndarray]]] = defaultdict(list)  # tick -> (receiver, sender, xy)
    unread: list[tuple[str, Exception]] = []
    domains: set[tuple[int, int]] = set()  # the (channel, domain) pairs with a control message
    has_channel = False

    def keep(topic: str) -> bool:
        part = keys.net_part(topic)
        return (part.startswith(("ctrl/tx/", "emp/up/", "emp/down/")) or part in ("data/rx", "stats")
                or topic.endswith(("/world/tick", "/world/truth", "/mission")))

    for topic, payload in raw_messages(mcap_path, keep):
        try:
            if keys.net_part(topic).startswith("ctrl/tx/"):
                has_channel = True
                domains.add(keys.channel_domain_of(topic))
                tick, vid, o = _control_objects(payload)
                n = len(o.object_id)
                if n:
                    gain = (1.0 - o.visibility.astype(np.float64)) * o.relevance  # the reward's terms, (n, m)
                    offered[tick] += n
                    wanted[tick] += int(np.count_nonzero((gain > 0).any(axis=1)))
                    size[tick] += int(o.size_bytes.sum())
                    offers[tick].append((int(vid), _Offer(o.object_id, o.centroid_xy.astype(np.float64))))
                continue
            msg = decode(payload)
        except Exception as exc:  # a malformed payload the recorder kept, an earlier message version
            unread.append((topic, exc))
            continue
        if isinstance(msg, Tick):
            ticks.add(msg.tick)
        elif isinstance(msg, WorldTruth):
            hit = np.flatnonzero(msg.vids == collider)
            if len(hit):
                truth[msg.tick] = (msg.pose[hit[0]].astype(np.float64), msg.size_m[hit[0], :2].astype(np.float64))
        elif isinstance(msg, Mission):
            if msg.role == "ego":
                egos.append(msg.vid)
                ego = min(egos)
        elif isinstance(msg, ChannelStats):
            has_channel = True
            data = msg.stats.get("data")
            if isinstance(data, dict):
                sent[msg.tick] = int(data.get("offered_bytes") or 0)
        elif isinstance(msg, DataBundle):
            has_channel = True
            ego_rx[msg.tick] += [(int(r.sender), int(r.object_id)) for r in msg.received_by(ego) or []]
        elif isinstance(msg, EmpUpload):
            has_channel = True
            emp_up[msg.tick].append((msg.vid, msg.points_world[:, :2]))
        elif isinstance(msg, EmpBundle):
            has_channel = True
            emp_down[msg.tick] += [(msg.receiver, s.sender, s.points_world[:, :2]) for s in msg.segments]
    if unread:
        log.warning("%s: %d messages unreadable (first: %s: %s); left out", mcap_path, len(unread), *unread[0])
    if not has_channel:
        return []
    emp = bool(emp_up or emp_down)
    capacity = capacity_bytes(profile) * max(1, len(domains))  # each domain's schedule fills its own interval
    ticks = ticks or set(offered) | set(sent) | set(ego_rx) | set(emp_up) | set(emp_down)
    rows = []
    for k in sorted(ticks):
        if emp:
            on_up = [v for v, xy in emp_up.get(k, []) if v != ego and _on_collider(xy, truth.get(k))]
            on_down = [s for r, s, xy in emp_down.get(k, []) if r == ego and s != ego
                       and _on_collider(xy, truth.get(k))]
            rows.append(IntervalLoad(k, 0, 0, 0, capacity, math.nan, 0, math.nan, bool(on_down),
                                     bool(on_up or on_down)))
            continue
        copies = _collider_copies(offers.get(k, []), truth.get(k), ego)
        bytes_offered = size.get(k, 0)
        bytes_sent = sent.get(k, 0)
        rows.append(IntervalLoad(
            k, offered.get(k, 0), wanted.get(k, 0), bytes_offered, capacity, bytes_offered / capacity, bytes_sent,
            bytes_sent / bytes_offered if bytes_offered else math.nan,
            any(rx in copies for rx in ego_rx.get(k, [])), bool(copies)))
    return rows


def _collider_copies(offers: Sequence[tuple[int, _Offer]], where: tuple[np.ndarray, np.ndarray] | None,
                     ego: int) -> set[tuple[int, int]]:
    """(sender, object id) of each sender's object on the collider: its nearest object,
    if within MATCH_M of the collider's true position; the ego's own map left out."""
    if where is None:
        return set()
    out = set()
    for sender, o in offers:
        if sender == ego:
            continue
        d = np.hypot(o.centroid_xy[:, 0] - where[0][0], o.centroid_xy[:, 1] - where[0][1])
        k = int(np.argmin(d))
        if d[k] <= MATCH_M:
            out.add((sender, int(o.object_id[k])))
    return out


def _on_collider(xy: np.ndarray, where: tuple[np.ndarray, np.ndarray] | None) -> bool:
    """At least MIN_POINTS of ``xy`` on the collider's footprint, as the judge counts them."""
    from world_server.geometry import count_in_box

    if where is None or len(xy) < MIN_POINTS:
        return False
    (x, y, yaw), (length, width) = where
    return count_in_box(np.ascontiguousarray(xy), float(x), float(y), float(np.cos(yaw)), float(np.sin(yaw)),
                        length / 2 + FOOTPRINT_MARGIN_M, width / 2 + FOOTPRINT_MARGIN_M) >= MIN_POINTS


# ---------------------------------------------------------------------------- summary


def load_summary(rows: Sequence[IntervalLoad]) -> dict[str, Any]:
    """A run's figures over its intervals; a figure without data is None (JSON null).

    ``delivery_offered``: share of the intervals in which some sender offered the
    collider that the ego decoded a copy of it; ``delivery_all``: of every interval."""
    load = np.array([r.load for r in rows], dtype=np.float64)
    load = load[np.isfinite(load)]
    share = np.array([r.share_sent for r in rows], dtype=np.float64)
    share = share[np.isfinite(share)]
    offered = sum(r.collider_offered for r in rows)
    delivered = sum(r.collider_to_ego for r in rows)
    delivered_offered = sum(r.collider_to_ego and r.collider_offered for r in rows)

    def stat(a: np.ndarray, f: Callable[[np.ndarray], Any]) -> float | None:
        return float(f(a)) if len(a) else None

    return {
        "intervals": len(rows),
        "capacity_bytes": rows[0].capacity_bytes if rows else None,
        "objects_offered_median": stat(np.array([r.objects_offered for r in rows]), np.median),
        "objects_wanted_median": stat(np.array([r.objects_wanted for r in rows]), np.median),
        "load_median": stat(load, np.median),
        "load_p90": stat(load, lambda a: np.quantile(a, 0.9)),
        "overloaded_share": stat(load, lambda a: np.mean(a > 1.0)),
        "share_sent_median": stat(share, np.median),
        "collider_offered_intervals": offered,
        "collider_delivered_intervals": delivered,
        "delivery_offered": delivered_offered / offered if offered else None,
        "delivery_all": delivered / len(rows) if rows else None,
    }


def keep_summary(mcap_path: Path, kept: Path) -> None:
    """Write the run's ``load_summary`` to ``kept`` (``KEPT`` beside the MCAP), so the
    report has its figures after the sweep deletes an MCAP over ``mcap_limit_mb``."""
    summary = load_summary(interval_load(mcap_path))
    tmp = kept.with_suffix(".tmp")
    tmp.write_text(json.dumps({"version": SUMMARY_VERSION, "summary": summary}, allow_nan=False))
    tmp.replace(kept)


def kept_summary(kept: Path) -> dict[str, Any] | None:
    """The summary ``keep_summary`` wrote, or None (none there, or from another version)."""
    try:
        got = json.loads(kept.read_text())
        return got["summary"] if got.get("version") == SUMMARY_VERSION else None
    except (OSError, ValueError, KeyError, AttributeError):
        return None


# ---------------------------------------------------------------------------- CLI


def _fmt(x: float | None, spec: str = ".2f") -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def mcap_args(module: str, description: str, json_help: str, argv: list[str] | None) -> argparse.Namespace | None:
    """The command line of a ``python -m deploy.experiments.<module> RUN.mcap [--json]``
    reader, its log set up; None (the error printed) if the MCAP is not a file."""
    ap = argparse.ArgumentParser(prog=f"python -m {module}", description=description)
    ap.add_argument("mcap", type=Path, help="a run's run.mcap")
    ap.add_argument("--json", action="store_true", help=json_help)
    args = ap.parse_args(argv)
    logging.basicConfig(level="INFO", format=f"{module}: %(message)s")
    if not args.mcap.is_file():
        print(f"error: mcap: {args.mcap} is not a file", file=sys.stderr)
        return None
    return args


def main(argv: list[str] | None = None) -> int:
    args = mcap_args("deploy.experiments.load", __doc__.splitlines()[0],
                     "print the summary and every interval as one JSON object", argv)
    if args is None:
        return 2
    t0 = time.perf_counter()
    rows = interval_load(args.mcap)
    took_s = time.perf_counter() - t0
    summary = load_summary(rows)
    if args.json:
        print(json.dumps({"mcap": str(args.mcap), "read_s": round(took_s, 3), "summary": summary,
                          "intervals": [asdict(r) for r in rows]},
                         default=lambda x: None if isinstance(x, float) and math.isnan(x) else x))
        return 0
    if not rows:
        print(f"{args.mcap}: no channel in this run (single or lane scheme): nothing offered")
        return 0
    s = summary
    print(f"{args.mcap}: {s['intervals']} intervals read in {took_s:.2f} s; capacity {s['capacity_bytes']} bytes "
          "an interval")
    print(f"offered load / capacity: median {_fmt(s['load_median'])}, p90 {_fmt(s['load_p90'])}, "
          f"over capacity in {_fmt(None if s['overloaded_share'] is None else 100 * s['overloaded_share'], '.0f')}% "
          "of intervals; "
          f"median share sent {_fmt(s['share_sent_median'])}; objects offered median "
          f"{_fmt(s['objects_offered_median'], '.0f')} ({_fmt(s['objects_wanted_median'], '.0f')} wanted)")
    print(f"collider to the ego: {s['collider_delivered_intervals']} of {s['collider_offered_intervals']} intervals "
          f"it was offered in (delivery {_fmt(s['delivery_offered'])}), {_fmt(s['delivery_all'])} of all intervals")
    print("tick  offered  wanted  bytes offered  load  bytes sent  share sent  collider offered  to ego")
    step = max(1, len(rows) // 8)
    for r in rows[::step]:
        print(f"{r.tick:4d}  {r.objects_offered:7d}  {r.objects_wanted:6d}  {r.bytes_offered:13d}  "
              f"{_fmt(r.load):>4}  {r.bytes_sent:10d}  {_fmt(r.share_sent):>10}  {'yes' if r.collider_offered else 'no':>16}  "
              f"{'yes' if r.collider_to_ego else 'no':>6}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
