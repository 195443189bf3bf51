"""``autocast report SWEEP_DIR``: the paper's tables and plots from a sweep's results.

Reads ``results.jsonl`` (the last record of each run key), ``plan.json`` (what was
planned) and, for the scheduled-delay plot, the MCAPs of runs with a V2V schedule.
Writes into ``SWEEP_DIR/report/`` (``--out``):

- ``outcomes.png``: outcome shares per scheme (paper: "Scenario outcome")
- ``safe_vs_density.png``: safe passage vs connected vehicles per scheme
- ``visibility_vs_density.png``: collider visibility, share of ticks and mean points,
  vs density (paper: "Collider visibility", on red-light violation when it was run)
- ``reaction_closest.png``: reaction time and closest distance per scenario and scheme
- ``scheduled_delay.png``: when each transmitted object arrived in its interval vs its
  reward (paper: "Scheduled delay", 20 vehicles)
- ``load_vs_density.png``: offered load over the channel's capacity, and the collider's
  delivery to the ego beside its visibility, vs density (``deploy.experiments.load``; each run's
  figures cached in ``SWEEP_DIR/report/load/<run id>.json``)
- ``summary.md``: the tables, with "safe passage % by scheme x density", and outcomes
  per event for the runs of a scenario of several events (records with ``events``); for
  the runs of a scenario of several domains, a table per domain
  (``channel_proxy.domain_stats``) and the handover cost per event
  (``deploy.experiments.handover``), each run's figures cached in
  ``SWEEP_DIR/report/network/<run id>.json``

A plot without data says so instead of failing. Exit code 0, or 2 when the directory
holds no sweep.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import os
import statistics
import sys
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from deploy.experiments.plan import PLAN, RESULTS, latest, read_results

log = logging.getLogger("deploy.experiments.report")

OUTCOMES = ("safe", "near_miss", "crash", "deadlock")
SCHEME_ORDER = ("single", "emp", "agnostic", "autocast", "autocast-fptas", "lane")
V2V_SCHEMES = ("agnostic", "autocast", "autocast-fptas")  # a schedule over the V2V channel to plot
SCHEME_COLOR = {"single": "tab:gray", "emp": "tab:blue", "agnostic": "tab:orange", "autocast": "tab:red",
                "autocast-fptas": "tab:pink", "lane": "tab:brown"}
SCHEME_MARKER = {"single": "s", "emp": "D", "agnostic": "^", "autocast": "o", "autocast-fptas": "v", "lane": "x"}
OUTCOME_COLOR = {"safe": "tab:green", "near_miss": "gold", "crash": "tab:red", "deadlock": "tab:purple"}
VISIBILITY_SCENARIO = "red_light"  # the paper's collider-visibility figure uses scenario C
DELAY_VEHICLES = 20  # the paper's scheduled-delay figure: 20 cars
FIGURES = ("outcomes.png", "safe_vs_density.png", "visibility_vs_density.png", "reaction_closest.png",
           "scheduled_delay.png", "load_vs_density.png")
NO_CHANNEL = ("single", "lane")  # schemes without a channel proxy: nothing offered, nothing to load
DEFAULT_MODEL = "ours"  # a record without a "model" field
NETWORK_CACHE_VERSION = 2  # ... when domain_stats' run summary or the handover figures do
PAPER_SAFE = ("Paper (safe passage vs traffic density): Single ~25% at every density; EMP and Agnostic ~60% "
              "on average, falling as density grows; AutoCast 100% up to 20 vehicles, a few near misses at 40.")


# ---------------------------------------------------------------------------- tables (pure)


def schemes_in(records: Iterable[dict[str, Any]]) -> list[str]:
    """The schemes present, in the paper's order (baselines first)."""
    present = {r["scheme"] for r in records}
    return [s for s in SCHEME_ORDER if s in present] + sorted(present - set(SCHEME_ORDER))


