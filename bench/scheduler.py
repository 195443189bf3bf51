"""Scheduler bench: the paper's "Optimality" and "Computation Time" figures on generated
intersection instances (autocast bench scheduler [--quick] [--out DIR]).

Every instance is one decision interval (T_d = 100 ms, B = 7.2 Mbps) at a four-way
intersection: connected vehicles, as many unconnected cars, pedestrians at the corners,
buildings on the corner blocks; each vehicle reports up to 30 objects it detects. Three
series:
- 1 x 100 ms: 5..40 vehicles, N = 1 frame of 90 kB. The exact optimum is a knapsack on
  the expected gain and is computed at every size.
- 10 x 10 ms: 5..40 vehicles, N = 10 frames of 9 kB. The exact optimum is out of
  reach; this series gives the computation times and the headline greedy40_ms.
- small: 3-6 vehicles with up to 3 objects each, N = 2-3 frames of 10 ms, where the
  exact multi-frame optimum (and, when it fits, the MDP value with feedback) is
  computed.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vehicle_agent.scheduler import (
    Instance,
    InstanceTooLarge,
    SchedulerState,
    check_schedule,
    expected_reward,
    get,
    instance_from_arrays,
    link_probabilities,
    mdp_optimal,
)
from vehicle_agent.scheduler.warmup import warm_up


ARM_LENGTH_M = 90.0
LANE_OFFSET_M = (1.75, 5.25)  # right-hand lanes' centre offsets from the road axis
BLOCK_CORNER_M = 12.0  # buildings fill every quadrant beyond |x|, |y| > 12 m
SENSOR_RANGE_M = 80.0
RELEVANCE_RANGE_M = 35.0
BYTES_PER_POINT = 16  # x, y, z, intensity as float32
HEADER_BYTES = 64

SCALE_VEHICLES = (5, 10, 20, 30, 40)
ALGORITHMS = ("greedy", "fptas", "knapsack", "agnostic", "optimal")
STARVED = "greedy+m"  # greedy with the starvation counters of a running agent
WORK_CONSERVING = "autocast"  # greedy+m with the frames' spare room filled (fill.py)


# ------------------------------------------------------------------------- instances


@dataclass(frozen=True, slots=True)
class Scene:
    xy: np.ndarray  # (A, 2) actor positions, world frame, metres
    arm: np.ndarray  # (A,) approach 0..3 (E, N, W, S), -1 for pedestrians
    along_m: np.ndarray  # (A,) distance to the intersection centre along the arm
    radius_m: np.ndarray  # (A,) occluding disc radius
    n_connected: int  # actors 0..n_connected-1 are the connected vehicles


def intersection_scene(rng: np.random.Generator, n_connected: int, n_others: int, n_pedestrians: int) -> Scene:
    """Cars on the four approaches (two lanes each way), pedestrians at the corners."""
    n_cars = n_connected + n_others
    arm = rng.integers(0, 4, n_cars)
    along = rng.uniform(-20.0, ARM_LENGTH_M, n_cars)  # negative: already through the box
    lateral = rng.choice(LANE_OFFSET_M, n_cars) * rng.choice((-1.0, 1.0), n_cars)
    angle = arm * (np.pi / 2)
    ux, uy = np.cos(angle), np.sin(angle)
    car_xy = np.stack([ux * along - uy * lateral, uy * along + ux * lateral], axis=1)
    corner = rng.integers(0, 4, n_pedestrians) * (np.pi / 2) + np.pi / 4
    ped_r = rng.uniform(13.0, 18.0, n_pedestrians)
    ped_xy = np.stack([ped_r * np.cos(corner), ped_r * np.sin(corner)], axis=1)
    return Scene(
        xy=np.concatenate([car_xy, ped_xy]),
        arm=np.concatenate([arm, -np.ones(n_pedestrians, dtype=np.int64)]),
        along_m=np.concatenate([along, ped_r]),
        radius_m=np.concatenate([np.full(n_cars, 2.2), np.full(n_pedestrians, 0.4)]),
        n_connected=n_connected,
    )


def line_of_sight(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """bool (C, A) twice: connected vehicle c ``detects`` actor a (in range, not behind a
    building corner; partly hidden objects are still segmented and can be shared) and
    ``sees`` it fully (no other actor's disc on the line of sight either)."""
    viewers = scene.xy[: scene.n_connected]
    d = scene.xy[None, :, :] - viewers[:, None, :]  # (C, A, 2)
    dist = np.hypot(d[..., 0], d[..., 1])
    t = np.linspace(0.05, 0.95, 19)
    pts = viewers[:, None, None, :] + d[:, :, None, :] * t[None, None, :, None]  # (C, A, T, 2)
    behind_building = np.any((np.abs(pts[..., 0]) > BLOCK_CORNER_M) & (np.abs(pts[..., 1]) > BLOCK_CORNER_M), axis=2)
    rel = scene.xy[None, None, :, :] - viewers[:, None, None, :]  # (C, 1, B, 2): blocker b from viewer c
    seg = d[:, :, None, :]  # (C, A, 1, 2)
    along = np.clip(np.sum(rel * seg, axis=-1) / np.maximum(np.sum(seg * seg, axis=-1), 1e-9), 0.0, 1.0)
    gap = np.hypot(*(rel - along[..., None] * seg).transpose(3, 0, 1, 2))  # blocker b to segment c -> a
    A = len(scene.xy)
    blocker = (gap < scene.radius_m[None, None, :]) & (along > 0.0) & (along < 1.0)
    blocker[:, np.arange(A), np.arange(A)] = False  # the target does not hide itself
    blocker[np.arange(scene.n_connected), :, np.arange(scene.n_connected)] = False  # nor the viewer
    own = np.zeros(dist.shape, dtype=bool)
    own[np.arange(scene.n_connected), np.arange(scene.n_connected)] = True
    detects = (dist < SENSOR_RANGE_M) & ~behind_building & ~own
    return detects, detects & ~np.any(blocker, axis=2)


def relevance(scene: Scene) -> np.ndarray:
    """float (A, C): r of actor a to connected vehicle c; an actor matters to c when it
    is close, on a crossing or oncoming approach, or ahead of c in its own approach."""
    C = scene.n_connected
    d = np.hypot(*(scene.xy[:, None, :] - scene.xy[None, :C, :]).transpose(2, 0, 1))  # (A, C)
    same_arm = scene.arm[:, None] == scene.arm[None, :C]
    ahead = scene.along_m[:, None] < scene.along_m[None, :C]
    approaching = scene.along_m[None, :C] > -5.0  # c has not left the box yet
    conflict = (~same_arm | ahead) & approaching
    r = np.clip(1.0 - d / RELEVANCE_RANGE_M, 0.0, 1.0) * conflict
    r[np.arange(C), np.arange(C)] = 0.0
    return np.round(r, 3)


def intersection_instance(
    rng: np.random.Generator,
    n_vehicles: int,
    *,
    objects_per_vehicle: int = 30,
    others: int | None = None,
    pedestrians: int | None = None,
    frame_duration_s: float = 0.01,
    n_frames: int = 10,
    bandwidth_bps: float = 7.2e6,
) -> Instance:
    """A scheduling instance as AutoCast would meet it at a busy intersection."""
    others = n_vehicles if others is None else others
    pedestrians = 4 + n_vehicles // 2 if pedestrians is None else pedestrians
    scene = intersection_scene(rng, n_vehicles, others, pedestrians)
    detects, seen = line_of_sight(scene)  # (C, A)
    r = relevance(scene)  # (A, C)
    C = n_vehicles
    vids = rng.permutation(np.arange(100, 100 + 3 * C))[:C]
    owner, oid, size, rows, unseen = [], [], [], [], []
    for i in range(C):
        visible = np.flatnonzero(detects[i])
        dist = np.hypot(*(scene.xy[visible] - scene.xy[i]).T)
        for a in visible[np.argsort(dist, kind="stable")][:objects_per_vehicle]:
            d_ia = float(np.hypot(*(scene.xy[a] - scene.xy[i])))
            points = int(np.clip(5000.0 / max(d_ia, 5.0), 60, 300) * rng.uniform(0.8, 1.2))
            owner.append(int(vids[i]))
            oid.append(int(a))
            size.append(points * BYTES_PER_POINT + HEADER_BYTES)
            visible_to_j = seen[:, a].astype(np.float64)
            y = (1.0 - visible_to_j) * r[a]  # y_(i,k),j = (1 - v) * r
            if a < C:
                y[a] = 0.0  # a connected vehicle needs no point cloud of itself
            rows.append(y)
            hidden = 1.0 - visible_to_j
            hidden[i] = 0.0
            unseen.append(float(hidden.sum()))  # sum_j (1 - v) over the other receivers
    reward = np.array(rows).reshape(len(rows), C)
    p = link_probabilities(scene.xy[:C])
    frame_bytes = int(bandwidth_bps * frame_duration_s / 8.0)  # S_f = B * T_n
    return instance_from_arrays(
        vids, owner, oid, size, reward, p,
        frame_bytes=frame_bytes, n_frames=n_frames, bandwidth_bps=bandwidth_bps, frame_duration_s=frame_duration_s,
        unseen=np.array(unseen),
    )


# ------------------------------------------------------------------------- measuring


@dataclass(frozen=True, slots=True)
class Run:
    reward: float | None  # expected reward of the schedule; None if the solver refused
    ms: float | None  # median wall time per call
    sent_bytes: int | None = None  # bytes on air over the interval (repeats counted)
    sent_objects: int | None = None  # distinct objects sent


def measure(fn: Callable[[], object], repeats: int) -> tuple[object, float]:
    """The result of ``fn`` and its median wall time in ms over ``repeats`` calls."""
    times = []
    result = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return result, statistics.median(times)


def run_all(inst: Instance, state: SchedulerState, repeats: int, algorithms: tuple[str, ...] = ALGORITHMS) -> dict[str, Run]:
    out: dict[str, Run] = {}
    for name in algorithms:
        scheduler = get(name)
        try:
            schedule, ms = measure(lambda: scheduler(inst, state), 1 if name == "optimal" else repeats)
        except InstanceTooLarge:
            out[name] = Run(None, None)
            continue
        check_schedule(inst, schedule)
        sent_bytes = sum(int(inst.size_bytes[list(f)].sum()) for f in schedule.frames if f)
        out[name] = Run(expected_reward(inst, schedule), ms, sent_bytes, len(schedule.sent()))
    return out


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b <= 0.0 else a / b


def _mean(xs: list[float | None]) -> float | None:
    xs = [x for x in xs if x is not None]
    return statistics.fmean(xs) if xs else None


def _fmt(x: float | None, spec: str = ".3f") -> str:
    return "-" if x is None else format(x, spec)


# ------------------------------------------------------------------------- series


@dataclass(frozen=True, slots=True)
class Case:
    series: str
    n_vehicles: int
    instance: Instance
    runs: dict[str, Run]
    mdp: float | None = None  # MDP value (per-frame feedback), small series only


SERIES = {"1 x 100 ms": (0.1, 1), "10 x 10 ms": (0.01, 10)}


def scale_series(name: str, seed: int, seeds: int, repeats: int) -> list[Case]:
    """5..40 vehicles. Every scheduler starts from a fresh state (the algorithms
    compared as such); greedy runs once more as ``STARVED``, from the state after one
    interval, whose starvation counters trade immediate reward for fairness."""
    frame_s, n_frames = SERIES[name]
    out = []
    for n_vehicles in SCALE_VEHICLES:
        rng = np.random.default_rng([seed, n_vehicles])
        for _ in range(seeds):
            inst = intersection_instance(rng, n_vehicles, frame_duration_s=frame_s, n_frames=n_frames)
            runs = run_all(inst, SchedulerState(), repeats)
            starved = SchedulerState().advance(inst, get("greedy")(inst, SchedulerState()))
            runs[STARVED] = run_all(inst, starved, repeats, ("greedy",))["greedy"]
            runs[WORK_CONSERVING] = run_all(inst, starved, repeats, ("autocast",))["autocast"]
            out.append(Case(name, n_vehicles, inst, runs))
    return out


def small_series(seed: int, count: int) -> list[Case]:
    """Instances the exact multi-frame optimum can solve; those with nothing to earn skipped."""
    rng = np.random.default_rng([seed, 1])
    out = []
    while len(out) < count:
        n_vehicles = int(rng.integers(3, 7))
        inst = intersection_instance(
            rng, n_vehicles, objects_per_vehicle=3, others=int(rng.integers(2, 8)), n_frames=int(rng.integers(2, 4))
        )
        runs = run_all(inst, SchedulerState(), 1)
        if not runs["optimal"].reward:
            continue
        try:
            mdp = mdp_optimal(inst, max_evaluations=200_000).value
        except InstanceTooLarge:
            mdp = None
        out.append(Case("small", n_vehicles, inst, runs, mdp))
    return out


# ------------------------------------------------------------------------- report


def ratios(cases: list[Case], num: str, den: str) -> list[float]:
    out = []
    for c in cases:
        r = _ratio(c.runs[num].reward, c.runs[den].reward)
        if r is not None:
            out.append(r)
    return out


RATIO_LABELS = {"greedy": "grd", "fptas": "fpt", "agnostic": "agn", "optimal": "opt", STARVED: "grd+m"}
RATIOS = (("greedy", "optimal"), ("fptas", "optimal"), ("agnostic", "optimal"), ("agnostic", "greedy"), (STARVED, "greedy"))


def reward_table(cases: list[Case]) -> list[str]:
    lines = [
        "expected reward per interval (mean over instances) and ratios (mean of per-instance ratios)",
        f"{'series':<11}{'veh':>4}{'objs':>6}{'wanted':>7} |{'optimal':>8}{'greedy':>8}{'fptas':>8}{'knapsk':>8}{'agnost':>8}"
        " |" + "".join(f"{RATIO_LABELS[a]}/{RATIO_LABELS[b]}".rjust(10) for a, b in RATIOS),
    ]
    keys = sorted({(c.series, c.n_vehicles) for c in cases if c.series != "small"}, key=lambda t: (t[0] != "1 x 100 ms", t[1]))
    for series, nv in keys:
        group = [c for c in cases if (c.series, c.n_vehicles) == (series, nv)]
        reward = {a: _mean([c.runs[a].reward for c in group]) for a in ALGORITHMS}
        if any(c.runs["optimal"].reward is None for c in group):
            reward["optimal"] = None
        lines.append(
            f"{series:<11}{nv:>4}{_mean([c.instance.n_objects for c in group]):>6.0f}"
            f"{_mean([float(c.instance.wanted().sum()) for c in group]):>7.0f} |"
            + "".join(f"{_fmt(reward[a], '.2f'):>8}" for a in ("optimal", "greedy", "fptas", "knapsack", "agnostic"))
            + " |"
            + "".join(f"{_fmt(_mean(ratios(group, a, b))):>10}" for a, b in RATIOS)
        )
    return lines


def time_table(cases: list[Case]) -> list[str]:
    cols = (*ALGORITHMS, STARVED, WORK_CONSERVING)
    lines = ["computation time per schedule, ms (median over repeats and instances)", f"{'series':<11}{'veh':>4} |" + "".join(f"{a:>10}" for a in cols)]
    keys = sorted({(c.series, c.n_vehicles) for c in cases if c.series != "small"}, key=lambda t: (t[0] != "1 x 100 ms", t[1]))
    for series, nv in keys:
        group = [c for c in cases if (c.series, c.n_vehicles) == (series, nv)]
        cells = []
        for a in cols:
            ms = [c.runs[a].ms for c in group if c.runs[a].ms is not None]
            cells.append(_fmt(statistics.median(ms), ".3f") if len(ms) == len(group) else "refused" if not ms else f"{statistics.median(ms):.3f}*")
        lines.append(f"{series:<11}{nv:>4} |" + "".join(f"{x:>10}" for x in cells))
    return lines


def airtime_table(cases: list[Case]) -> list[str]:
    """What each schedule carries, 10 x 10 ms series: bytes on air and distinct objects."""
    cols = (STARVED, WORK_CONSERVING, "agnostic")
    lines = ["airtime carried per interval, 10 x 10 ms (mean over instances): kB on air / distinct objects sent",
             f"{'veh':>4}{'objs':>6}{'kB':>6} |" + "".join(f"{a:>16}" for a in cols)]
    for nv in SCALE_VEHICLES:
        group = [c for c in cases if c.series == "10 x 10 ms" and c.n_vehicles == nv]
        if not group:
            continue
        total_kb = _mean([float(c.instance.size_bytes.sum()) / 1e3 for c in group])
        cells = [f"{_mean([c.runs[a].sent_bytes / 1e3 for c in group]):.1f} / {_mean([c.runs[a].sent_objects for c in group]):.0f}"
                 for a in cols]
        lines.append(f"{nv:>4}{_mean([c.instance.n_objects for c in group]):>6.0f}{total_kb:>6.0f} |"
                     + "".join(f"{x:>16}" for x in cells))
    return lines


def small_table(cases: list[Case]) -> list[str]:
    lines = [f"small instances (N = 2-3 frames of 10 ms, {len(cases)} instances): reward / optimal", f"{'':<10}{'mean':>8}{'worst':>8}{'<0.98':>8}"]
    for a in ("greedy", "fptas", "knapsack", "agnostic"):
        r = ratios(cases, a, "optimal")
        lines.append(f"{a:<10}{statistics.fmean(r):>8.3f}{min(r):>8.3f}{sum(x < 0.98 for x in r):>8d}")
    with_mdp = [c for c in cases if c.mdp]
    if with_mdp:
        r = [c.runs["optimal"].reward / c.mdp for c in with_mdp]
        lines.append(f"{'opt/MDP':<10}{statistics.fmean(r):>8.3f}{min(r):>8.3f}{sum(x < 0.98 for x in r):>8d}   ({len(with_mdp)} with the MDP solved)")
    return lines


def plot(cases: list[Case], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"optimal": "black", "greedy": "tab:red", "fptas": "tab:blue", "knapsack": "tab:green", "agnostic": "tab:gray"}
    fig, axes = plt.subplots(2, 2, figsize=(12, 9))
    ax = axes[0, 0]
    group = [c for c in cases if c.series == "1 x 100 ms"]
    for a in ("agnostic", "knapsack", "fptas", "greedy"):  # greedy drawn last, on top
        xs, mean, low = [], [], []
        for nv in SCALE_VEHICLES:
            r = ratios([c for c in group if c.n_vehicles == nv], a, "optimal")
            if r:
                xs.append(nv)
                mean.append(statistics.fmean(r))
                low.append(statistics.fmean(r) - min(r))
        ax.errorbar(xs, mean, yerr=[low, [0.0] * len(low)], fmt="o-", color=colors[a], label=a, capsize=3, alpha=0.85, ms=4 if a == "greedy" else 7)
    ax.set_ylim(0.0, 1.05)
    ax.set_title("Reward / exact optimum, N = 1 x 100 ms frame (bar: worst)")
    ax.set_xlabel("connected vehicles")
    ax.set_ylabel("expected reward / optimum")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")
    ax = axes[0, 1]
    group = [c for c in cases if c.series == "10 x 10 ms"]
    for a in ("agnostic", "knapsack", "fptas", "greedy"):
        xs = [nv for nv in SCALE_VEHICLES if any(c.n_vehicles == nv for c in group)]
        ys = [statistics.fmean(c.runs[a].reward for c in group if c.n_vehicles == nv) for nv in xs]
        ax.plot(xs, ys, "o-", color=colors[a], label=a, alpha=0.85)
    ax.set_title("Total expected reward, N = 10 x 10 ms frames (no exact optimum)")
    ax.set_xlabel("connected vehicles")
    ax.set_ylabel("expected reward per interval")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left")
    ax = axes[1, 0]
    for series, style in zip(SERIES, ("--", "-")):
        group = [c for c in cases if c.series == series]
        for a in ALGORITHMS:
            xs, ys = [], []
            for nv in SCALE_VEHICLES:
                ms = [c.runs[a].ms for c in group if c.n_vehicles == nv]
                if ms and all(m is not None for m in ms):
                    xs.append(nv)
                    ys.append(statistics.median(ms))
            if xs:
                ax.plot(xs, ys, "o" + style, color=colors[a], label=f"{a} ({series})")
    ax.axhline(100.0, color="k", ls=":", lw=1)
    ax.text(5, 110.0, "T_d = 100 ms", fontsize=8)
    ax.axhline(1.0, color="tab:red", ls=":", lw=1)
    ax.text(5, 1.1, "1 ms target", fontsize=8, color="tab:red")
    ax.set_yscale("log")
    ax.set_ylim(1e-4, 1e3)
    ax.set_title("Computation time per schedule (median; dashed: 1 x 100 ms)")
    ax.set_xlabel("connected vehicles")
    ax.set_ylabel("ms")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, ncol=2, loc="lower right")
    ax = axes[1, 1]
    small = [c for c in cases if c.series == "small"]
    data = [ratios(small, a, "optimal") for a in ("greedy", "fptas", "knapsack", "agnostic")]
    labels = ["greedy", "fptas", "knapsack", "agnostic"]
    with_mdp = [c for c in small if c.mdp]
    if with_mdp:
        data.append([c.runs["optimal"].reward / c.mdp for c in with_mdp])
        labels.append("optimal/MDP")
    ax.boxplot(data, tick_labels=labels, whis=(0, 100))
    ax.set_ylim(0.0, 1.05)
    ax.set_title(f"Reward / exact optimum, {len(small)} small instances (N = 2-3)")
    ax.set_ylabel("ratio")
    ax.grid(alpha=0.3)
    fig.suptitle("AutoCast scheduler on generated intersection instances: reward and computation time")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="autocast bench scheduler", description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer instances and repeats (well under a minute)")
    ap.add_argument("--out", type=Path, default=Path("runs/bench_scheduler"), help="directory for the plot")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    seeds, repeats, n_small = (2, 5, 60) if args.quick else (5, 15, 300)

    warm_up()
    cases: list[Case] = []
    for series in SERIES:
        cases += scale_series(series, args.seed, seeds, repeats)
    cases += small_series(args.seed, n_small)

    for lines in (reward_table(cases), time_table(cases), airtime_table(cases),
                  small_table([c for c in cases if c.series == "small"])):
        print("\n".join(lines))
        print()
    png = args.out / "scheduler.png"
    plot(cases, png)
    print(f"plot: {png}")

    feasible = [r for c in cases for r in ratios([c], "greedy", "optimal")]
    scale = [c for c in cases if c.series != "small"]
    at40 = [c for c in cases if c.series == "10 x 10 ms" and c.n_vehicles == 40]
    greedy40 = statistics.median(c.runs[STARVED].ms for c in at40)
    fptas40 = statistics.median(c.runs["fptas"].ms for c in at40)
    wc40 = statistics.median(c.runs[WORK_CONSERVING].ms for c in at40)
    wc_bytes = statistics.fmean(c.runs[WORK_CONSERVING].sent_bytes / c.runs["agnostic"].sent_bytes
                                for c in scale if c.runs["agnostic"].sent_bytes)
    print(f"work-conserving: autocast40_ms={wc40:.3f} autocast_over_agnostic_bytes={wc_bytes:.3f}")
    print(
        f"scheduler: greedy_vs_optimal={min(feasible):.3f} agnostic_vs_greedy={statistics.fmean(ratios(scale, 'agnostic', 'greedy')):.3f} "
        f"greedy40_ms={greedy40:.3f} fptas_over_greedy_time={fptas40 / greedy40:.0f}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
