"""Screenshots of a run in the rerun viewer, headless, for docs/viewing.md.

    python docs/screenshots.py runs/<id> --out docs/img

Renders ``autocast view``'s recording of the run in a real rerun viewer window on a
virtual X display (Xvfb with its Composite extension off) with software Vulkan (Mesa's
lavapipe), moves the time cursor with the viewer's control API and saves three
screenshots: the first tick; the last tick at which the ego's received points fall on
the collider (its red shared points) while its own LiDAR has not yet had a return from
it; and the last tick. It prints when each first happened, for the captions. Needs the Debian packages ``xvfb``,
``mesa-vulkan-drivers``, ``libvulkan1`` and ``imagemagick`` (to shrink the PNGs).
A docs tool: the test suite never starts a viewer.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing

from deploy.record import view  # noqa: E402
from deploy.record.runlog import LogStats, iter_log, read_prelude, received_world, scan_points  # noqa: E402
from protocol.messages import DataBundle, LidarConfig, Scan, WorldTruth  # noqa: E402
from vehicle_agent.frames import sensor_to_world  # noqa: E402

log = logging.getLogger("screenshots")

EGO = 0
MIN_POINTS = 5  # the judge's threshold for "the collider is in view"
MARGIN_M = 0.3  # points this close outside the collider's box still count (its surface)
WINDOW = "1920x1080"  # the viewer's window
SCREEN = "3900x1100"  # Xvfb's screen: its pointer starts at the centre, off the window (no hover tooltips)


@dataclass(frozen=True, slots=True)
class Moments:
    start_s: float
    first_shared_s: float | None  # the ego's received points first fall on the collider
    first_own_s: float | None  # the ego's own LiDAR first returns from it
    shared_only_s: float | None  # the last tick with shared points on it before its own LiDAR had any
    end_s: float
    collider: int


def on_box(points: np.ndarray, pose: np.ndarray, size: np.ndarray) -> int:
    """How many world points fall in a vehicle's footprint (its box seen from above, plus a margin)."""
    if not len(points):
        return 0
    c, s = np.cos(pose[2]), np.sin(pose[2])
    dx, dy = points[:, 0] - pose[0], points[:, 1] - pose[1]
    along, across = c * dx + s * dy, -s * dx + c * dy
    inside = (np.abs(along) <= size[0] / 2 + MARGIN_M) & (np.abs(across) <= size[1] / 2 + MARGIN_M) & \
        (points[:, 2] > 0.2)
    return int(np.count_nonzero(inside))


def moments(mcap: Path) -> Moments:
    """When the collider first shows up in the ego's received points and in its own scan."""
    prelude = read_prelude(mcap)
    passive = prelude.passive_vids()
    if not passive:
        raise SystemExit("no vehicle without V2V in the log's ground truth: no collider to look for")
    collider = passive[0]
    lidar = prelude.missions[EGO].lidar if EGO in prelude.missions else LidarConfig()
    truth: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    start = end = None
    first_shared = first_own = shared_only = None
    for _, msg in iter_log(mcap, LogStats()):
        if isinstance(msg, WorldTruth):
            row = np.flatnonzero(msg.vids == collider)
            if len(row):
                truth[msg.tick] = (msg.pose[row[0]].astype(np.float64), msg.size_m[row[0]].astype(np.float64))
            start = msg.t_sim_s if start is None else start
            end = msg.t_sim_s
        elif isinstance(msg, DataBundle) and first_own is None and msg.tick in truth:
            row = np.flatnonzero(msg.receivers == EGO)
            if len(row):
                world, _ = received_world(msg)
                got = [world[t] for t in np.flatnonzero(msg.decoded[row[0]]).tolist()]
                if got and on_box(np.vstack(got), *truth[msg.tick]) >= MIN_POINTS:
                    first_shared = msg.t_sim_s if first_shared is None else first_shared
                    shared_only = msg.t_sim_s if first_own is None else shared_only
        elif isinstance(msg, Scan) and msg.vid == EGO and first_own is None and msg.tick in truth:
            world = sensor_to_world(scan_points(msg, lidar, 0), msg.pose, lidar.mount_height_m)
            if on_box(world, *truth[msg.tick]) >= MIN_POINTS:
                first_own = msg.t_sim_s
    if start is None:
        raise SystemExit("no ground truth in the log")
    return Moments(start, first_shared, first_own, shared_only, end, collider)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_display() -> int:
    return next(n for n in range(90, 200) if not Path(f"/tmp/.X11-unix/X{n}").exists()
                and not Path(f"/tmp/.X{n}-lock").exists())