def judged(records: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    return [r for r in records if r.get("status") == "judged" and r.get("outcome") in OUTCOMES]


def outcome_counts(records: Sequence[dict[str, Any]]) -> dict[str, Counter]:
    """Per scheme: how many runs ended in each outcome, and how many ``failed``."""
    out: dict[str, Counter] = {s: Counter() for s in schemes_in(records)}
    for r in records:
        out[r["scheme"]][r["outcome"] if r.get("status") == "judged" and r.get("outcome") in OUTCOMES
                         else "failed"] += 1
    return out


def safe_by_density(records: Sequence[dict[str, Any]]) -> dict[tuple[str, int], tuple[int, int]]:
    """(scheme, vehicles) -> (safe runs, judged runs)."""
    out: dict[tuple[str, int], list[int]] = defaultdict(lambda: [0, 0])
    for r in judged(records):
        cell = out[(r["scheme"], r["vehicles"])]
        cell[0] += r["outcome"] == "safe"
        cell[1] += 1
    return {k: (v[0], v[1]) for k, v in out.items()}


@dataclass(frozen=True, slots=True)
class Visibility:
    runs: int
    share_mean: float  # share of ticks the collider was in the ego's fused view (>= 5 points)
    points_mean: float  # collider points in the ego's fused view, mean over ticks
    encounter_mean: float | None = None  # the share over the encounter (judge.py), mean over the runs with it


def visibility_by_density(records: Sequence[dict[str, Any]]) -> dict[tuple[str, int], Visibility]:
    """(scheme, vehicles) -> the collider's visibility in the ego's fused view, mean over runs."""
    groups: dict[tuple[str, int], list[dict[str, Any]]] = defaultdict(list)
    for r in judged(records):
        if r.get("collider_visible_share") is not None:
            groups[(r["scheme"], r["vehicles"])].append(r)
    def encounter(g: list[dict[str, Any]]) -> float | None:
        shares = [r["collider_visible_share_encounter"] for r in g
                  if r.get("collider_visible_share_encounter") is not None]
        return statistics.fmean(shares) if shares else None

    return {k: Visibility(len(g), statistics.fmean(r["collider_visible_share"] for r in g),
                          statistics.fmean(r.get("collider_points_mean") or 0.0 for r in g), encounter(g))
            for k, g in groups.items()}


@dataclass(frozen=True, slots=True)
class ScenarioRow:
    runs: int
    outcomes: Counter
    reaction_mean_s: float  # a run in which the ego never saw the collider in time counts 0 s
    reaction_max_s: float
    closest_mean_m: float
    closest_min_m: float


def per_scenario(records: Sequence[dict[str, Any]]) -> dict[tuple[str, str], ScenarioRow]:
    """(scenario, scheme) -> outcomes, reaction time, closest distance of its judged runs
    (a run of several events by its top-level fields: its worst event's)."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = defaultdict(list)
    for r in judged(records):
        groups[(r["scenario"], r["scheme"])].append(r)
    return {k: _row(g) for k, g in groups.items()}


def per_event(records: Sequence[dict[str, Any]]) -> dict[tuple[str, str, str], ScenarioRow]:
    """(scenario, event, scheme) -> the same figures per event, from the judged runs whose
    record carries ``events`` (a scenario of several events: each entry is one event's)."""
    groups: dict[tuple[str, str, str], list[dict[str, Any]]] = defaultdict(list)
    for r in judged(records):
        for e in r.get("events") or ():
            groups[(r["scenario"], e["event"], r["scheme"])].append(e)
    return {k: _row(g) for k, g in groups.items()}


def _row(g: Sequence[dict[str, Any]]) -> ScenarioRow:
    reaction = [r.get("reaction_time_s") or 0.0 for r in g]
    closest = [r["closest_distance_m"] for r in g]
    return ScenarioRow(len(g), Counter(r["outcome"] for r in g), statistics.fmean(reaction), max(reaction),
                       statistics.fmean(closest), min(closest))


# ---------------------------------------------------------------------------- scheduled delay


@dataclass(frozen=True, slots=True)
class Sent:
    """One object a vehicle transmitted in one interval, as the channel played it."""

    tick: int
    sender: int
    object_id: int
    reward: float  # sum over the sender's receivers of (1 - v) r: H at the interval's first frame
    size_bytes: int
    delay_s: float  # end of its first airtime, from the start of the interval's data phase
    copies: int  # how often it went on air this interval


def schedule_of_run(mcap_path: Path) -> list[Sent]:
    """Every transmitted object of a run: the channel proxy's per-interval record of each
    transmission (``net/stats``: sender, object, start, end of airtime) joined with the
    sender's control message of that interval (``net/ctrl/tx``: the object's v and r).
    Control messages this build cannot read (a log of an earlier message version, say)
    leave their objects out, and the run's count of them is logged as a warning."""
    from deploy.experiments.load import raw_messages
    from protocol import keys
    from protocol.codec import decode
    from protocol.messages import ChannelStats, ControlMsg
    from protocol.security import opened

    offers: dict[tuple[int, int], dict[int, tuple[float, int]]] = {}
    played: dict[tuple[int, int, int], list[float]] = {}
    unread: list[Exception] = []
    def keep(topic: str) -> bool:  # every domain's control messages, the proxy's statistics
        part = keys.net_part(topic)
        return part.startswith("ctrl/tx/") or part == "stats"

    for topic, payload in raw_messages(mcap_path, keep):
        try:
            msg = opened(decode(payload))  # a signed control message: its body
        except Exception as exc:  # a malformed payload the recorder kept; the rest still counts
            if keys.net_part(topic).startswith("ctrl/tx/"):
                unread.append(exc)
            continue
        if isinstance(msg, ControlMsg):
            o = msg.objects
            reward = ((1.0 - o.visibility.astype(np.float64)) * o.relevance).sum(axis=1) if len(o.object_id) else []
            offers.setdefault((msg.tick, msg.vid), {}).update(  # a sender in two domains: both offers
                {int(k): (float(h), int(s)) for k, h, s in zip(o.object_id, reward, o.size_bytes)})
        elif isinstance(msg, ChannelStats):
            for sender, oid, _start_s, rx_s, *_ in (msg.stats.get("data") or {}).get("objects", []):
                played.setdefault((msg.tick, int(sender), int(oid)), []).append(float(rx_s))
    if unread:
        log.warning("%s: %d control messages unreadable (%s); their objects are left out of the delay table",
                    mcap_path, len(unread), unread[0])
    out = []
    for (tick, sender, oid), rx in sorted(played.items()):
        offer = offers.get((tick, sender), {}).get(oid)
        if offer is not None:
            out.append(Sent(tick, sender, oid, offer[0], offer[1], min(rx), len(rx)))
    return out


def delay_runs(records: Sequence[dict[str, Any]], vehicles: int | None, per_scheme: int
               ) -> tuple[int | None, dict[str, list[dict[str, Any]]]]:
    """The density to plot (``vehicles``, else 20 when run, else the densest) and, per V2V
    scheme, up to ``per_scheme`` judged runs at it, in plan order."""
    v2v = [r for r in judged(records) if r["scheme"] in V2V_SCHEMES]
    if not v2v:
        return vehicles, {}
    densities = {r["vehicles"] for r in v2v}
    if vehicles is None:
        vehicles = DELAY_VEHICLES if DELAY_VEHICLES in densities else max(densities)
    out: dict[str, list[dict[str, Any]]] = {}
    for r in v2v:
        if r["vehicles"] == vehicles and len(out.setdefault(r["scheme"], [])) < per_scheme:
            out[r["scheme"]].append(r)
    return vehicles, {s: rs for s, rs in out.items() if rs}


def run_dirs(sweep_dir: Path, plan: dict[str, Any] | None, record: dict[str, Any]) -> list[Path]:
    """Where a run's directory may be: under the sweep (``runs/<run id>``), under the
    plan's ``runs_dir`` (``--runs-dir``, a cluster's shared directory), where the run wrote it."""
    out = [sweep_dir / "runs" / record["run_id"]]
    if (plan or {}).get("runs_dir"):
        out.append(Path(plan["runs_dir"]) / record["run_id"])
    if record.get("run_dir"):
        out.append(Path(record["run_dir"]))
    return out


def mcap_of(sweep_dir: Path, plan: dict[str, Any] | None, record: dict[str, Any]) -> Path | None:
    """A run's MCAP where this machine sees it (in one of ``run_dirs``, or where the
    record says); None if none exists (deleted, or on a worker's own disk)."""
    candidates = [d / "run.mcap" for d in run_dirs(sweep_dir, plan, record)]
    if record.get("mcap"):
        candidates.append(Path(record["mcap"]))
    return next((c for c in candidates if c.is_file()), None)


def missing_mcaps_note(missing: Sequence[dict[str, Any]], plan: dict[str, Any] | None) -> str:
    """Which runs' MCAPs the scheduled-delay plot lacks, and why if the record says."""
    if not missing:
        return ""
    deleted = [r["run_id"] for r in missing if r.get("mcap_deleted_mb")]
    absent = [r for r in missing if not r.get("mcap_deleted_mb")]
    parts = []
    if deleted:
        parts.append(f"{len(deleted)} deleted after the run for their size (`mcap_limit_mb`): {_ids(deleted)}")
    if absent:
        hosts = sorted({r["host"] for r in absent if r.get("host")})
        where = (f" (they ran on {', '.join(hosts)}; their runs directory, "
                 f"`{(plan or {}).get('runs_dir', 'runs/')}`, is not shared with this machine?)" if hosts else "")
        parts.append(f"{len(absent)} not found on this machine{where}: {_ids([r['run_id'] for r in absent])}")
    return (f"scheduled_delay.png lacks the MCAPs of {len(missing)} of the runs chosen for it: "
            + "; ".join(parts) + ".")


def _ids(run_ids: Sequence[str], shown: int = 8) -> str:
    more = f" and {len(run_ids) - shown} more" if len(run_ids) > shown else ""
    return ", ".join(f"`{r}`" for r in run_ids[:shown]) + more


def spearman(x: Sequence[float], y: Sequence[float]) -> float | None:
    """Rank correlation (ties share their mean rank); None when undefined."""
    if len(x) < 3:
        return None
    rx, ry = _ranks(np.asarray(x, float)), _ranks(np.asarray(y, float))
    if rx.std() == 0 or ry.std() == 0:
        return None
    return float(np.corrcoef(rx, ry)[0, 1])


def _ranks(a: np.ndarray) -> np.ndarray:
    order = np.argsort(a, kind="stable")
    ranks = np.empty(len(a))
    ranks[order] = np.arange(len(a), dtype=float)
    for v in np.unique(a):
        tie = a == v
        ranks[tie] = ranks[tie].mean()
    return ranks


DISCRETE_LEVELS = 8  # at most this many distinct rewards: group by value, else by quartile


@dataclass(frozen=True, slots=True)
class RewardGroup:
    label: str  # "1" (a reward value) or "0.12-0.50" (a quartile's range)
    x: float  # where it sits on the plot's reward axis: the value, or the quartile's number
    delays_ms: np.ndarray
    quartile: bool = False


def reward_groups(sent: Sequence[Sent]) -> list[RewardGroup]:
    """Objects grouped by reward, ascending: by value when rewards take few values (with
    boolean relevance H counts the receivers that need the object), else by quartile."""
    if not sent:
        return []
    reward = np.round(np.array([s.reward for s in sent]), 3)
    delay_ms = np.array([s.delay_s * 1e3 for s in sent])
    values = np.unique(reward)
    if len(values) <= DISCRETE_LEVELS:
        return [RewardGroup(f"{v:g}", float(v), delay_ms[reward == v]) for v in values]
    edges = np.quantile(reward, [0.0, 0.25, 0.5, 0.75, 1.0])
    idx = np.clip(np.searchsorted(edges, reward, side="right") - 1, 0, 3)
    return [RewardGroup(f"{edges[q]:.2f}-{edges[q + 1]:.2f}", float(q), delay_ms[idx == q], quartile=True)
            for q in range(4) if np.any(idx == q)]


@dataclass(frozen=True, slots=True)
class DelayRow:
    runs: int
    sent: int
    spearman: float | None  # reward vs delay: negative when higher rewards arrive earlier
    by_reward: tuple[tuple[str, float, int], ...]  # (reward group, median delay ms, objects)


def delay_table(by_scheme: dict[str, tuple[int, list[Sent]]]) -> dict[str, DelayRow]:
    out = {}
    for scheme, (runs, sent) in by_scheme.items():
        groups = tuple((g.label, float(np.median(g.delays_ms)), len(g.delays_ms)) for g in reward_groups(sent))
        out[scheme] = DelayRow(runs, len(sent), spearman([s.reward for s in sent], [s.delay_s for s in sent]), groups)
    return out


# ---------------------------------------------------------------------------- offered load (deploy.experiments.load)


def model_of(record: dict[str, Any]) -> str:
    return record.get("model") or DEFAULT_MODEL


def cached(mcap: Path, cache: Path, version: int, compute: Callable[[Path], Any]) -> Any:
    """``compute(mcap)``, from ``cache`` when it was computed from the same file (path,
    size, mtime) by the same ``version``, else computed and cached."""
    st = mcap.stat()
    stamp = {"version": version, "mcap": str(mcap), "mcap_bytes": st.st_size, "mcap_mtime_ns": st.st_mtime_ns}
    try:
        got = json.loads(cache.read_text())
        if {k: got.get(k) for k in stamp} == stamp:
            return got["summary"]
    except (OSError, ValueError, KeyError, AttributeError):
        pass
    summary = compute(mcap)
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(".tmp")
    tmp.write_text(json.dumps({**stamp, "summary": summary}, allow_nan=False))
    tmp.replace(cache)
    return summary


def run_load(mcap: Path, cache: Path) -> dict[str, Any]:
    """``deploy.experiments.load.load_summary`` of a run's MCAP, cached (``cached``)."""
    from deploy.experiments import load

    return cached(mcap, cache, load.SUMMARY_VERSION, lambda m: load.load_summary(load.interval_load(m)))


def _read_one(read: Callable[[Path, Path], dict[str, Any]], mcap: Path, cache: Path
              ) -> tuple[dict[str, Any] | None, str | None]:
    try:
        return read(mcap, cache), None
    except Exception as exc:
        return None, str(exc)


def _per_run(sweep_dir: Path, plan: dict[str, Any] | None, records: Sequence[dict[str, Any]],
             wanted: Callable[[dict[str, Any]], bool], read: Callable[[Path, Path], dict[str, Any]],
             cache_dir: Path, what: str) -> tuple[list[tuple[dict[str, Any], dict[str, Any]]], list[dict[str, Any]]]:
    """(record, ``read(mcap, cache_dir / "<run id>.json")``) of every judged run ``wanted``
    whose MCAP is here, and the records of those whose MCAP is not or could not be read (a
    truncated or foreign log: ``what`` is logged as not read and the report goes on without
    it). ``read``, a module-level function, runs in a process per core: a sweep's logs are
    read once, each on its own, and a cached run is a file read."""
    found, missing = [], []
    for r in judged(records):
        if not wanted(r):
            continue
        mcap = mcap_of(sweep_dir, plan, r)
        if mcap is None:
            missing.append(r)
        else:
            found.append((r, mcap))
    args = ([read] * len(found), [m for _, m in found], [cache_dir / f"{r['run_id']}.json" for r, _ in found])
    workers = min(os.cpu_count() or 1, len(found))
    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            results = list(pool.map(_read_one, *args, chunksize=max(1, len(found) // (8 * workers))))
    else:
        results = [_read_one(*a) for a in zip(*args)]
    got = []
    for (r, mcap), (value, error) in zip(found, results):
        if error is None:
            got.append((r, value))
        else:
            log.warning("%s: %s not read: %s", mcap, what, error)
            missing.append(r)
    return got, missing


def load_of_runs(sweep_dir: Path, plan: dict[str, Any] | None, records: Sequence[dict[str, Any]], cache_dir: Path
                 ) -> tuple[list[tuple[dict[str, Any], dict[str, Any]]], list[dict[str, Any]]]:
    """(record, load summary) of every judged run with a channel whose MCAP is here, and
    the records of those whose MCAP is not (or could not be read)."""
    from deploy.experiments import load

    got, missing = _per_run(sweep_dir, plan, records, lambda r: r["scheme"] not in NO_CHANNEL, run_load, cache_dir,
                            "offered load")
    still = []
    for r in missing:  # an MCAP the sweep deleted for its size: the summary it kept first
        kept = next((s for d in run_dirs(sweep_dir, plan, r) if (s := load.kept_summary(d / load.KEPT))), None)
        if kept is not None:
            got.append((r, kept))
        else:
            still.append(r)
    return [(r, summary) for r, summary in got if summary["intervals"]], still


@dataclass(frozen=True, slots=True)
class LoadCell:
    runs: int
    load_median: float | None  # median over runs of each run's median offered load / capacity
    overloaded_share: float | None  # intervals with load > 1, pooled over the runs
    share_sent_median: float | None  # median over runs of each run's median share sent
    delivery_offered: float | None  # intervals with a copy of the collider at the ego / intervals it was offered
    delivery_all: float | None  # the same over every interval
    visibility: float | None  # the records' collider_visible_share, mean over the runs


def load_by_density(pairs: Sequence[tuple[dict[str, Any], dict[str, Any]]]) -> dict[tuple[str, str, int], LoadCell]:
    """(model, scheme, vehicles) -> the load and the collider's delivery over its runs."""
    groups: dict[tuple[str, str, int], list[tuple[dict[str, Any], dict[str, Any]]]] = defaultdict(list)
    for r, s in pairs:
        groups[(model_of(r), r["scheme"], r["vehicles"])].append((r, s))

    def median(xs: Iterable[float | None]) -> float | None:
        xs = [x for x in xs if x is not None]
        return statistics.median(xs) if xs else None

    out = {}
    for k, g in groups.items():
        with_load = [s for _, s in g if s.get("load_median") is not None]
        intervals = sum(s["intervals"] for s in with_load)
        offered = sum(s["collider_offered_intervals"] for _, s in g)
        delivered = sum(s["collider_delivered_intervals"] for _, s in g)
        total = sum(s["intervals"] for _, s in g)
        vis = [r["collider_visible_share"] for r, _ in g if r.get("collider_visible_share") is not None]
        out[k] = LoadCell(
            len(g), median(s["load_median"] for s in with_load),
            sum(s["overloaded_share"] * s["intervals"] for s in with_load) / intervals if intervals else None,
            median(s["share_sent_median"] for s in with_load),
            delivered / offered if offered else None, delivered / total if total else None,
            statistics.fmean(vis) if vis else None)
    return out


def load_table_md(cells: dict[tuple[str, str, int], LoadCell]) -> list[str]:
    """Rows by scheme then density; a model column only when the sweep holds more than one."""
    models = sorted({m for m, _, _ in cells})
    several = len(models) > 1

    def pct(x: float | None) -> str:
        return "-" if x is None else f"{100 * x:.0f}%"

    def num(x: float | None) -> str:
        return "-" if x is None else f"{x:.2f}"

    rows = []
    for (m, s, n), c in sorted(cells.items(), key=lambda kv: (kv[0][0], _order(kv[0][1]), kv[0][2])):
        rows.append([*([m] if several else []), s, n, c.runs, num(c.load_median), pct(c.overloaded_share),
                     num(c.share_sent_median), pct(c.delivery_offered), pct(c.delivery_all), pct(c.visibility)])
    return _md([*(["model"] if several else []), "scheme", "vehicles", "runs", "offered load / capacity (median)",
                "intervals over capacity", "share sent (median)", "collider delivery (intervals offered)",
                "collider delivery (all intervals)", "collider visibility"], rows)


# ---------------------------------------------------------------------------- several domains


@functools.cache
def several_domains(scenario: str) -> bool:
    """Whether the scenario's map declares several scheduler domains (docs/domains.md)."""
    from world_server.scenarios import ScenarioParams, builder_of

    try:
        return len(builder_of(scenario)(ScenarioParams(scenario=scenario)).roadmap.domains) > 1
    except Exception as exc:  # a name this build does not know, a plugin that wants other parameters
        log.info("scenario %s: not built (%s); counted as one domain", scenario, exc)
        return False


def run_network(mcap: Path, cache: Path) -> dict[str, Any]:
    """A network run's per-domain summary (``channel_proxy.domain_stats.read_summary``; None
    without a V2V channel) and its events' handover figures
    (``deploy.experiments.handover.run_costs``), cached (``cached``)."""
    from channel_proxy import domain_stats
    from deploy.experiments import handover

    def compute(m: Path) -> dict[str, Any]:
        domains = domain_stats.read_summary(m)
        return {"domains": domains if domains["intervals"] else None, "handover": handover.run_costs(m)}

    return cached(mcap, cache, NETWORK_CACHE_VERSION, compute)


def network_of_runs(sweep_dir: Path, plan: dict[str, Any] | None, records: Sequence[dict[str, Any]],
                    cache_dir: Path) -> tuple[list[tuple[dict[str, Any], dict[str, Any]]], list[dict[str, Any]]]:
    """(record, ``run_network``) of every judged run of a scenario of several domains whose
    MCAP is here, and the records of those whose MCAP is not (or could not be read)."""
    return _per_run(sweep_dir, plan, records, lambda r: several_domains(r["scenario"]), run_network, cache_dir,
                    "per-domain figures")


@dataclass(frozen=True, slots=True)
class DomainCell:
    runs: int
    channel: int
    intervals: int  # pooled over the runs
    members_median: float  # members per interval, pooled over the runs' intervals
    members_max: int
    joined_per_run: float  # vehicles that joined the domain, mean over the runs
    left_per_run: float
    load_median: float  # bytes on the air per interval over the capacity, pooled over the intervals
    load_max: float
    transmissions: int
    collided: int
    ctrl_sent: int | None = None  # control messages sent in the domain; None: a run's figures lack them
    ctrl_dropped: int | None = None  # ... that its channel's control pool had no room for


def domain_cells(pairs: Sequence[tuple[dict[str, Any], dict[str, Any]]]
                 ) -> dict[tuple[str, str, str, int, int], DomainCell]:
    """(model, scenario, scheme, vehicles, domain) -> its figures over the runs with a V2V
    channel (a run without one, Single's or EMP's, has no domains)."""
    groups: dict[tuple[str, str, str, int, int], list[tuple[dict[str, Any], int]]] = defaultdict(list)
    for r, net in pairs:
        summary = net.get("domains") or {}
        for d, ds in (summary.get("domains") or {}).items():
            key = (model_of(r), r["scenario"], r["scheme"], r["vehicles"], int(d))
            groups[key].append((ds, summary["capacity_bytes"]))
    out = {}
    for k, g in groups.items():
        members = np.concatenate([np.asarray(ds["members"], dtype=np.int64) for ds, _ in g])
        load = np.concatenate([np.asarray(ds["offered_bytes"], dtype=np.float64) / cap for ds, cap in g])
        out[k] = DomainCell(len(g), g[0][0]["channel"], len(members), float(np.median(members)), int(members.max()),
                            statistics.fmean(ds["joined"] for ds, _ in g),
                            statistics.fmean(ds["left"] for ds, _ in g), float(np.median(load)), float(load.max()),
                            sum(ds["transmissions"] for ds, _ in g), sum(ds["collided"] for ds, _ in g),
                            *_ctrl_counts([ds for ds, _ in g]))
    return out


def _ctrl_counts(summaries: list[dict[str, Any]]) -> tuple[int | None, int | None]:
    """The domain's control messages sent and dropped over the runs; (None, None) if a
    run's summary lacks them (one made before ``domain_stats`` counted them)."""
    if not all("ctrl_sent" in ds and "ctrl_dropped" in ds for ds in summaries):
        return None, None
    return sum(ds["ctrl_sent"] for ds in summaries), sum(ds["ctrl_dropped"] for ds in summaries)


def domain_table_md(cells: dict[tuple[str, str, str, int, int], DomainCell]) -> list[str]:
    """Rows by scenario, scheme, density, domain; a model column only when there are several."""
    several = len({k[0] for k in cells}) > 1
    rows = []
    for (m, sc, s, n, d), c in sorted(cells.items(), key=lambda kv: (kv[0][0], kv[0][1], _order(kv[0][2]),
                                                                     *kv[0][3:])):
        rows.append([*([m] if several else []), sc, s, n, d, c.channel, c.runs,
                     f"{c.members_median:g} ({c.members_max})", f"{c.joined_per_run:.1f}", f"{c.left_per_run:.1f}",
                     f"{c.load_median:.2f} ({c.load_max:.2f})",
                     _pct(c.collided, c.transmissions),
                     "-" if c.ctrl_sent is None else _pct(c.ctrl_dropped, c.ctrl_sent)])
    return _md([*(["model"] if several else []), "scenario", "scheme", "vehicles", "domain", "channel", "runs",
                "members per interval, median (max)", "joined per run", "left per run",
                "load per interval, median (max)", "collided (of transmissions)",
                "control dropped (of sent)"], rows)


@dataclass(frozen=True, slots=True)
class HandoverCell:
    runs: int
    crossed: int  # runs whose event ego crossed a border during its event
    crossings: int
    around: dict[str, int]  # ticks, visible, points: pooled over the runs
    away: dict[str, int]

    @property
    def cost(self) -> float | None:
        """Visible share away minus around (positive: seen less around the crossings)."""
        from deploy.experiments.handover import share

        a, b = share(self.around), share(self.away)
        return None if a is None or b is None else b - a


def handover_cells(pairs: Sequence[tuple[dict[str, Any], dict[str, Any]]]
                   ) -> dict[tuple[str, str, str, str, int], HandoverCell]:
    """(model, scenario, event, scheme, vehicles) -> the collider's visibility around the
    event ego's border crossings and away from them, pooled over the runs' ticks."""
    groups: dict[tuple[str, str, str, str, int], list[dict[str, Any]]] = defaultdict(list)
    for r, net in pairs:
        for e in net.get("handover") or ():
            groups[(model_of(r), r["scenario"], e["event"], r["scheme"], r["vehicles"])].append(e)

    def pool(g: list[dict[str, Any]], part: str) -> dict[str, int]:
        return {f: sum(e[part][f] for e in g) for f in ("ticks", "visible", "points")}

    return {k: HandoverCell(len(g), sum(bool(e["crossings"]) for e in g), sum(len(e["crossings"]) for e in g),
                            pool(g, "around"), pool(g, "away")) for k, g in groups.items()}


def handover_table_md(cells: dict[tuple[str, str, str, str, int], HandoverCell]) -> list[str]:
    several = len({k[0] for k in cells}) > 1

    def seen(t: dict[str, int]) -> str:
        return f"{_pct(t['visible'], t['ticks'])}, {t['points'] / t['ticks']:.0f} pts" if t["ticks"] else "-"

    rows = []
    for (m, sc, ev, s, n), c in sorted(cells.items(), key=lambda kv: (kv[0][0], kv[0][1], kv[0][2],
                                                                      _order(kv[0][3]), kv[0][4])):
        rows.append([*([m] if several else []), sc, ev, s, n, c.runs, c.crossed, c.crossings, seen(c.around),
                     seen(c.away), "-" if c.cost is None else f"{100 * c.cost:+.0f}"])
    return _md([*(["model"] if several else []), "scenario", "event", "scheme", "vehicles", "runs",
                "runs whose ego crossed", "crossings", "visible around a crossing (ticks), mean points",
                "visible away from any (ticks), mean points", "cost (away - around, % points)"], rows)


# ---------------------------------------------------------------------------- plots


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _n(count: int, noun: str) -> str:
    return f"{count} {noun}{'' if count == 1 else 's'}"


def _density_limits(densities: Sequence[int]) -> tuple[float, float]:
    pad = 0.08 * ((max(densities) - min(densities)) or 10)
    return min(densities) - pad, max(densities) + pad


def _dodge(xs: Sequence[int], i: int, k: int, densities: Sequence[int]) -> list[float]:
    """Shift scheme i of k sideways by a little, so equal values do not hide each other."""
    span = (max(densities) - min(densities)) or 10
    return [x + (i - (k - 1) / 2) * 0.012 * span for x in xs]


def _no_data(ax, what: str) -> None:
    ax.text(0.5, 0.5, f"no data: {what}", ha="center", va="center", transform=ax.transAxes, fontsize=11,
            color="0.35")
    ax.set_xticks([])
    ax.set_yticks([])


def _save(fig, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)


def plot_outcomes(records: Sequence[dict[str, Any]], path: Path) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    counts = outcome_counts(records)
    schemes = [s for s in counts if sum(counts[s][o] for o in OUTCOMES)]
    if not schemes:
        _no_data(ax, "no judged runs")
    else:
        x = np.arange(len(schemes))
        bottom = np.zeros(len(schemes))
        for o in OUTCOMES:
            share = np.array([100.0 * counts[s][o] / sum(counts[s][q] for q in OUTCOMES) for s in schemes])
            ax.bar(x, share, bottom=bottom, color=OUTCOME_COLOR[o], label=o.replace("_", " "), width=0.6)
            for xi, b, h in zip(x, bottom, share):
                if h >= 6:
                    ax.text(xi, b + h / 2, f"{h:.0f}%", ha="center", va="center", fontsize=8)
            bottom += share
        labels = [f"{s}\n{_n(sum(counts[s][o] for o in OUTCOMES), 'run')}" + (f", {counts[s]['failed']} failed"
                                                                        if counts[s]["failed"] else "")
                  for s in schemes]
        ax.set_xticks(x, labels)
        ax.set_ylim(0, 100)
        ax.set_ylabel("share of judged runs (%)")
        ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
    ax.set_title("Scenario outcome per scheme (all scenarios, speeds, deltas, densities)")
    _save(fig, path)


def plot_safe_vs_density(records: Sequence[dict[str, Any]], path: Path) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    table = safe_by_density(records)
    if not table:
        _no_data(ax, "no judged runs")
    else:
        densities = sorted({n for _, n in table})
        schemes = schemes_in(judged(records))
        for i, s in enumerate(schemes):
            xs = [n for n in densities if (s, n) in table]
            ys = [100.0 * table[(s, n)][0] / table[(s, n)][1] for n in xs]
            ax.plot(_dodge(xs, i, len(schemes), densities), ys, "-", marker=SCHEME_MARKER.get(s, "o"),
                    color=SCHEME_COLOR.get(s), label=s, lw=2, alpha=0.85)
        ax.set_xticks(densities)
        ax.set_xlim(*_density_limits(densities))
        ax.set_ylim(-3, 103)
        ax.set_xlabel("connected vehicles in range")
        ax.set_ylabel("safe passage (% of judged runs)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    ax.set_title("Safe passage vs traffic density")
    _save(fig, path)


def visibility_records(records: Sequence[dict[str, Any]]) -> tuple[list[dict[str, Any]], str]:
    """Red-light violation's runs when the sweep ran it (as the paper's figure), else all."""
    red = [r for r in records if r["scenario"] == VISIBILITY_SCENARIO]
    return (red, VISIBILITY_SCENARIO) if judged(red) else (list(records), "all scenarios")


def plot_visibility(records: Sequence[dict[str, Any]], path: Path) -> None:
    plt = _pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.5))
    chosen, which = visibility_records(records)
    table = visibility_by_density(chosen)
    if not table:
        _no_data(a, "no judged runs")
        _no_data(b, "no judged runs")
    else:
        densities = sorted({n for _, n in table})
        schemes = schemes_in(judged(chosen))
        for i, s in enumerate(schemes):
            xs = [n for n in densities if (s, n) in table]
            style = {"marker": SCHEME_MARKER.get(s, "o"), "color": SCHEME_COLOR.get(s), "label": s, "alpha": 0.85}
            a.plot(_dodge(xs, i, len(schemes), densities), [100.0 * table[(s, n)].share_mean for n in xs], "-",
                   **style)
            b.plot(_dodge(xs, i, len(schemes), densities), [table[(s, n)].points_mean for n in xs], "-", **style)
        for ax in (a, b):
            ax.set_xticks(densities)
            ax.set_xlim(*_density_limits(densities))
            ax.set_xlabel("connected vehicles in range")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        a.set_ylim(-3, 103)
        a.set_ylabel("ticks with the collider in view (%)")
        b.set_ylim(bottom=0)
        b.set_ylabel("collider points in view (mean over ticks)")
    a.set_title(f"Collider visible time vs density ({which})")
    b.set_title(f"Collider visible size vs density ({which})")
    fig.suptitle("Collider visibility in the ego's fused view (own + received points; Single: own LiDAR)",
                 fontsize=10)
    _save(fig, path)


def plot_reaction_closest(records: Sequence[dict[str, Any]], path: Path) -> None:
    plt = _pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.5))
    table = per_scenario(records)
    if not table:
        _no_data(a, "no judged runs")
        _no_data(b, "no judged runs")
    else:
        scenarios = sorted({sc for sc, _ in table})
        schemes = schemes_in(judged(records))
        width = 0.8 / len(schemes)
        for i, s in enumerate(schemes):
            x = np.arange(len(scenarios)) + (i - (len(schemes) - 1) / 2) * width
            rows = [table.get((sc, s)) for sc in scenarios]
            has = [r is not None for r in rows]
            xs = x[has]
            got = [r for r in rows if r is not None]
            a.bar(xs, [r.reaction_mean_s for r in got], width, color=SCHEME_COLOR.get(s), label=s)
            a.errorbar(xs, [r.reaction_mean_s for r in got],
                       yerr=[[0] * len(got), [r.reaction_max_s - r.reaction_mean_s for r in got]],
                       fmt="none", ecolor="k", capsize=2, lw=0.8)
            b.bar(xs, [r.closest_mean_m for r in got], width, color=SCHEME_COLOR.get(s), label=s)
            b.plot(xs, [r.closest_min_m for r in got], "v", color="k", ms=5)
        for ax in (a, b):
            ax.set_xticks(np.arange(len(scenarios)), scenarios)
            ax.grid(alpha=0.3, axis="y")
            ax.legend(fontsize=8)
        a.set_ylabel("reaction time (s): mean, bar to max")
        b.axhline(2.0, color="k", ls="--", lw=1)
        b.text(-0.45, 2.1, "near miss < 2 m", fontsize=8)
        b.set_ylabel("closest distance (m): mean, triangle = min")
    a.set_title("Reaction time per scenario (never aware in time = 0 s)")
    b.set_title("Closest distance ego-collider per scenario")
    _save(fig, path)


def plot_scheduled_delay(by_scheme: dict[str, tuple[int, list[Sent]]], vehicles: int | None, path: Path,
                         why_empty: str) -> None:
    plt = _pyplot()
    schemes = [s for s in SCHEME_ORDER if s in by_scheme] or ["-"]
    fig, axes = plt.subplots(1, len(schemes), figsize=(max(8.0, 5.5 * len(schemes)), 4.8), squeeze=False,
                             sharey=True)
    for ax, s in zip(axes[0], schemes):
        runs, sent = by_scheme.get(s, (0, []))
        if not sent:
            _no_data(ax, why_empty if s == "-" else f"{s}: no transmissions")
            continue
        groups = reward_groups(sent)
        xs = [g.x for g in groups]
        step = min(np.diff(xs)) if len(xs) > 1 else 1.0
        ax.boxplot([g.delays_ms for g in groups], positions=xs, widths=0.5 * step, whis=(5, 95), showfliers=False,
                   manage_ticks=False, medianprops={"color": "k", "lw": 2})
        rng = np.random.default_rng(0)
        for g in groups:
            jitter = rng.uniform(-0.2, 0.2, len(g.delays_ms)) * step
            ax.scatter(g.x + jitter, g.delays_ms, s=6, alpha=0.25, color=SCHEME_COLOR.get(s), edgecolors="none")
            ax.text(g.x, 101, f"n={len(g.delays_ms)}", ha="center", va="bottom", fontsize=7)
        ax.set_xticks(xs, [g.label for g in groups])
        ax.set_xlim(xs[0] - 0.6 * step, xs[-1] + 0.6 * step)
        ax.set_ylim(0, 108)
        ax.set_xlabel("object reward H = sum over receivers of (1 - v) r" + (" (quartiles)" if groups[0].quartile
                                                                           else ""))
        ax.grid(alpha=0.3)
        ax.set_title(f"{s}: {_n(len(sent), 'object')} sent, {_n(runs, 'run')}")
    axes[0][0].set_ylabel("scheduled delay (ms from the interval's start)")
    fig.suptitle(f"Scheduled delay vs reward{f' ({vehicles} vehicles)' if vehicles else ''}\n"
                 "when each transmitted object arrived in its 100 ms interval", fontsize=10)
    _save(fig, path)


MODEL_MARKERS = ("o", "s", "^", "D", "v", "x")


def plot_load(cells: dict[tuple[str, str, int], LoadCell], path: Path, why_empty: str) -> None:
    plt = _pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.8))
    if not cells:
        _no_data(a, why_empty)
        _no_data(b, why_empty)
    else:
        densities = sorted({n for _, _, n in cells})
        models = sorted({m for m, _, _ in cells})
        several = len(models) > 1
        lines = sorted({(m, s) for m, s, _ in cells}, key=lambda ms: (ms[0], _order(ms[1])))
        loads = []
        for i, (m, s) in enumerate(lines):
            xs = [n for n in densities if (m, s, n) in cells]
            x = dict(zip(xs, _dodge(xs, i, len(lines), densities)))
            marker = MODEL_MARKERS[models.index(m) % len(MODEL_MARKERS)] if several else SCHEME_MARKER.get(s, "o")
            style = {"marker": marker, "color": SCHEME_COLOR.get(s), "alpha": 0.85}
            name = f"{s} ({m})" if several else s
            with_load = [n for n in xs if cells[(m, s, n)].load_median is not None]
            if with_load:
                ys = [cells[(m, s, n)].load_median for n in with_load]
                loads += ys
                a.plot([x[n] for n in with_load], ys, "-", label=name, **style)
            got = [n for n in xs if cells[(m, s, n)].delivery_offered is not None]
            b.plot([x[n] for n in got], [100 * cells[(m, s, n)].delivery_offered for n in got], "-",
                   label=f"{name}: delivered", **style)
            seen = [n for n in xs if cells[(m, s, n)].visibility is not None]
            b.plot([x[n] for n in seen], [100 * cells[(m, s, n)].visibility for n in seen], ":",
                   label=f"{name}: visible", mfc="none", **style)
        a.axhline(1.0, color="k", ls="--", lw=1)
        if loads and min(loads) > 0:
            a.set_yscale("log")  # loads span orders of magnitude from 5 to 40 vehicles
        if not loads:
            _no_data(a, "no V2V run (EMP has no control messages)")
        for ax in (a, b):
            ax.set_xticks(densities)
            ax.set_xlim(*_density_limits(densities))
            ax.set_xlabel("connected vehicles in range")
            ax.grid(alpha=0.3)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7)
        a.set_ylabel("bytes offered / channel capacity (median interval)")
        b.set_ylim(-3, 103)
        b.set_ylabel("% of intervals")
    a.set_title("Offered load vs density (dashed: the channel's capacity)")
    b.set_title("Collider delivered to the ego (of intervals offered)\nand visible in its fused view (dotted)")
    _save(fig, path)


