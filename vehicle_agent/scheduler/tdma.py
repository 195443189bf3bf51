"""TDMA layout of a schedule: who transmits what, when, inside each frame.

Frame n starts at n * T_n. Inside it, senders take turns in decreasing order of the
summed reward of the objects they send in that frame (ties: lower vid first), each
sending its objects back to back, highest reward first (ties: lower object id). The
objects a work-conserving schedule put in the frame's spare airtime (``Schedule.fill``)
follow all of those, laid out by the same rule among themselves, so they delay
nothing. An object of s bytes lasts s * 8 / B seconds. Every agent computes the same layout from
the same schedule, so a sender knows its slot and a receiver knows when to listen.
"""

from __future__ import annotations

from dataclasses import dataclass

from protocol.codec import slots_constructor
from vehicle_agent.scheduler.instance import Instance, Schedule


@dataclass(frozen=True, slots=True)
class Transmission:
    frame: int
    vid: int  # sender i
    object_id: int  # k
    index: int  # object index in the instance
    start_s: float  # from the start of the decision interval
    duration_s: float  # s_ik * 8 / B
    size_bytes: int


@dataclass(frozen=True, slots=True)
class Slot:
    """One sender's contiguous turn in one frame."""

    frame: int
    vid: int
    start_s: float
    duration_s: float


@dataclass(frozen=True, slots=True)
class TdmaPlan:
    transmissions: tuple[Transmission, ...]  # in time order
    frame_duration_s: float

    def slots(self) -> tuple[Slot, ...]:
        """Each sender's turn per frame, in time order."""
        out: list[Slot] = []
        for t in self.transmissions:
            last = out[-1] if out else None
            if last is not None and last.frame == t.frame and last.vid == t.vid:
                out[-1] = Slot(t.frame, t.vid, last.start_s, t.start_s + t.duration_s - last.start_s)
            else:
                out.append(Slot(t.frame, t.vid, t.start_s, t.duration_s))
        return tuple(out)

    def sent_by(self, vid: int) -> tuple[Transmission, ...]:
        return tuple(t for t in self.transmissions if t.vid == vid)


def tdma_plan(instance: Instance, schedule: Schedule) -> TdmaPlan:
    """Lay the schedule out in time (frame duration T_n = S_f * 8 / B)."""
    rows = tdma_rows(instance, schedule)
    return TdmaPlan(tuple(_new_transmission(*row) for row in rows), instance.frame_bytes * 8.0 / instance.bandwidth_bps)


def tdma_rows(instance: Instance, schedule: Schedule) -> list[tuple[int, int, int, int, float, float, int]]:
    """``tdma_plan``'s transmissions as tuples of their fields (frame, vid, object_id,
    index, start_s, duration_s, size_bytes), in time order: for a caller that keeps a
    few of them (a vehicle its own, ``agreement.plan``) without a record for each."""
    frame_s = instance.frame_bytes * 8.0 / instance.bandwidth_bps
    scheduled = sorted(schedule.sent())
    total_reward = dict(zip(scheduled, instance.reward[scheduled].sum(axis=1).tolist()))  # sum_j y_(i,k),j
    owner = instance.owner.tolist()
    vids = instance.vids.tolist()
    oids = instance.object_id.tolist()
    sizes = instance.size_bytes.tolist()
    bandwidth_bps = instance.bandwidth_bps
    out: list[tuple[int, int, int, int, float, float, int]] = []
    for n, frame in enumerate(schedule.frames):
        spare = set(schedule.filled(n))
        t = n * frame_s
        for part in ([k for k in frame if k not in spare], sorted(spare)) if spare else (frame,):
            by_sender: dict[int, list[int]] = {}
            for k in part:
                by_sender.setdefault(owner[k], []).append(k)
            senders = sorted(by_sender, key=lambda i: (-sum(total_reward[k] for k in by_sender[i]), vids[i]))
            for i in senders:
                for k in sorted(by_sender[i], key=lambda k: (-total_reward[k], oids[k])):
                    duration = sizes[k] * 8.0 / bandwidth_bps
                    out.append((n, vids[i], oids[k], k, t, duration, sizes[k]))
                    t += duration
    return out


_new_transmission = slots_constructor(Transmission)  # Transmission(...) without the frozen __init__'s setattr calls
