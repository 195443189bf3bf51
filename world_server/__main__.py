"""The world server: ``python -m world_server --scenario left_turn --vehicles 10``.

By default it is the run's Zenoh hub (listening on loopback) and spawns one
lane-following ``vehicle_agent`` process per connected vehicle; ``--agents external``
waits for agents started elsewhere (the launcher, another host).
"""

from __future__ import annotations

import argparse
import json
import logging
import secrets
import signal
import sys
import time

from processes.manager import ProcessManager, ProcSpec
from protocol import keys
from protocol.model import ModelError, add_model_args, lidar_config, model_from
from protocol.security import Verifier
from protocol.session import DEFAULT_HUB, ZenohArgs, add_zenoh_args, session_scope, zenoh_args_from
from protocol.shm import add_shm_arg
from world_server import geometry, lidar
from world_server.scenarios import ScenarioError, load_scenario_file, params_from_dict
from world_server.server import WorldServer
from world_server.sim import Simulation

log = logging.getLogger("world_server")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m world_server", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sc = ap.add_argument_group("scenario")
    sc.add_argument("--scenario", default=None, help="overtaking | left_turn | red_light (default left_turn); "
                    "corridor3 | grid4 | corridor3x | grid4_handover: several junctions (docs/domains.md)")
    sc.add_argument("--vehicles", type=int, default=None,
                    help="connected vehicles in range, ego included (default 10; at most 64 a scheduler domain "
                    "of the map)")
    sc.add_argument("--collider-speed", type=float, default=None, metavar="KMH", help="collider base speed (default 30)")
    sc.add_argument("--delta", type=float, default=None, metavar="SECONDS",
                    help="collider reaches the conflict point this long after the ego (default 0)")
    sc.add_argument("--seed", type=int, default=None)
    sc.add_argument("--duration", type=float, default=None, metavar="SECONDS", help="sim time limit (default: the scenario's own, 30-40 s for the paper's)")
    sc.add_argument("--scenario-file", default=None, help="a TOML file of the same fields; flags override it")
    ap.add_argument("--run-id", default=None, help="key prefix ac/<run>/ (default: generated)")
    ap.add_argument("--realtime", action="store_true", help="tick on the wall clock instead of lock-step")
    ap.add_argument("--agents", choices=["spawn", "external"], default="spawn",
                    help="spawn lane-following agent processes, or wait for external ones")
    ap.add_argument("--agent-timeout-s", type=float, default=10.0,
                    help="wall time an agent may take for one tick before it is declared dead")
    ap.add_argument("--startup-timeout-s", type=float, default=120.0)
    ap.add_argument("--ego-reports", action="store_true",
                    help="each event's ego agent reports its fused view every tick: lock-step waits for it from "
                         "the first tick")
    ap.add_argument("--wait-for", nargs="+", default=[], metavar="NAME",
                    help="also wait, before tick 0, for each named participant's liveliness token "
                         "ac/<run>/alive/p/NAME (a process that must see the run from its first tick)")
    ap.add_argument("--wait-for-proxy", action="store_true",
                    help="also wait, before tick 0, for the channel proxy's liveliness token ac/<run>/alive/proxy "
                         "(a run with a V2V channel or EMP's relay: tick 0's messages go through the proxy)")
    ap.add_argument("--authority", default=None, metavar="HEX",
                    help="the run's authority's Ed25519 public key: accept only commands and reports signed by "
                         "the vehicle's own certificate (docs/security.md)")
    ap.add_argument("--json", action="store_true", help="end with the outcome as one JSON line")
    ap.add_argument("--log-level", default="INFO")
    add_model_args(ap)
    add_shm_arg(ap)
    add_zenoh_args(ap)
    return ap.parse_args(argv)


def scenario_params(args: argparse.Namespace):
    values = _file_fields(args.scenario_file) if args.scenario_file else {}
    flags = {"scenario": args.scenario, "vehicles": args.vehicles, "collider_speed_kmh": args.collider_speed,
             "delta_s": args.delta, "seed": args.seed, "duration_s": args.duration}
    values.update({k: v for k, v in flags.items() if v is not None})
    return params_from_dict(values)


