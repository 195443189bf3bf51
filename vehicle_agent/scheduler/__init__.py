"""Which objects each vehicle sends in which PHY frame (the paper's scheduler section).

Pure algorithms over a canonical ``Instance``; every agent calls them identically::

    instance = make_instance(offers, p_deliver, vids=live_vids)
    schedule = get("autocast")(instance, state)
    plan = tdma_plan(instance, schedule)
    state = state.advance(instance, schedule)
"""

from vehicle_agent.scheduler.agnostic import agnostic_schedule
from vehicle_agent.scheduler.fill import fill_order, work_conserving
from vehicle_agent.scheduler.greedy import greedy_schedule
from vehicle_agent.scheduler.instance import (
    Instance,
    ObjectKey,
    ObjectOffer,
    Schedule,
    SenderOffers,
    check_schedule,
    expected_reward,
    frame_weights,
    instance_from_arrays,
    link_probabilities,
    link_probability,
    make_instance,
    weight_H,
)
from vehicle_agent.scheduler.knapsack import InstanceTooLarge, knapsack_exact, knapsack_fptas
from vehicle_agent.scheduler.optimal import MdpSolution, mdp_optimal, optimal_open_loop
from vehicle_agent.scheduler.registry import SchedulerFn, UnknownSchedulerError, get, names, register
from vehicle_agent.scheduler.state import SchedulerState
from vehicle_agent.scheduler.tdma import Slot, TdmaPlan, Transmission, tdma_plan, tdma_rows

__all__ = [
    "Instance",
    "InstanceTooLarge",
    "MdpSolution",
    "ObjectKey",
    "ObjectOffer",
    "Schedule",
    "SchedulerFn",
    "SchedulerState",
    "SenderOffers",
    "Slot",
    "TdmaPlan",
    "Transmission",
    "UnknownSchedulerError",
    "agnostic_schedule",
    "check_schedule",
    "expected_reward",
    "fill_order",
    "frame_weights",
    "get",
    "greedy_schedule",
    "instance_from_arrays",
    "knapsack_exact",
    "knapsack_fptas",
    "link_probabilities",
    "link_probability",
    "make_instance",
    "mdp_optimal",
    "names",
    "optimal_open_loop",
    "register",
    "tdma_plan",
    "tdma_rows",
    "weight_H",
    "work_conserving",
]
