"""What a handover costs an event's ego: the collider's visibility in its fused view in
the second around each of its border crossings, against its event's ticks away from
any border (docs/domains.md, "What a handover costs").

    python -m deploy.experiments.handover RUN.mcap [--json]

For each event of a run (its ego, its collider, its window: the ticks its judge
watched, up to the event's ``t_end_s``), from the run's MCAP:

- the ego's **domains** at tick k: the agent's rule (``DomainTable.membership``: every
  domain whose radius plus the guard band holds it, else the nearest) at its true
  position (``world/truth`` of tick k), on the map's domains (``world/map``);
- a **crossing** at tick k: the ego's domains at k differ from those at k - 1 (it
  joined a domain, left one, or both);
- the collider's **points** at tick k: the ego's fused view (``AgentReport.fused_xy`` on
  ``v/<ego>/report``) on the collider's true box plus 0.25 m (``world/truth`` of tick
  k), counted as the judge counts them; **visible**: at least 5 points. These are the
  judge's per-tick figures: over the window they give the record's
  ``collider_visible_share`` and ``collider_points_mean``;
- **around** a crossing at k: ticks k - 5 .. k + 4 of the window (one second, the half
  before the crossing and the half from it); **away**: the window's ticks at least 10
  ticks (one second) from every crossing of the run, so a tick 5 to 9 ticks from a
  crossing is neither;
- the **cost**: the visible share away minus the visible share around (percentage
  points; positive when the ego saw the collider less around its crossings).

A window without a crossing has no "around" ticks; its ticks are all "away".
"""

from __future__ import annotations

import json
import logging
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

AROUND_BEFORE_TICKS = 5  # around a crossing at k: k - 5 ...
AROUND_AFTER_TICKS = 5  # ... to k + 4, one second of 100 ms intervals
AWAY_TICKS = 10  # away: at least this many ticks (one second) from every crossing
VISIBLE_POINTS = 5  # the judge's AWARE_MIN_POINTS
FOOTPRINT_MARGIN_M = 0.25  # the judge's margin around the collider's body
WINDOW_SLACK_S = 1e-6  # a tick at the event's t_end_s is in its window (the judge watched it)


@dataclass(frozen=True, slots=True)
class Crossing:
    tick: int
    joined: tuple[int, ...]
    left: tuple[int, ...]


def crossings(ticks: Sequence[int], domains: Sequence[tuple[int, ...]]) -> list[Crossing]:
    """Ticks at which the domains differ from the previous tick's (``ticks`` ascending,
    ``domains[i]`` the domains at ``ticks[i]``)."""
    out = []
    for i in range(1, len(ticks)):
        before, now = set(domains[i - 1]), set(domains[i])
        if before != now:
            out.append(Crossing(int(ticks[i]), tuple(sorted(now - before)), tuple(sorted(before - now))))
    return out


def around(window: Sequence[int], k: int) -> list[int]:
    """The window's ticks in the second around a crossing at tick ``k``."""
    return [t for t in window if k - AROUND_BEFORE_TICKS <= t < k + AROUND_AFTER_TICKS]


def away(window: Sequence[int], crossing_ticks: Sequence[int]) -> list[int]:
    """The window's ticks at least AWAY_TICKS from every crossing."""
    return [t for t in window if all(abs(t - k) >= AWAY_TICKS for k in crossing_ticks)]


def tally(points: dict[int, int], ticks: Sequence[int]) -> dict[str, int]:
    """Ticks, visible ticks and the points' sum over ``ticks`` (those with a count)."""
    got = [points[t] for t in ticks if t in points]
    return {"ticks": len(got), "visible": sum(n >= VISIBLE_POINTS for n in got), "points": int(sum(got))}


def event_cost(name: str, ego: int, collider: int, ticks: Sequence[int], domains: Sequence[tuple[int, ...]],
               window: Sequence[int], points: dict[int, int]) -> dict[str, Any]:
    """One event's figures: its crossings in the window, each with its tally, the pooled
    tallies around (a tick around two crossings counts once) and away, and the window's."""
    every = crossings(ticks, domains)
    first, last = (window[0], window[-1]) if window else (0, -1)
    inside = [c for c in every if first <= c.tick <= last]
    near = sorted({t for c in inside for t in around(window, c.tick)})
    return {"event": name, "ego": ego, "collider": collider, "window": tally(points, window),
            "crossings": [{"tick": c.tick, "joined": list(c.joined), "left": list(c.left),
                           **tally(points, around(window, c.tick))} for c in inside],
            "crossings_outside": len(every) - len(inside),
            "around": tally(points, near), "away": tally(points, away(window, [c.tick for c in every]))}


# ---------------------------------------------------------------------------- reading a run's log


