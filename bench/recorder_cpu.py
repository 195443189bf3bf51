"""The recorder's writer CPU per tick, this tree's against another tree's, in one process.

    python -m bench.recorder_cpu runs/<id>/run.mcap --against /path/to/other/tree [--rounds 9] [--scans]

Replays a recording's raw messages through ``McapLog.write`` (the recorder's whole
writing path: the envelope, the MCAP records, zstd; with the JSON mirror, decoding and
JSON too) into memory, with the mirror off and on, alternating this tree's
``deploy/record/recorder.py`` with the other tree's (loaded from its file; the rest of the
code is this tree's) round by round: the machine's speed drifts, so only alternating
rounds compare. Prints ms of CPU (``time.process_time``) per tick, min and median over
the rounds, and their ratios. LiDAR scans are left out unless ``--scans`` (what
`autocast run --scans none` records); the receiving side (Zenoh, the callbacks) is
not in it.
"""

from __future__ import annotations

import argparse
import importlib.util
import io
import statistics
import sys
import time
from pathlib import Path
from types import ModuleType

from deploy.record import recorder
from protocol.codec import peek_envelope


def load_recorder(tree: Path) -> ModuleType:
    """The recorder of ``tree`` as a module of its own (``deploy/record/recorder.py``;
    ``deploy/recorder.py`` in a tree from before ``deploy/`` had packages)."""
    name = "recorder_of_" + "".join(c if c.isalnum() else "_" for c in str(tree))
    path = tree / "deploy" / "record" / "recorder.py"
    spec = importlib.util.spec_from_file_location(name, path if path.exists() else tree / "deploy" / "recorder.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def raw_messages(path: Path, scans: bool) -> list[tuple[str, bytes, int]]:
    with open(path, "rb") as f:
        return [(ch.topic, bytes(m.data), m.log_time) for _, ch, m in recorder.read_messages(f)
                if ch.message_encoding == recorder.MESSAGE_ENCODING and (scans or not ch.topic.endswith("/scan"))]


def write_cpu_s(module: ModuleType, items: list[tuple[str, bytes, int]], mirror: bool) -> float:
    t0 = time.process_time()
    log = module.McapLog(io.BytesIO(), {}, "zstd", json_mirror=mirror)
    for item in items:
        log.write(*item)
    log.finish()
    return time.process_time() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.recorder_cpu", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mcap", type=Path, help="a recording (run.mcap)")
    ap.add_argument("--against", type=Path, required=True, metavar="TREE", help="the other tree (a git worktree)")
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--scans", action="store_true", help="keep the LiDAR scans in the replay")
    args = ap.parse_args(argv)
    items = raw_messages(args.mcap, args.scans)
    ticks = len({t for _, p, _ in items if (t := peek_envelope(p)) is not None and t.cls.__name__ == "Tick"})
    ticks = max(ticks, 1)
    trees = {"this": recorder, "against": load_recorder(args.against.resolve())}
    cpu: dict[tuple[str, bool], list[float]] = {}
    for module in trees.values():  # warm: converters, numpy, zstd
        write_cpu_s(module, items[:500], True)
    for _ in range(args.rounds):
        for name, module in trees.items():
            for mirror in (False, True):
                cpu.setdefault((name, mirror), []).append(write_cpu_s(module, items, mirror) * 1e3 / ticks)
    print(f"{len(items)} messages, {ticks} ticks, {args.rounds} rounds alternating; ms of CPU per tick (min / median)")
    for mirror in (False, True):
        this, other = cpu["this", mirror], cpu["against", mirror]
        print(f"mirror {'on ' if mirror else 'off'}: this {min(this):.2f} / {statistics.median(this):.2f}, "
              f"against {min(other):.2f} / {statistics.median(other):.2f}, ratio "
              f"{min(this) / min(other):.3f} / {statistics.median(this) / statistics.median(other):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