# ---------------------------------------------------------------------------- summary.md


def _pct(num: int, den: int) -> str:
    return f"{100.0 * num / den:.0f}% ({num}/{den})" if den else "-"


def _md(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return out


def safe_table_md(records: Sequence[dict[str, Any]]) -> list[str]:
    """Safe-passage % by scheme x density (rows schemes, columns vehicle counts, then all)."""
    table = safe_by_density(records)
    densities = sorted({n for _, n in table})
    rows = []
    for s in schemes_in(judged(records)):
        cells = [_pct(*table[(s, n)]) if (s, n) in table else "-" for n in densities]
        total = [table[(s, n)] for n in densities if (s, n) in table]
        rows.append([s, *cells, _pct(sum(t[0] for t in total), sum(t[1] for t in total))])
    return _md(["scheme", *[f"{n} vehicles" for n in densities], "all"], rows)


def _outcome_cells(row: ScenarioRow) -> list[Any]:
    return [row.runs, *[row.outcomes[o] for o in OUTCOMES], f"{row.reaction_mean_s:.2f}", f"{row.closest_mean_m:.2f}",
            f"{row.closest_min_m:.2f}"]


OUTCOME_COLUMNS = ("judged", *[o.replace("_", " ") for o in OUTCOMES], "reaction mean (s)", "closest mean (m)",
                   "closest min (m)")


def per_scenario_md(records: Sequence[dict[str, Any]]) -> list[str]:
    table = per_scenario(records)
    return _md(["scenario", "scheme", *OUTCOME_COLUMNS],
               [[sc, s, *_outcome_cells(row)]
                for (sc, s), row in sorted(table.items(), key=lambda kv: (kv[0][0], _order(kv[0][1])))])


def per_event_md(records: Sequence[dict[str, Any]]) -> list[str]:
    """Rows by scenario, then its events in the records' order, then scheme."""
    table = per_event(records)
    order: dict[tuple[str, str], int] = {}
    for r in judged(records):
        for e in r.get("events") or ():
            order.setdefault((r["scenario"], e["event"]), len(order))
    return _md(["scenario", "event", "scheme", *OUTCOME_COLUMNS],
               [[sc, ev, s, *_outcome_cells(row)]
                for (sc, ev, s), row in sorted(table.items(), key=lambda kv: (kv[0][0], order[kv[0][:2]],
                                                                               _order(kv[0][2])))])


def coverage(records: Sequence[dict[str, Any]], plan: dict[str, Any] | None) -> str:
    """What the directory holds against its last plan. A directory can hold several plans'
    runs (a sweep widened or narrowed later, e.g. more densities for one scenario), and
    ``plan.json`` is the last one: runs are counted by key, not by number."""
    n_judged = len(judged(records))
    text = f"{len(records)} runs recorded ({n_judged} judged, {len(records) - n_judged} failed)"
    if not plan or not plan.get("runs"):
        return text + "."
    planned = {r["run_key"] for r in plan["runs"]}
    recorded = {r["run_key"] for r in records}
    text += (f"; the last plan (`plan.json`, git revision {plan.get('git_revision', 'unknown')}) has "
             f"{len(planned)} runs, {len(planned - recorded)} of them not run yet")
    earlier = len(recorded - planned)
    return text + (f"; {earlier} recorded runs are from earlier plans." if earlier else ".")


def summary_md(sweep_dir: Path, records: Sequence[dict[str, Any]], plan: dict[str, Any] | None,
               delay: dict[str, DelayRow], delay_vehicles: int | None, delay_note: str,
               load: dict[tuple[str, str, int], LoadCell] | None = None, load_note: str = "",
               network: Sequence[tuple[dict[str, Any], dict[str, Any]]] | None = None,
               network_note: str = "") -> str:
    name = (plan or {}).get("spec", {}).get("name", sweep_dir.name)
    lines = [f"# Sweep report: {name}", "",
             f"`{sweep_dir}`: {coverage(records, plan)} Report written {time.strftime('%Y-%m-%d %H:%M')}.", "",
             "Figures: " + ", ".join(f"[{f}]({f})" for f in FIGURES) + ".", "",
             "Shares are of judged runs; failed runs (no outcome) are counted apart.", ""]
    models = sorted({r.get("model") or "ours" for r in records})
    lines += [f"Model{'s' if len(models) > 1 else ''}: {', '.join(models)} (docs/models.md)"
              + (": the tables pool them, but the offered-load table keeps them apart." if len(models) > 1 else "."),
              ""]

    lines += ["## Outcome shares per scheme", ""]
    counts = outcome_counts(records)
    lines += _md(["scheme", "judged", *[o.replace("_", " ") for o in OUTCOMES], "failed"],
                 [[s, sum(c[o] for o in OUTCOMES), *[_pct(c[o], sum(c[q] for q in OUTCOMES)) for o in OUTCOMES],
                   c["failed"]] for s, c in counts.items()])
    lines += ["", "## Safe-passage % by scheme x density", ""]
    lines += safe_table_md(records)
    lines += ["", PAPER_SAFE, ""]

    chosen, which = visibility_records(records)
    vis = visibility_by_density(chosen)
    densities = sorted({n for _, n in vis})
    lines += [f"## Collider visibility by scheme x density ({which})", "",
              "Share of ticks with the collider in the ego's fused view (at least 5 of its points), and its "
              "mean points per tick; Single's view is its own LiDAR. In brackets the share over the encounter "
              "alone: the ticks before the ego or the collider had passed the conflict point.", ""]

    def cell(v: Visibility) -> str:
        during = f" ({100 * v.encounter_mean:.0f}%)" if v.encounter_mean is not None else ""
        return f"{100 * v.share_mean:.0f}%{during} / {v.points_mean:.0f} pts"

    lines += _md(["scheme", *[f"{n} vehicles" for n in densities]],
                 [[s, *[cell(vis[(s, n)]) if (s, n) in vis else "-" for n in densities]]
                  for s in schemes_in(judged(chosen))])

    lines += ["", "## Per scenario: outcomes, reaction time, closest distance", "",
              "Reaction time: from the ego's first view of the collider to the last moment braking could still "
              "stop it; a run in which that never happened counts 0 s. A run of several events counts as its "
              "worst event (below, each event apart).", ""]
    lines += per_scenario_md(records)
    if per_event(records):
        lines += ["", "## Per event: runs of several events", "",
                  "Each event of a scenario with several (docs/domains.md) judged on its own: its ego, its "
                  "collider, its conflict point.", ""]
        lines += per_event_md(records)

    lines += ["", f"## Scheduled delay vs reward ({f'{delay_vehicles} vehicles' if delay_vehicles else 'no V2V runs'})",
              "", delay_note, ""]
    if delay:
        lines += _md(["scheme", "runs", "objects sent", "Spearman(reward, delay)",
                      "median delay by reward: reward -> ms (objects)"],
                     [[s, d.runs, d.sent, "-" if d.spearman is None else f"{d.spearman:+.2f}",
                       "; ".join(f"{label} -> {ms:.1f} ({n})" for label, ms, n in d.by_reward)]
                      for s, d in delay.items()])
    lines += ["", "## Offered load and the collider's delivery by scheme x density", "",
              "From each judged run's MCAP (`python -m deploy.experiments.load`): per interval, the bytes of every object in "
              "the senders' control messages over the data channel's capacity (B N T_n / 8), the share of them "
              "put on the air, and whether the ego decoded a copy of the collider. Load and share sent: median "
              "over runs of each run's median interval; delivery: intervals in which the ego decoded the collider "
              "over those in which a sender offered it (and over all); visibility: `collider_visible_share`, "
              "mean over the same runs. EMP has no control messages: no load; its delivery counts relayed "
              "segments with at least 5 of the collider's points.", ""]
    if load:
        lines += load_table_md(load)
    if load_note:
        lines += ["", load_note]
    if network is not None:
        lines += network_md(network, network_note)
    failed = [r for r in records if r.get("status") != "judged"]
    if failed:
        lines += ["", "## Failed runs", ""]
        lines += _md(["run", "exit code", "failure"],
                     [[r["run_id"], r.get("exit_code"), str((r.get("error") or {}).get("failure", "")).replace("|", "/")]
                      for r in failed])
    dead = [r for r in judged(records) if r.get("dead_agents")]
    if dead:
        lines += ["", "## Judged runs with dead agents", "",
                  "An agent the world declared dead drove with the failsafe brake from then on.", ""]
        lines += _md(["run", "dead agents"], [[r["run_id"], json.dumps(r["dead_agents"])] for r in dead])
    return "\n".join(lines) + "\n"


def network_md(pairs: Sequence[tuple[dict[str, Any], dict[str, Any]]], note: str) -> list[str]:
    """The sections of a sweep with runs of several domains: per domain, and the handover cost."""
    lines = ["", "## Per domain: members, handovers, load, collisions", "",
             "Runs of a scenario of several domains (docs/domains.md), from each judged run's MCAP "
             "(`python -m channel_proxy.domain_stats RUN_DIR`): a domain's members per interval (the vehicles "
             "that sent their control message in it; an interval without any counts 0), median and max over "
             "every interval of the runs; the vehicles that joined and left it, mean per run; its load, the "
             "bytes its members put on the air in an interval over the data channel's capacity (B N T_n / 8), "
             "median and max over the intervals (domains on one channel share it: the channel's load is their "
             "sum); and its transmissions lost to a collision at some receiver. Single and EMP have no "
             "domains on the air: no rows.", ""]
    cells = domain_cells(pairs)
    lines += domain_table_md(cells) if cells else [
        "No data: no judged V2V run of several domains has its MCAP here."]
    lines += ["", "## Handover cost: the collider's visibility around the ego's border crossings", "",
              "Per event (`python -m deploy.experiments.handover RUN.mcap`): the ticks of the event's window (up to "
              "its judgement) in the second around each border crossing of its ego (ticks k - 5 .. k + 4 of a "
              "crossing at tick k: its domains differ from tick k - 1's) and those at least one second from every "
              "crossing; in each, the share of ticks with the collider in the ego's fused view (at least 5 of its "
              "points, as the judge counts them) and its mean points, pooled over the runs' ticks. Cost: the share "
              "away minus the share around. Single's fused view is its own LiDAR: its row is what the crossing's "
              "place and moment give without any radio.", ""]
    cells = handover_cells(pairs)
    lines += handover_table_md(cells) if cells else ["No data: no judged run of several domains has its MCAP here."]
    return lines + (["", note] if note else [])


def _order(scheme: str) -> int:
    return SCHEME_ORDER.index(scheme) if scheme in SCHEME_ORDER else len(SCHEME_ORDER)


# ---------------------------------------------------------------------------- CLI


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="autocast report", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sweep_dir", type=Path, help="a directory autocast sweep wrote")
    ap.add_argument("--out", type=Path, help="where the figures and summary.md go (default SWEEP_DIR/report)")
    ap.add_argument("--delay-vehicles", type=int, help="density of the scheduled-delay plot (default 20 when run, "
                    "else the densest)")
    ap.add_argument("--delay-runs", type=int, default=12, help="runs per scheme read for it (default 12)")
    args = ap.parse_args(argv)
    logging.basicConfig(level="INFO", format="autocast report: %(message)s")

    results = args.sweep_dir / RESULTS
    if not results.exists() and not (args.sweep_dir / PLAN).exists():
        print(f"error: sweep_dir: {args.sweep_dir} holds no {RESULTS} or {PLAN}", file=sys.stderr)
        return 2
    records = list(latest(read_results(results)).values())
    try:
        plan = json.loads((args.sweep_dir / PLAN).read_text())
    except (OSError, ValueError):
        plan = None
    out = args.out or args.sweep_dir / "report"
    out.mkdir(parents=True, exist_ok=True)

    plot_outcomes(records, out / "outcomes.png")
    plot_safe_vs_density(records, out / "safe_vs_density.png")
    plot_visibility(records, out / "visibility_vs_density.png")
    plot_reaction_closest(records, out / "reaction_closest.png")

    vehicles, chosen = delay_runs(records, args.delay_vehicles, args.delay_runs)
    by_scheme: dict[str, tuple[int, list[Sent]]] = {}
    missing: list[dict[str, Any]] = []
    for scheme, runs in chosen.items():
        sent, read = [], 0
        for r in runs:
            mcap = mcap_of(args.sweep_dir, plan, r)
            if mcap is None:
                missing.append(r)
                continue
            sent += schedule_of_run(mcap)
            read += 1
        if read:
            by_scheme[scheme] = (read, sent)
    lacking = missing_mcaps_note(missing, plan)
    if lacking:
        log.warning("%s", lacking)
    if by_scheme:
        why = ""
        note = (f"From the runs' MCAPs (up to {args.delay_runs} runs per scheme at {vehicles} vehicles): each "
                "object a vehicle transmitted, as the channel proxy played it (`net/stats`: end of its first "
                "airtime from the start of the interval's data phase), joined with the sender's control message "
                "of that interval (`net/ctrl/tx`: the object's visibility v and relevance r per receiver). "
                "Negative Spearman: higher rewards arrive earlier.")
    else:
        why = ("no judged V2V run (agnostic, autocast, autocast-fptas)" if not chosen
               else "the V2V runs' MCAPs are missing")
        note = f"No data: {why}."
    if lacking:
        note += " " + lacking
    plot_scheduled_delay(by_scheme, vehicles if by_scheme else None, out / "scheduled_delay.png", why)

    t0 = time.perf_counter()
    pairs, no_mcap = load_of_runs(args.sweep_dir, plan, records, args.sweep_dir / "report" / "load")
    load = load_by_density(pairs)
    load_note = "" if load else "No data: no judged run with a channel (every scheme but single) has its MCAP here."
    if no_mcap:
        load_note += (f" {_n(len(no_mcap), 'judged run')} with a channel left out, MCAP missing or unreadable: "
                      f"{_ids([r['run_id'] for r in no_mcap])}.")
    log.info("offered load of %s in %.1f s", _n(len(pairs), "run"), time.perf_counter() - t0)
    plot_load(load, out / "load_vs_density.png", "no judged run with a channel and its MCAP")

    network, network_note = None, ""
    if any(several_domains(r["scenario"]) for r in judged(records)):
        t0 = time.perf_counter()
        network, no_mcap = network_of_runs(args.sweep_dir, plan, records, args.sweep_dir / "report" / "network")
        if no_mcap:
            network_note = (f"{_n(len(no_mcap), 'judged run')} of several domains left out, MCAP missing or "
                            f"unreadable: {_ids([r['run_id'] for r in no_mcap])}.")
        log.info("per-domain figures of %s in %.1f s", _n(len(network), "run"), time.perf_counter() - t0)

    (out / "summary.md").write_text(summary_md(args.sweep_dir, records, plan, delay_table(by_scheme),
                                               vehicles if by_scheme else None, note, load, load_note.strip(),
                                               network, network_note))
    log.info("%d runs -> %s: %s, summary.md", len(records), out, ", ".join(FIGURES))
    return 0


if __name__ == "__main__":
    sys.exit(main())
