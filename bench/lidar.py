"""LiDAR bench: one 64 x 1800 scan and all 40 scans of a tick in a 40-vehicle intersection.

The scene is synthetic and seeded: cars and trucks on the lanes of a 4-arm intersection
within 85 m of the centre, each rocking back and forth along its lane so the boxes move
every tick while the scene stays non-overlapping and statistically the same.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from protocol.messages import LidarConfig
from world_server.lidar import scan, scan_many

CAR = (4.5, 1.8, 1.5)
TRUCK = (9.0, 2.5, 3.5)
CAR_MOUNT_M = 1.9
TRUCK_MOUNT_M = 3.8
LANE_OFFSETS_M = (1.75, 5.25)  # two lanes per direction, 3.5 m wide
ARM_START_M = 12.0  # keep the box of the junction itself clear
ARM_END_M = 85.0
DT_S = 0.1
SWAY_M = 0.4  # amplitude of the motion along the lane; below half of the 1 m gap
SWAY_PERIOD_S = 2.0


def intersection_scene(
    n: int, seed: int, truck_share: float = 0.2
) -> tuple[np.ndarray, np.ndarray]:
    """n non-overlapping boxes (n, 6) on the lanes of a 4-arm junction, and their phases (n,)."""
    rng = np.random.default_rng(seed)
    boxes: list[list[float]] = []
    lanes: list[tuple[int, int, int]] = []  # (arm, side, lane) of each box
    along: list[tuple[float, float]] = []  # (start, end) distance from the centre
    while len(boxes) < n:
        size = TRUCK if rng.random() < truck_share else CAR
        arm = int(rng.integers(4))  # 0: +x, 1: +y, 2: -x, 3: -y
        side = int(rng.integers(2))  # 0: inbound, 1: outbound
        lane = int(rng.integers(2))
        s = rng.uniform(ARM_START_M + size[0] / 2, ARM_END_M - size[0] / 2)
        span = (s - size[0] / 2 - 1.0, s + size[0] / 2 + 1.0)  # 1 m gap
        clash = any(
            lanes[j] == (arm, side, lane) and span[0] < along[j][1] and along[j][0] < span[1]
            for j in range(len(boxes))
        )
        if clash:
            continue
        arm_yaw = arm * math.pi / 2
        # inbound drives towards the centre on its right-hand side (offset -> right of travel)
        offset = LANE_OFFSETS_M[lane] * (1.0 if side == 0 else -1.0)
        ax, ay = math.cos(arm_yaw), math.sin(arm_yaw)
        cx = s * ax - offset * ay
        cy = s * ay + offset * ax
        yaw = arm_yaw + (math.pi if side == 0 else 0.0)
        boxes.append([cx, cy, yaw, *size])
        lanes.append((arm, side, lane))
        along.append(span)
    phases = rng.uniform(0.0, 2.0 * math.pi, n)
    return np.array(boxes), phases


def at_tick(boxes: np.ndarray, phases: np.ndarray, tick: int) -> np.ndarray:
    """The scene at a tick: every box shifted along its heading by its sway."""
    shift = SWAY_M * np.sin(2.0 * math.pi * tick * DT_S / SWAY_PERIOD_S + phases)
    moved = boxes.copy()
    moved[:, 0] += shift * np.cos(boxes[:, 2])
    moved[:, 1] += shift * np.sin(boxes[:, 2])
    return moved


def sensors_of(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every vehicle carries a LiDAR at its centre: poses, mount heights, own box index."""
    heights = np.where(boxes[:, 5] > 2.0, TRUCK_MOUNT_M, CAR_MOUNT_M)
    return boxes[:, :3].copy(), heights, np.arange(len(boxes))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="autocast bench lidar", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="fewer repetitions (a few seconds)")
    parser.add_argument(
        "--ticks", type=int, default=None, help="ticks of 40 scans (default 200, quick 30)"
    )
    parser.add_argument("--vehicles", type=int, default=40)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    ticks = args.ticks if args.ticks is not None else (30 if args.quick else 200)
    reps = 100 if args.quick else 1000

    cfg = LidarConfig()
    boxes, phases = intersection_scene(args.vehicles, args.seed)
    poses, heights, skips = sensors_of(boxes)

    t0 = time.perf_counter()
    scan(boxes, poses[0], heights[0], cfg, int(skips[0]))  # compiles or loads the numba cache
    first_call_ms = (time.perf_counter() - t0) * 1e3
    scan_many(boxes, poses, heights, cfg, skips)  # builds the ground tables of every height

    scan_ms = []
    for _ in range(reps):
        t0 = time.perf_counter()
        scan(boxes, poses[0], heights[0], cfg, int(skips[0]))
        scan_ms.append((time.perf_counter() - t0) * 1e3)

    tick_ms = []
    n_points: list[int] = []
    n_object_points: list[int] = []
    for tick in range(1, ticks + 1):
        world = at_tick(boxes, phases, tick)
        poses, heights, skips = sensors_of(world)
        t0 = time.perf_counter()
        out = scan_many(world, poses, heights, cfg, skips)
        tick_ms.append((time.perf_counter() - t0) * 1e3)
        n_points.extend(len(lbl) for _, lbl in out)
        n_object_points.extend(int(np.count_nonzero(lbl >= 0)) for _, lbl in out)

    scan_med = float(np.median(scan_ms))
    tick_med = float(np.median(tick_ms))
    n_trucks = int(np.count_nonzero(boxes[:, 5] > 2.0))
    rows = [
        ("scene", f"{len(boxes)} vehicles ({n_trucks} trucks), seed {args.seed}"),
        ("lidar", f"{cfg.beams} x {cfg.azimuth_steps} rays, range {cfg.range_m:g} m"),
        ("first call (numba start-up + cache load)", f"{first_call_ms:9.1f} ms"),
        (
            "one scan, median",
            f"{scan_med:9.3f} ms  (p90 {np.percentile(scan_ms, 90):.3f}, n={reps})",
        ),
        (
            f"tick of {len(boxes)} scans, median",
            f"{tick_med:9.2f} ms  (p90 {np.percentile(tick_ms, 90):.2f}, n={ticks})",
        ),
        ("per scan within a tick", f"{tick_med / len(boxes):9.3f} ms"),
        (
            "points per scan, median",
            f"{np.median(n_points):9.0f}  (min {min(n_points)}, max {max(n_points)})",
        ),
        ("object points per scan, median", f"{np.median(n_object_points):9.0f}"),
    ]
    width = max(len(name) for name, _ in rows)
    for name, value in rows:
        print(f"{name:<{width}}  {value}")
    print(f"lidar: scan_ms={scan_med:.2f} tick40_ms={tick_med:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