def _file_fields(path: str) -> dict:
    params = load_scenario_file(path)
    return {name: getattr(params, name) for name in params.__dataclass_fields__}


def summary(result: dict) -> str:
    """The outcome in one line; a run of several events: a line per event, then the run's
    (its worst event's outcome)."""
    if result["outcome"] is None:
        return f"not judged: {result.get('failure')}  [{result['scenario']}, {result['vehicles']} vehicles, " \
               f"seed {result['seed']}, {result['ticks']} ticks]"
    run = (f"[{result['scenario']}, {result['vehicles']} vehicles, seed {result['seed']}, "
           f"{result['ticks']} ticks in {result['wall_s']:.1f} s wall]")
    events = result.get("events")
    if not events:
        return f"{_judged(result)}  {run}"
    lines = [f"{e['event']} (ego {e['ego']}, collider {e['collider']}): {_judged(e)}  at {e['t_end_s']:.1f} s"
             for e in events]
    worst = f"outcome: {result['outcome']} (the worst of {len(events)} events: {result['event']})"
    return "\n".join([*lines, f"{worst}  {run}"])


def _judged(r: dict) -> str:
    react, closest = r["reaction_time_s"], r["closest_distance_m"]
    return (f"outcome: {r['outcome']}  closest distance {'n/a' if closest is None else f'{closest:.2f} m'}  "
            f"reaction time {'n/a' if react is None else f'{react:.2f} s'}  "
            f"collider in the ego's {'fused' if r['visibility_source'] == 'fused' else 'own'} view "
            f"{100 * r['collider_visible_share']:.0f}% of ticks ({r['collider_points_mean']:.0f} points mean)")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s world %(levelname)s %(message)s")
    try:
        params = scenario_params(args)
        sim = Simulation(params, lidar_config(model_from(args)))
    except (ScenarioError, ModelError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    run_id = args.run_id or time.strftime("%Y%m%d-%H%M%S-") + secrets.token_hex(2)
    try:
        for name in args.wait_for:
            keys.participant_alive(run_id, name)
    except ValueError as exc:
        print(f"error: wait_for: {exc}", file=sys.stderr)
        return 2
    try:
        verifier = Verifier(bytes.fromhex(args.authority), run_id) if args.authority else None
    except ValueError as exc:
        print(f"error: authority: {exc}", file=sys.stderr)
        return 2
    z = zenoh_args_from(args)
    if not z.listen and not z.connect and not z.config_file:
        z = ZenohArgs(listen=(DEFAULT_HUB,))
    lidar.warm_up(sim.lidar_cfg)
    geometry.warm_up()
    agent_hub = list(z.listen[:1] or z.connect[:1])
    with session_scope(z) as session, ProcessManager() as procs:
        server = WorldServer(sim, session, run_id, realtime=args.realtime,
                             agent_timeout_s=args.agent_timeout_s, startup_timeout_s=args.startup_timeout_s,
                             ego_reports=args.ego_reports, verifier=verifier, wait_for=tuple(args.wait_for),
                             wait_for_proxy=args.wait_for_proxy, shm_dir=args.shm_dir)
        signal.signal(signal.SIGINT, lambda *_: server.stop())
        signal.signal(signal.SIGTERM, lambda *_: server.stop())
        if args.agents == "spawn":
            for vid in sim.connected_vids:
                flags = ["--run-id", run_id, "--vid", str(vid), "--scheme", "lane"] + \
                    [f for ep in agent_hub for f in ("--connect", ep)] + \
                    (["--shm-dir", args.shm_dir] if args.shm_dir else [])
                procs.start(ProcSpec(f"agent{vid}", "vehicle_agent", tuple(flags)))
        result = server.serve()
        print(summary(result))
        if args.json:
            print(json.dumps(result, allow_nan=False), flush=True)
    print(server.drops.exit_line("world"), file=sys.stderr, flush=True)  # after the session closed: every drop
    if verifier is not None:
        print(verifier.rejections.exit_line("world"), file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
