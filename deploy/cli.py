"""The ``autocast`` command: one CLI, one subcommand per job.

Each subcommand hands its remaining arguments to the module that owns the job, so
``autocast world ...`` and ``python -m world_server ...`` are the same thing.
"""

from __future__ import annotations

import importlib
import sys

# command -> module whose ``main(argv) -> int`` runs it
SUBCOMMANDS = {"sweep": "deploy.experiments.sweep", "report": "deploy.experiments.report", "view": "deploy.record.view",
               "export": "deploy.record.export", "deploy": "deploy.multihost.hosts", "bench": "bench.__main__"}
# bench/__init__.py's HEADLINE_KEYS, named here so the launcher imports nothing of the benches (tests/test_benches.py)
BENCHES = ("lidar", "perception", "scheduler", "channel", "pipeline", "fuzz")

USAGE = """usage: autocast <command> [args]

commands:
  run [flags]            one run: world, channel proxy, one agent per connected vehicle
                         and the MCAP recorder as processes (autocast run --help)
  world [flags]          run the world server with lane-following test agents
                         (python -m world_server --help for the flags)
  sweep [flags]          a matrix of runs from a preset or a file, resumable
                         (autocast sweep --help)
  report SWEEP_DIR       the paper's tables and plots from a sweep's results
  view RUN.mcap          a rerun recording of a run (--save out.rrd for headless use)
  export RUN.mcap --foxglove OUT.mcap
                         the run's scene in Foxglove's schemas (its 3-D panel)
  deploy [flags]         start a run's processes spread over several hosts
                         (autocast deploy --help)
  bench NAME [--quick]   print benchmark figures; NAME is one of: {benches}
""".format(benches=", ".join(BENCHES))


def main(argv: list[str] | None = None) -> int:
    own_process = argv is None  # the command line of this process, not a call from Python
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        return 0 if argv else 2
    cmd, rest = argv[0], argv[1:]
    if cmd == "run":
        from deploy.launch.run import exit_now, main as run_main
        code = run_main(rest)
        if own_process:
            exit_now(code)
        return code
    if cmd == "world":
        from world_server.__main__ import main as world_main
        return world_main(rest)
    if cmd in SUBCOMMANDS:
        return importlib.import_module(SUBCOMMANDS[cmd]).main(rest)
    print(f"autocast: unknown command {cmd!r}\n\n{USAGE}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