def wait_for(predicate, what: str, timeout_s: float = 120.0) -> None:
    """Poll ``predicate`` (a viewer state query) until it holds; the viewer has no event
    to wait on for 'done loading'."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise SystemExit(f"timed out waiting for {what}")
        time.sleep(0.5)


def imagemagick() -> str:
    """ImageMagick's command (Debian's ``imagemagick`` installs ``convert-im6.q16``; a
    ``convert`` earlier on PATH may be something else)."""
    for name in ("magick", "convert-im6.q16", "convert"):
        if shutil.which(name):
            return name
    raise SystemExit("ImageMagick not found (apt-get install imagemagick)")


def screenshot(client, tries: int = 4) -> bytes:
    """The viewer's own screenshot. Software rendering on a busy machine can take longer
    than the control API's 15 s deadline for one frame: ask again."""
    for attempt in range(tries):
        try:
            return client.take_screenshot()
        except TimeoutError:
            log.info("screenshot: no frame within the deadline (try %d of %d)", attempt + 1, tries)
    raise SystemExit("the viewer painted no frame for a screenshot")


def shrink(src: Path, dst: Path, width: int, colors: int) -> None:
    """A smaller PNG: scaled to ``width`` and quantized to a palette."""
    subprocess.run([imagemagick(), str(src), "-resize", f"{width}x", "-dither", "None", "-colors", str(colors),
                    "-strip", f"PNG8:{dst}"], check=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a run directory (or its run.mcap)")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "img")
    ap.add_argument("--width", type=int, default=1280, help="width of the saved PNGs")
    ap.add_argument("--colors", type=int, default=96, help="palette size of the saved PNGs")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="screenshots: %(message)s")
    mcap = args.run / "run.mcap" if args.run.is_dir() else args.run
    imagemagick()
    for tool in ("Xvfb", "rerun"):
        if shutil.which(tool) is None:
            raise SystemExit(f"{tool} not found (apt-get install xvfb mesa-vulkan-drivers libvulkan1 imagemagick)")
    from rerun.experimental import ViewerClient

    m = moments(mcap)
    log.info("collider %d: the ego's shared points on it from %s s, its own LiDAR's from %s s; run %.1f-%.1f s",
             m.collider, m.first_shared_s, m.first_own_s, m.start_s, m.end_s)
    shots = {"view-start": m.start_s, "view-end": m.end_s}
    if m.shared_only_s is not None:
        shots["view-shared"] = m.shared_only_s
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="autocast-shots-") as tmp:
        rrd = Path(tmp) / "run.rrd"
        t0 = time.perf_counter()
        if view.main([str(mcap), "--save", str(rrd)]) != 0:
            return 1
        log.info("autocast view: %.1f s", time.perf_counter() - t0)
        display, port = free_display(), free_port()
        xvfb = subprocess.Popen(["Xvfb", f":{display}", "-screen", "0", f"{SCREEN}x24", "-extension", "Composite",
                                 "-nolisten", "tcp"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        viewer = None
        try:
            wait_for(lambda: Path(f"/tmp/.X11-unix/X{display}").exists(), "Xvfb", 30)
            env = {**os.environ, "DISPLAY": f":{display}"}
            env.pop("WAYLAND_DISPLAY", None)
            viewer = subprocess.Popen(["rerun", "--renderer", "vulkan", "--port", str(port), "--window-size", WINDOW,
                                       "--hide-welcome-screen", "--memory-limit", "4GB", str(rrd)], env=env,
                                      stdout=subprocess.DEVNULL, stderr=open(Path(tmp) / "viewer.log", "w"))
            url = f"rerun+http://127.0.0.1:{port}/proxy"

            def connected() -> bool:
                if viewer.poll() is not None:
                    raise SystemExit(f"the viewer exited with {viewer.returncode}: {Path(tmp) / 'viewer.log'}")
                try:
                    ViewerClient.connect(url).get_state()
                    return True
                except Exception:  # not listening yet
                    return False

            wait_for(connected, "the viewer to listen", 120)
            client = ViewerClient.connect(url)

            def loaded() -> bool:  # the file is read in order: the last tick's time is there at the end
                state = client.get_state()
                ends = [tl.end for r in state.recordings for tl in r.timelines if tl.name == view.SIM_TIME]
                return not state.loading and bool(ends) and ends[0] is not None and ends[0] >= round(m.end_s * 1e9)

            wait_for(loaded, "the recording to load", 300)
            for name, t in shots.items():
                client.set_time(timeline=view.SIM_TIME, duration=t, play_state="paused")
                time.sleep(2.0)  # a few frames at the new time: the viewer reports no 'painted' event
                raw = Path(tmp) / f"{name}.png"
                raw.write_bytes(screenshot(client))
                shrink(raw, args.out / f"{name}.png", args.width, args.colors)
                log.info("%s at %.1f s -> %s (%d KiB)", name, t, args.out / f"{name}.png",
                         (args.out / f"{name}.png").stat().st_size // 1024)
            for v in client.get_state().views:
                for r in v.reports:
                    log.warning("view %s: %s %s", v.name, r.severity, r.summary)
        finally:
            for proc in (viewer, xvfb):
                if proc is not None and proc.poll() is None:
                    proc.terminate()
                    try:
                        proc.wait(timeout=10)
                    except subprocess.TimeoutExpired:
                        proc.kill()
    return 0


if __name__ == "__main__":
    sys.exit(main())
