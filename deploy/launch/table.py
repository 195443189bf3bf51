"""The one table of a run's processes (openpilot's process_config).

``processes(cfg)`` says, for one run, which processes exist and with which flags: the
recorder, the world, the channel proxy (every scheme that shares) and one agent per
connected vehicle. The launcher (``deploy/launch/run.py``) only starts, watches and stops
what this table returns; nothing else decides what a run is made of.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path

from processes.manager import ProcSpec
from protocol.model import OURS, Model
from world_server.scenarios import ScenarioParams, build

RECORDER = "recorder"
WORLD = "world"
PROXY = "proxy"
NO_PROXY_SCHEMES = ("single", "lane")  # no V2V: nothing for a channel to carry
EMP_SCHEME = "emp"  # the paper's EMP baseline: the proxy plays the edge relay
SCHEDULING_SCHEMES = ("agnostic", "autocast", "autocast-fptas")  # the ones --scheduler can replace
DEFAULT_PROFILE = "lte-direct"


@dataclass(frozen=True, slots=True)
class RunConfig:
    """Everything that defines one run's processes."""

    run_id: str
    hub: str  # the launcher's Zenoh endpoint; every process connects to it
    params: ScenarioParams
    scheme: str
    run_dir: Path  # runs/<id>
    realtime: bool = False
    scans: str = "ego"  # which LiDAR scans the recorder keeps
    agent_timeout_s: float = 10.0
    log_level: str = "INFO"  # world, proxy, recorder
    agent_log_level: str = "WARNING"  # N agents at INFO would bury the other logs
    scheduler: str | None = None  # None: the scheme's own
    channel_profile: str = DEFAULT_PROFILE  # the V2V radio, played by the proxy, assumed by the agents
    signing: bool = False  # V2X messages signed and verified (docs/security.md)
    authority: str = ""  # the run's authority's public key (hex) once credentials are issued (deploy.launch.credentials)
    lock_down: bool = False  # Zenoh: a password per process and the run's ACL (deploy.launch.credentials)
    wait_for: tuple[str, ...] = ()  # participants besides the table's whose token the world waits for before tick 0
    shm_dir: str = ""  # one host's run: the scans and bundles go through this directory (protocol.shm)
    json_mirror: bool = True  # the recorder also writes every message as JSON, for Foxglove (docs/viewing.md)
    model: Model = OURS  # the modelling profile every process runs under (protocol.model, docs/models.md)

    @property
    def mcap_path(self) -> Path:
        return self.run_dir / "run.mcap"

    @property
    def log_dir(self) -> Path:
        return self.run_dir / "logs"


def processes(cfg: RunConfig) -> list[ProcSpec]:
    """The run's processes, in start order; the recorder comes first."""
    table = [
        ProcSpec(RECORDER, "deploy.record.recorder", recorder_args(cfg), critical=True),
        ProcSpec(WORLD, "world_server", world_args(cfg), critical=True),
    ]
    if needs_proxy(cfg.scheme):
        table.append(ProcSpec(PROXY, "channel_proxy", proxy_args(cfg), critical=True))
    table += [ProcSpec(agent_name(vid), "vehicle_agent", agent_args(cfg, vid)) for vid in connected_vids(cfg.params)]
    return table


def agent_name(vid: int) -> str:
    return f"agent{vid}"


@functools.lru_cache(maxsize=8)
def connected_vids(params: ScenarioParams) -> tuple[int, ...]:
    """The connected vehicles' ids; building the scenario also validates it (``ScenarioError``)."""
    return tuple(a.vid for a in build(params).connected())


@functools.lru_cache(maxsize=8)
def net_domains(params: ScenarioParams) -> tuple[tuple[int, int], ...]:
    """(channel, domain) of each scheduler domain of the scenario's map (docs/domains.md):
    ``((0, 0),)`` for a map of one."""
    return tuple((d.channel, d.domain_id) for d in build(params).roadmap.to_msg().scheduler_domains())


def needs_proxy(scheme: str) -> bool:
    """Every scheme that shares needs the medium (``emp``: the proxy's edge-relay mode)."""
    return scheme not in NO_PROXY_SCHEMES


def _common(cfg: RunConfig, name: str) -> tuple[str, ...]:
    flags = ("--run-id", cfg.run_id, "--connect", cfg.hub)
    if cfg.lock_down:
        flags += ("--zenoh-config", str(zenoh_config_path(cfg, name)))
    if cfg.shm_dir and name != RECORDER:  # the recorder subscribes to what it keeps: the writers send that over Zenoh
        flags += ("--shm-dir", cfg.shm_dir)
    return flags


