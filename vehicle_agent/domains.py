"""Which scheduler domains a vehicle takes part in (paper 4.1, docs/domains.md).

The map declares the domains (``MapMsg.domains``: centre, radius R/2, channel; a map
that declares none has one around the origin). A vehicle belongs to every domain whose
circle, widened by the guard band, holds its position: two at a border, where it
schedules and transmits in both and hands over from one to the other as it drives on.
A vehicle within no domain's circle belongs to the nearest one, so every vehicle is in
at least one and a map of one domain puts every vehicle in it, wherever it drives.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from protocol.messages import ControlMsg, MapMsg
from vehicle_agent.agreement import AgreementConfig, Decision, HeardControl, PlannedTx, decide, plan

GUARD_BAND_M = 1.8  # 40 mph for one T_d: a vehicle joins a domain an interval before it enters it


@dataclass(frozen=True, slots=True)
class DomainTable:
    """The map's domains as arrays; row d is domain ``ids[d]`` (ids are 0, 1, ... in order)."""

    ids: np.ndarray  # int64 (D,)
    center: np.ndarray  # float64 (D, 2)
    radius_m: np.ndarray  # float64 (D,)
    channel: np.ndarray  # int64 (D,)

    @staticmethod
    def of(mapmsg: MapMsg) -> DomainTable:
        ds = mapmsg.scheduler_domains()
        return DomainTable(np.array([d.domain_id for d in ds], dtype=np.int64),
                           np.array([(d.x_m, d.y_m) for d in ds], dtype=np.float64).reshape(-1, 2),
                           np.array([d.radius_m for d in ds], dtype=np.float64),
                           np.array([d.channel for d in ds], dtype=np.int64))

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def limit_m(self) -> np.ndarray:
        """(D,) how far from its centre a vehicle is a member: the radius and the guard band."""
        return self.radius_m + GUARD_BAND_M

    def membership(self, x_m: float, y_m: float) -> tuple[int, ...]:
        """The domains a vehicle at (x, y) takes part in, ascending: every one within
        reach, else the nearest."""
        d = np.hypot(x_m - self.center[:, 0], y_m - self.center[:, 1])
        inside = np.flatnonzero(d <= self.limit_m)
        return tuple(int(self.ids[i]) for i in (inside if len(inside) else [int(np.argmin(d))]))

    def channel_of(self, domain: int) -> int:
        return int(self.channel[domain])


def schedule_domains(vid: int, tick: int, own: Mapping[int, ControlMsg],
                     heard: Mapping[int, Sequence[ControlMsg | HeardControl]],
                     config: AgreementConfig) -> dict[int, tuple[Decision, tuple[PlannedTx, ...]]]:
    """The agreement rule in each domain ``d`` of ``own`` on that domain's messages
    alone (``own[d]``, ``heard[d]``): its decision and this vehicle's transmissions
    there. What a vehicle decides in one domain does not depend on any other domain it
    is in, so vehicles that heard the same messages of a domain agree on its schedule."""
    out = {}
    for d in sorted(own):
        decision = decide(vid, tick, own[d], heard.get(d, ()), config)
        out[d] = (decision, plan(decision, config))
    return out