def run_costs(mcap_path: Path) -> list[dict[str, Any]]:
    """``event_cost`` of every event of a judged run (its ``world/outcome``); empty for a
    run without an outcome or a map."""
    from deploy.experiments.load import raw_messages
    from protocol.codec import decode
    from protocol.messages import AgentReport, MapMsg, Outcome, WorldTruth
    from vehicle_agent.domains import DomainTable

    table = result = None
    truth: dict[int, WorldTruth] = {}
    fused: dict[tuple[int, int], np.ndarray] = {}  # (vid, tick) -> fused view
    unread = 0

    def keep(topic: str) -> bool:  # the map, truth and outcome of the world, each ego's v/<vid>/report
        return topic.endswith(("/world/map", "/world/truth", "/world/outcome", "/report"))

    for _, payload in raw_messages(mcap_path, keep):
        try:
            msg = decode(payload)
        except Exception:  # a malformed payload the recorder kept, an earlier message version
            unread += 1
            continue
        if isinstance(msg, MapMsg):
            table = DomainTable.of(msg)
        elif isinstance(msg, WorldTruth):
            truth[msg.tick] = msg
        elif isinstance(msg, AgentReport):
            fused[(msg.vid, msg.tick)] = msg.fused_xy
        elif isinstance(msg, Outcome):
            result = msg.result
    if unread:
        log.warning("%s: %d messages unreadable; left out", mcap_path, unread)
    if table is None or result is None or not truth:
        log.warning("%s: no %s; no handover figures", mcap_path,
                    "map" if table is None else "outcome" if result is None else "ground truth")
        return []
    events = result.get("events") or [{"event": result.get("scenario", ""), "ego": 0,
                                       "collider": result["vehicles"], "t_end_s": result["t_end_s"]}]
    ticks = sorted(truth)
    out = []
    for e in events:
        ego, collider = int(e["ego"]), int(e["collider"])
        rows = [(k, _row(truth[k], ego), _row(truth[k], collider)) for k in ticks]
        rows = [(k, i, c) for k, i, c in rows if i is not None and c is not None]
        doms = [table.membership(float(truth[k].pose[i, 0]), float(truth[k].pose[i, 1])) for k, i, _ in rows]
        window = [k for k, _, _ in rows if truth[k].t_sim_s <= float(e["t_end_s"]) + WINDOW_SLACK_S]
        points = {k: _collider_points(fused[(ego, k)], truth[k], c) for k, _, c in rows if (ego, k) in fused}
        out.append(event_cost(e["event"], ego, collider, [k for k, _, _ in rows], doms, window, points))
    return out


def _row(truth, vid: int) -> int | None:
    hit = np.flatnonzero(truth.vids == vid)
    return int(hit[0]) if len(hit) else None


def _collider_points(xy: np.ndarray, truth, c: int) -> int:
    from world_server.geometry import count_in_box

    x, y, yaw = (float(v) for v in truth.pose[c])
    length, width = (float(v) for v in truth.size_m[c, :2])
    return int(count_in_box(np.ascontiguousarray(xy, dtype=np.float64), x, y, float(np.cos(yaw)), float(np.sin(yaw)),
                            length / 2 + FOOTPRINT_MARGIN_M, width / 2 + FOOTPRINT_MARGIN_M))


# ---------------------------------------------------------------------------- CLI


def share(t: dict[str, int]) -> float | None:
    return t["visible"] / t["ticks"] if t["ticks"] else None


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.0f}%"


def main(argv: list[str] | None = None) -> int:
    from deploy.experiments.load import mcap_args

    args = mcap_args("deploy.experiments.handover", __doc__.splitlines()[0], "print every event's figures as JSON",
                     argv)
    if args is None:
        return 2
    costs = run_costs(args.mcap)
    if args.json:
        print(json.dumps(costs))
        return 0
    for e in costs:
        w, a, b = e["window"], e["around"], e["away"]
        print(f"{e['event']} (ego {e['ego']}, collider {e['collider']}): window {w['ticks']} ticks, collider visible "
              f"in {_pct(share(w))}; {len(e['crossings'])} crossing{'' if len(e['crossings']) == 1 else 's'} in it"
              + (f" ({e['crossings_outside']} after it)" if e["crossings_outside"] else ""))
        for c in e["crossings"]:
            print(f"  tick {c['tick']}: joined {c['joined'] or '-'}, left {c['left'] or '-'}: visible in "
                  f"{c['visible']} of {c['ticks']} ticks around it")
        print(f"  around: {_pct(share(a))} of {a['ticks']} ticks; away: {_pct(share(b))} of {b['ticks']} ticks")
    return 0


if __name__ == "__main__":
    sys.exit(main())
