"""The agent's per-tick step.

For now the agent is a lane follower: it tracks its mission route at its cruise
speed (stationary vehicles hold still). Perception, spatial reasoning, scheduling,
fusion and planning join this step as their stages land, one line each.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from protocol.messages import Command, Mission, Scan
from vehicle_agent.control import VehicleController


@dataclass
class LaneFollower:
    mission: Mission
    controller: VehicleController = field(init=False)

    def __post_init__(self) -> None:
        self.controller = VehicleController(self.mission.spec, self.mission.decision_interval_s)

    def run_step(self, scan: Scan) -> Command:
        accel, steer = self.controller.run_step(scan.pose, scan.speed_mps, self.mission.route,
                                                self.mission.cruise_speed_mps)
        return Command(scan.tick, scan.t_sim_s, self.mission.vid, accel, steer)
