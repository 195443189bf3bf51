"""The V2V channel proxy: ``python -m channel_proxy --run-id RUN --connect HUB``.

Agents publish on ``net/ctrl/tx/<vid>`` and ``net/data/tx/<vid>``; the proxy publishes
on ``net/ctrl/rx`` and ``net/data/rx`` one bundle per phase with every message once and
which receiver heard (decoded) which, and per-interval statistics on ``net/stats``. It
follows the world's ticks (``world/tick``). ``--mode emp`` plays the EMP edge relay
instead (``net/emp/up/<vid>`` -> ``net/emp/down/<vid>``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import signal
import sys

from channel_proxy.loss import CURVES
from channel_proxy.profiles import PROFILES, get_profile
from channel_proxy.proxy import MODES, ChannelProxy, ProxyConfig
from protocol.model import OURS, Model, add_model_args, model_from
from protocol.session import add_zenoh_args, session_scope, zenoh_args_from
from protocol.shm import add_shm_arg

log = logging.getLogger("channel_proxy")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m channel_proxy", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run-id", help="the run's id (key prefix ac/<run>/)")
    ap.add_argument("--mode", choices=MODES, default="v2v", help="V2V medium, or the EMP edge relay")
    ap.add_argument("--profile", default=None, help="radio profile (default lte-direct; emp-v2i in EMP mode); "
                    "--list-profiles shows them")
    ap.add_argument("--list-profiles", action="store_true", help="print the profiles and exit")
    ap.add_argument("--seed", type=int, default=0, help="loss draws are a function of (seed, tick, link, item)")
    ap.add_argument("--ctrl-loss", type=float, default=0.0, help="fixed extra loss rate on control links")
    ap.add_argument("--data-loss", type=float, default=0.0, help="fixed extra loss rate on data links")
    rx = ap.add_argument_group("reception model (overrides the profile's)")
    rx.add_argument("--curve", choices=CURVES, default=None)
    rx.add_argument("--range-m", type=float, default=None, help="R: PRR(R) = 0.5 (shadowed, logistic)")
    rx.add_argument("--sigma-db", type=float, default=None, help="log-normal shadowing (shadowed)")
    rx.add_argument("--p-fixed", type=float, default=None, help="p at every distance (fixed)")
    rx.add_argument("--cutoff-m", type=float, default=None, help="nobody hears beyond (default 2R)")
    ph = ap.add_argument_group("phases")
    ph.add_argument("--realtime", action="store_true", help="close phases at wall-clock deadlines after each tick")
    ph.add_argument("--phase-timeout-s", type=float, default=5.0, help="lock-step: wait per phase for the missing")
    ph.add_argument("--dead-after", type=int, default=3, help="absences in a row before a vehicle is not waited for")
    ph.add_argument("--ctrl-deadline-s", type=float, default=0.03, help="real-time: control closes after the tick")
    ph.add_argument("--data-deadline-s", type=float, default=0.09, help="real-time: data closes after the tick")
    em = ap.add_argument_group("EMP relay")
    em.add_argument("--relay-xy", type=float, nargs=2, default=(0.0, 0.0), metavar=("X", "Y"))
    em.add_argument("--emp-bytes-per-point", type=float, default=None,
                    help="on-air coding of a segment's points (default: the model's, 6)")
    ap.add_argument("--relay-extra-frames", action="store_true",
                    help="a signed run: relay every frame of a vehicle's slot, not only its own (receivers verify; "
                         "docs/security.md)")
    ap.add_argument("--stay", action="store_true", help="keep running after the world's outcome")
    ap.add_argument("--log-level", default="WARNING")
    add_model_args(ap)
    add_shm_arg(ap)
    add_zenoh_args(ap)
    return ap.parse_args(argv)


def profile_from(args: argparse.Namespace, model: Model = OURS):
    """The profile named, else EMP's relay or the model's V2V radio, with the flags' reception model."""
    name = args.profile or ("emp-v2i" if args.mode == "emp" else model.channel_profile)
    profile = get_profile(name, model.channel_loss)
    overrides = {f: getattr(args, a) for f, a in (("curve", "curve"), ("range_m", "range_m"), ("sigma_db", "sigma_db"),
                                                   ("p_fixed", "p_fixed"), ("cutoff_m", "cutoff_m"))
                 if getattr(args, a) is not None}
    if overrides:
        profile = dataclasses.replace(profile, prr=dataclasses.replace(profile.prr, **overrides))
    return profile


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.list_profiles:
        for p in PROFILES.values():
            print(f"{p.name:<18} B={p.bandwidth_bps / 1e6:g} Mbps  T_n={p.frame_duration_s * 1e3:g} ms  "
                  f"N={p.n_frames}  R={p.prr.range_m:g} m ({p.prr.curve})  {p.description}")
        return 0
    if not args.run_id:
        print("error: --run-id is required", file=sys.stderr)
        return 2
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s proxy %(levelname)s %(message)s")
    try:
        model = model_from(args)
        emp_bytes = args.emp_bytes_per_point if args.emp_bytes_per_point is not None else model.emp_bytes_per_point
        config = ProxyConfig(
            run_id=args.run_id, profile=profile_from(args, model), mode=args.mode, seed=args.seed,
            ctrl_loss=args.ctrl_loss, data_loss=args.data_loss, realtime=args.realtime,
            phase_timeout_s=args.phase_timeout_s, dead_after=args.dead_after,
            ctrl_deadline_s=args.ctrl_deadline_s, data_deadline_s=args.data_deadline_s,
            relay_xy=tuple(args.relay_xy), emp_bytes_per_point=float(emp_bytes),
            exit_on_outcome=not args.stay, relay_extra_frames=args.relay_extra_frames, shm_dir=args.shm_dir,
        )
    except (KeyError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    p = config.profile
    log.info("%s mode, profile %s: B=%g Mbps, T_n=%g ms, N=%d, R=%g m", config.mode, p.name, p.bandwidth_bps / 1e6,
             p.frame_duration_s * 1e3, p.n_frames, p.prr.range_m)
    try:
        with session_scope(zenoh_args_from(args)) as session:
            proxy = ChannelProxy(config, session)
            signal.signal(signal.SIGINT, lambda *_: proxy.stop())
            signal.signal(signal.SIGTERM, lambda *_: proxy.stop())
            counters = proxy.serve()
    except ConnectionError as exc:
        log.error("%s", exc)
        return 2
    summary = dataclasses.asdict(counters)
    summary["malformed_dropped"] = proxy.drops.total
    log.info("proxy done: %s", json.dumps(summary))
    print(proxy.drops.exit_line("proxy"), file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