def credentials_dir(cfg: RunConfig) -> Path:
    return cfg.run_dir / "credentials"


def v2x_credentials_path(cfg: RunConfig, vid: int) -> Path:
    """Vehicle ``vid``'s key and certificate (``protocol.security.Credentials``)."""
    return credentials_dir(cfg) / f"{agent_name(vid)}.v2x.json"


def zenoh_config_path(cfg: RunConfig, name: str) -> Path:
    """Process (or router) ``name``'s Zenoh config with its password (``deploy.launch.credentials``)."""
    return credentials_dir(cfg) / f"{name}.zenoh.json5"


def recorder_args(cfg: RunConfig) -> tuple[str, ...]:
    p = cfg.params
    meta = {"scenario": p.scenario, "vehicles": p.vehicles, "seed": p.seed, "scheme": cfg.scheme,
            "scheduler": cfg.scheduler or "", "channel_profile": cfg.channel_profile,
            "collider_speed_kmh": p.collider_speed_kmh, "delta_s": p.delta_s, "duration_s": p.duration_s,
            "mode": "realtime" if cfg.realtime else "lockstep", "signed": cfg.signing, "lock_down": cfg.lock_down,
            "model": cfg.model.label(), "model_settings": json.dumps(cfg.model.settings(), sort_keys=True)}
    flags = [f for k, v in meta.items() for f in ("--meta", f"{k}={v}")]
    mirror = ("--json-mirror",) if cfg.json_mirror else ()  # JSON beside msgpack: Foxglove reads it (docs/viewing.md)
    return (*_common(cfg, RECORDER), "--out", str(cfg.mcap_path), "--scans", cfg.scans, "--log-level", cfg.log_level,
            *mirror, *flags)


def world_args(cfg: RunConfig) -> tuple[str, ...]:
    p = cfg.params
    flags = [*_common(cfg, WORLD), "--agents", "external", "--json", "--log-level", cfg.log_level,
             "--scenario", p.scenario, "--vehicles", str(p.vehicles), "--collider-speed", str(p.collider_speed_kmh),
             "--delta", str(p.delta_s), "--seed", str(p.seed), "--duration", str(p.duration_s),
             "--agent-timeout-s", str(cfg.agent_timeout_s), *cfg.model.args()]
    if cfg.realtime:
        flags.append("--realtime")
    if cfg.scheme != "lane":  # every agent pipeline but the blind lane follower reports the ego's fused view
        flags.append("--ego-reports")
    if cfg.signing:
        flags += ["--authority", _authority(cfg)]
    if needs_proxy(cfg.scheme):  # the agents' tick-0 messages go through the proxy: it must be subscribed
        flags.append("--wait-for-proxy")
    if cfg.wait_for:
        flags += ["--wait-for", *cfg.wait_for]
    return tuple(flags)


NOT_ISSUED = "ISSUED-AT-LAUNCH"  # --dry-run: the authority's key does not exist yet


def _authority(cfg: RunConfig) -> str:
    return cfg.authority or NOT_ISSUED


def proxy_args(cfg: RunConfig) -> tuple[str, ...]:
    flags = [*_common(cfg, PROXY), "--seed", str(cfg.params.seed), "--log-level", cfg.log_level,
             "--mode", "emp" if cfg.scheme == EMP_SCHEME else "v2v", *cfg.model.args()]
    if cfg.scheme != EMP_SCHEME:
        flags += ["--profile", cfg.channel_profile]
    else:  # EMP's segments on the air, as the model charges them
        flags += ["--emp-bytes-per-point", str(cfg.model.emp_bytes_per_point)]
    if cfg.realtime:
        flags.append("--realtime")
    if cfg.signing:  # receivers verify: the medium relays every frame of a slot
        flags.append("--relay-extra-frames")
    return tuple(flags)


def agent_args(cfg: RunConfig, vid: int) -> tuple[str, ...]:
    flags = [*_common(cfg, agent_name(vid)), "--vid", str(vid), "--scheme", cfg.scheme, "--log-level",
             cfg.agent_log_level, "--channel-profile", cfg.channel_profile, *cfg.model.args()]
    if cfg.scheduler:
        flags += ["--scheduler", cfg.scheduler]
    if cfg.signing:
        flags += ["--credentials", str(v2x_credentials_path(cfg, vid))]
    return tuple(flags)
