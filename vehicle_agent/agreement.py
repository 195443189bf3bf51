"""Decentralised schedule agreement: which control messages a vehicle schedules over,
and when it may transmit, so that vehicles that heard different messages do not collide.

Why a rule is needed. Every vehicle computes the schedule itself from the control
messages it heard. Two senders whose instances differ lay out different TDMA plans and
their airtimes overlap. With independent control loss q and n vehicles, a vehicle hears
all n - 1 others with probability (1 - q)^(n-1): 1.6% at n = 40, q = 10%. So no rule
that needs every vehicle's fresh object map can keep vehicles in agreement, and one
interval's messages cannot be confirmed before they are used (one broadcast round).

The rule (pure functions; every input is something the vehicle heard):

1. Members. Each control message carries ``heard``: whom its sender heard last interval.
   A vehicle counts, over the ballots it holds (its own heard set and those of the
   messages it heard), how many list each vehicle (an author's own listing does not
   count); the members M are those listed by at least ``quorum`` (10%) of the ballots. A
   live vehicle of the domain appears on most ballots, a silent one on none, so every
   vehicle computes the same M with overwhelming probability (a binomial tail) although
   no two hold the same ballots; only a vehicle heard by about a tenth of the others
   (far out at the edge of radio range) can be a member for some and not for others. A
   newcomer is a member from its second interval on; in the very first interval nobody
   is, and nobody transmits.
2. Groups. M is split into G = min(N, ceil(|M| / group_size)) groups of equal size by
   ranking the members on a hash of (tick, vid) (the grouping changes every tick, so
   every pair of vehicles competes sometimes); group g owns PHY frames f with f mod G = g.
   Frames of different groups are disjoint, so groups cannot collide with each other.
   (Ranking keeps groups equal, at a price: a vehicle counted by some and not by others
   shifts the ranks behind it and regroups them for that interval. Hashing each member
   straight to a group would confine such a split to one group, but unequal groups cost
   3-10% of the reward in the bench; with the 10% quorum splits are rare enough.)
3. Completeness. Inside its group a vehicle schedules the group members' fresh offers
   with the real scheduler (greedy: prioritisation by H/s across the group's senders)
   and transmits its own part of the plan only if it heard every member of its group.
   Every vehicle that does transmit built the same instance (same members, same
   messages, same frames, same p) and so the same plan: no overlap. A vehicle that
   missed a group member stays silent this interval (its share of the group's frames is
   lost, nothing else is).

The price is the choice of group size: a group of g senders is complete with
probability (1 - q)^(g-1) (73% for g = 4 at q = 10%), while smaller groups prioritise
across fewer senders (at 40 vehicles, groups of 4 keep ~0.9 of the global greedy's
reward with perfect control). ``group_size=None`` is one group: the paper's global
schedule, exact but rarely complete under loss. ``rule="heard"`` is the paper's naive
behaviour (schedule over whatever was heard, always transmit), for comparison.

p_ij in the instance must be agreed too: it is the reception model (``channel_proxy.loss``,
the proxy's own) at the distance between two group members' reported poses, and the
model at the domain radius for a receiver outside the group, whose fresh pose not every
member holds. Scheduler state is not carried across intervals by the vehicles that
schedule: it would diverge between vehicles that heard different messages.
``agreed_state`` derives it from the decision alone: the starvation counters m are
those the group members' own messages report for their objects (``ControlMsg.unscheduled``,
each sender counting its own objects with ``unscheduled_after``), and agnostic's round
robin starts at a group member picked by the tick. So every complete member weighs the
group's objects with the same compensated H/s.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from channel_proxy.loss import PrrModel, keyed_uniform_1d, link_probabilities
from protocol.codec import MalformedMessage, decode, decode_fields, fields_decoder, slots_constructor
from protocol.messages import ControlMsg, Pose
from vehicle_agent.scheduler import Instance, Schedule, SchedulerState, SenderOffers, get, make_instance, tdma_rows

RULES = ("grouped", "heard")
GROUPING_SALT = 0x61677265  # keys the grouping hash apart from the channel's loss draws
_BEFORE_ANY_OBJECT = -(1 << 62)  # an object id below every real one


@dataclass(frozen=True, slots=True)
class AgreementConfig:
    """What every vehicle of a domain must configure identically."""

    rule: str = "grouped"
    group_size: int | None = 4  # senders per group; None: one group (the paper's global schedule)
    quorum: float = 0.1  # share of ballots that must list a vehicle for it to be a member
    n_frames: int = 10  # N
    frame_duration_s: float = 0.01  # T_n
    bandwidth_bps: float = 7.2e6  # B
    domain_radius_m: float = 85.0  # R/2: p for receivers outside the group is the model's here
    prr: PrrModel = field(default_factory=PrrModel)
    scheduler: str = "autocast"

    def __post_init__(self) -> None:
        if self.rule not in RULES:
            raise ValueError(f"rule must be one of {RULES}")
        if self.group_size is not None and self.group_size < 1:
            raise ValueError("group_size must be >= 1 or None")
        if not 0.0 <= self.quorum <= 1.0 or self.n_frames < 1:
            raise ValueError("quorum must lie in [0, 1] and n_frames be >= 1")

    @staticmethod
    def from_profile(profile, **kw) -> AgreementConfig:
        """The B, T_n, N and reception model of a ``channel_proxy.profiles.ChannelProfile``."""
        return AgreementConfig(n_frames=profile.n_frames, frame_duration_s=profile.frame_duration_s,
                               bandwidth_bps=profile.bandwidth_bps, prr=profile.prr, **kw)


# --------------------------------------------------------------------- the rule's steps


def members(ballots: Mapping[int, Iterable[int]], quorum: float) -> np.ndarray:
    """Vehicles that at least ``quorum`` of the ballots (and at least one) list as heard,
    ascending. ``ballots`` maps each ballot's author to whom it heard last interval; an
    author's listing of itself does not count: a member is a vehicle others heard."""
    if not ballots:
        return np.zeros(0, dtype=np.int64)
    need = max(1, math.ceil(quorum * len(ballots) - 1e-9))
    lists = list(ballots.values())
    if all(type(h) is np.ndarray and h.ndim == 1 for h in lists):  # as messages carry them: int64 arrays
        vid = np.concatenate(lists)
        if vid.dtype == np.int64:  # each list's values as np.asarray(h, dtype=np.int64) gives them
            got = _listed_by_quorum(np.fromiter(ballots, dtype=np.int64, count=len(ballots)), vid,
                                    np.array([len(h) for h in lists], dtype=np.int64), need)
            if got is not None:
                return got
    listed = [np.asarray(h if isinstance(h, np.ndarray) else list(h), dtype=np.int64).ravel()
              for h in ballots.values()]
    lengths = [len(h) for h in listed]
    author = np.repeat(np.fromiter(ballots, dtype=np.int64, count=len(ballots)), lengths)
    vid = np.concatenate(listed)
    no_repeats = _each_ascending(vid, lengths)
    others = vid != author
    vid, author = vid[others], author[others]
    if no_repeats and (not len(vid) or (vid.min() >= 0 and vid.max() < 1 << 16)):
        counted = np.bincount(vid)  # no ballot lists a vehicle twice: one vote per entry
        vids = np.flatnonzero(counted)
        votes = counted[vids]
    elif no_repeats:
        vids, votes = np.unique(vid, return_counts=True)
    else:
        order = np.lexsort((author, vid))  # a ballot listing a vehicle twice still votes once
        vid, author = vid[order], author[order]
        first = np.ones(len(vid), dtype=bool)
        first[1:] = (vid[1:] != vid[:-1]) | (author[1:] != author[:-1])
        vids, votes = np.unique(vid[first], return_counts=True)
    return vids[votes >= need].astype(np.int64)


@njit(cache=True)
def _listed_by_quorum(author, vid, lengths, need):
    """``members`` of ballots whose lists are concatenated in ``vid`` (``lengths`` each,
    by ``author``): the vehicles at least ``need`` ballots list, not counting an author's
    listing of itself nor a ballot's second listing of a vehicle; ascending. None if a
    listed id lies outside [0, 2^16) (``members`` counts those with numpy)."""
    top = -1
    for e in range(vid.shape[0]):
        if vid[e] < 0 or vid[e] >= 1 << 16:
            return None
        top = max(top, vid[e])
    votes = np.zeros(top + 1, dtype=np.int64)
    last = np.full(top + 1, -1, dtype=np.int64)  # the last ballot that listed each vehicle
    e = 0
    for b in range(lengths.shape[0]):
        for _ in range(lengths[b]):
            v = vid[e]
            e += 1
            if v != author[b] and last[v] != b:
                last[v] = b
                votes[v] += 1
    n = 0
    for v in range(top + 1):
        n += votes[v] >= need
    out = np.empty(n, dtype=np.int64)
    n = 0
    for v in range(top + 1):
        if votes[v] >= need:
            out[n] = v
            n += 1
    return out


def _each_ascending(values: np.ndarray, lengths: list[int]) -> bool:
    """Each run of ``lengths`` consecutive values strictly ascending (as the heard lists
    of control messages are): then no ballot lists a vehicle twice."""
    if len(values) < 2:
        return True
    rises = values[1:] > values[:-1]
    starts = np.cumsum(lengths)[:-1]  # a run's first value need not exceed the one before it
    rises[starts[(starts > 0) & (starts < len(values))] - 1] = True
    return bool(rises.all())


def n_groups(n_members: int, group_size: int | None, n_frames: int) -> int:
    if n_members == 0:
        return 0
    if group_size is None:
        return 1
    return min(n_frames, max(1, math.ceil(n_members / group_size)))


def group_of(member_vids: np.ndarray, tick: int, n: int) -> np.ndarray:
    """Group index of each member: members ranked by a hash of (tick, vid), dealt round
    robin into ``n`` groups, so sizes differ by at most one and change every tick."""
    vids = np.asarray(member_vids, dtype=np.int64)
    if n <= 0:
        return np.full(len(vids), -1, dtype=np.int64)
    rank = np.empty(len(vids), dtype=np.int64)
    rank[np.lexsort((vids, keyed_uniform_1d(GROUPING_SALT, tick, vids)))] = np.arange(len(vids))
    return rank % n


def frames_of(group: int, n: int, n_frames: int) -> tuple[int, ...]:
    """The PHY frames group ``group`` of ``n`` owns: f with f mod n = group."""
    return tuple(f for f in range(n_frames) if n > 0 and f % n == group)


@dataclass(frozen=True, slots=True, eq=False)
class HeardControl:
    """A control message heard this interval, read as far as every vehicle needs it:
    its sender's ballot (``heard``) for the members, and its motion for the neighbour
    table. The object map, most of the message, only the sender's group schedules
    over: ``decide`` opens it (``message``) for its group's members alone, 3 of the 39
    messages a vehicle hears at 40 vehicles."""

    tick: int
    t_sim_s: float
    vid: int
    pose: Pose
    speed_mps: float
    trajectory: np.ndarray
    heard: np.ndarray
    raw: bytes

    FIELDS = ("tick", "t_sim_s", "vid", "pose", "speed_mps", "trajectory", "heard")

    @staticmethod
    def read(raw: bytes) -> HeardControl:
        """Raises ``MalformedMessage`` if the envelope or one of these fields is."""
        return _read_heard(raw)

    def message(self) -> ControlMsg:
        """The whole message; raises ``MalformedMessage`` (its object map, say), as
        ``decode`` would. The fields ``read`` took from ``raw`` are not read again: only
        the rest is (most of a decode's time was the object map, but not all)."""
        try:
            objects, unscheduled, digests, domains = decode_fields(self.raw, ControlMsg, _REST)
        except MalformedMessage:
            return decode(self.raw, ControlMsg)  # refused again, in decode's words
        return _new_control(self.tick, self.t_sim_s, self.vid, self.pose, self.speed_mps, self.trajectory, objects,
                            self.heard, unscheduled, digests, domains)


_read_heard = fields_decoder(ControlMsg, HeardControl.FIELDS, HeardControl)  # one generated function a message
_REST = tuple(f.name for f in dataclasses.fields(ControlMsg) if f.name not in HeardControl.FIELDS)
_new_control = slots_constructor(ControlMsg)  # ControlMsg(...) without the frozen __init__'s cost


def offers_of(msg: ControlMsg) -> SenderOffers:
    om = msg.objects
    return SenderOffers(om.object_id, om.size_bytes, om.receivers, om.visibility, om.relevance)


@dataclass(frozen=True, slots=True, eq=False)
class Decision:
    """What the rule decided for one vehicle and interval."""

    tick: int
    vid: int
    members: np.ndarray  # M, ascending
    group: np.ndarray  # the vehicle's group (members), ascending; empty if it is not a member
    frames: tuple[int, ...]  # the PHY frames its group owns
    missing: np.ndarray  # group members whose control message it did not hear (or could not read)
    messages: dict[int, ControlMsg]  # the group members' messages it schedules over (own included)
    malformed: dict[int, MalformedMessage] = field(default_factory=dict)  # heard, but unreadable when opened

    @property
    def is_member(self) -> bool:
        return self.vid in set(self.group.tolist())

    @property
    def transmits(self) -> bool:
        """Member, complete view of its group: its part of the group's plan is safe to send."""
        return self.is_member and len(self.missing) == 0 and len(self.frames) > 0


def decide(vid: int, tick: int, own: ControlMsg, heard: Sequence[ControlMsg | HeardControl],
           config: AgreementConfig) -> Decision:
    """Apply the rule to the control messages heard this interval (``own`` is the vehicle's
    own message of this interval; ``heard`` those in its ``CtrlBundle``, whole or as
    ``HeardControl``, whose object maps are opened here for the group's members only)."""
    ballots: dict[int, ControlMsg | HeardControl] = {int(m.vid): m for m in heard if m.tick == tick and m.vid != vid}
    ballots[vid] = own
    if config.rule == "heard":  # the paper's behaviour: one group of whatever was heard
        msgs, bad = _opened(ballots)
        everyone = np.array(sorted(msgs), dtype=np.int64)
        return Decision(tick, vid, everyone, everyone, tuple(range(config.n_frames)), np.zeros(0, np.int64), msgs,
                        bad)
    m = members({v: msg.heard for v, msg in ballots.items()}, config.quorum)
    G = n_groups(len(m), config.group_size, config.n_frames)
    groups = group_of(m, tick, G)
    mine = np.flatnonzero(m == vid)
    if len(mine) == 0:
        return Decision(tick, vid, m, np.zeros(0, np.int64), (), np.zeros(0, np.int64), {vid: own})
    g = int(groups[mine[0]])
    group = m[groups == g]
    msgs, bad = _opened({v: ballots[v] for v in group.tolist() if v in ballots})
    missing = np.array([v for v in group.tolist() if v not in msgs], dtype=np.int64)
    return Decision(tick, vid, m, group, frames_of(g, G, config.n_frames), missing, msgs, bad)


def _opened(ballots: Mapping[int, ControlMsg | HeardControl]) -> tuple[dict[int, ControlMsg],
                                                                       dict[int, MalformedMessage]]:
    """The whole messages of ``ballots`` (same order), and the errors of those that
    cannot be read: a vehicle that cannot read a member's object map did not hear it."""
    msgs, bad = {}, {}
    for v, m in ballots.items():
        if isinstance(m, HeardControl):
            try:
                msgs[v] = m.message()
            except MalformedMessage as err:
                bad[v] = err
        else:
            msgs[v] = m
    return msgs, bad


# --------------------------------------------------------------------- the plan


@dataclass(frozen=True, slots=True)
class PlannedTx:
    """One of the vehicle's own transmissions: start from the start of the data phase."""

    object_id: int
    start_s: float
    size_bytes: int
    frame: int


def agreed_p(decision: Decision, config: AgreementConfig) -> AgreedLinks:
    """p_ij from what every complete group member holds: the model at the distance
    between two group members' reported poses, the model at the domain radius otherwise."""
    known = sorted(decision.messages)
    xy = np.array([[decision.messages[v].pose.x_m, decision.messages[v].pose.y_m] for v in known]).reshape(-1, 2)
    outside = _OUTSIDE.get(config)
    if outside is None:
        outside = _OUTSIDE[config] = float(config.prr.prr(config.domain_radius_m))
    return AgreedLinks({v: n for n, v in enumerate(known)}, link_probabilities(xy, config.prr), outside)


_OUTSIDE: dict[AgreementConfig, float] = {}  # the model at the domain radius, by configuration: one a process


@dataclass(frozen=True, slots=True)
class AgreedLinks:
    """p_ij between the vehicles ``at`` indexes into ``p``; ``outside`` for any other pair.
    Call it for one pair, or ask for the ``matrix`` of many (what ``make_instance`` does)."""

    at: dict[int, int]
    p: np.ndarray
    outside: float

    def __call__(self, i: int, j: int) -> float:
        a, b = self.at.get(i), self.at.get(j)
        return self.outside if a is None or b is None else float(self.p[a, b])

    def matrix(self, vids: Sequence[int]) -> np.ndarray:
        out = np.full((len(vids), len(vids)), self.outside)
        known = [(n, self.at[v]) for n, v in enumerate(vids) if v in self.at]  # a group's few among the members
        if known:
            rows, at = (np.array(x, dtype=np.int64) for x in zip(*known))
            out[rows[:, None], rows] = self.p[at[:, None], at]
        return out


def agreed_state(decision: Decision) -> SchedulerState:
    """Scheduler state every group member derives alike from the messages it schedules
    over: the starvation counters m their senders report for their own objects, and a
    round-robin cursor just before the first object of the group member the tick picks
    (``group[tick mod |group|]``), so agnostic's rotation moves on every interval
    without a carried cursor, which would diverge between vehicles; and the tick as the
    key of a shuffled order (``agnostic-shuffle``)."""
    if len(decision.group) == 0:
        return SchedulerState()
    first = int(decision.group[decision.tick % len(decision.group)])
    starved = []  # (vid, object id, m) of each object its sender reports m > 0 for, in message order
    for v, msg in decision.messages.items():
        ids, u = msg.objects.object_id, msg.unscheduled
        if type(u) is np.ndarray and u.dtype == np.int64 and u.shape == (len(ids),):
            counts = u.tolist()  # msg.starvation() without its copies: max(m, 0) > 0 where m > 0
        else:
            counts = msg.starvation().tolist()
        if counts and max(counts) > 0:  # a few numbers: plain Python, not a dozen numpy calls
            starved += [(v, k, c) for k, c in zip(np.asarray(ids, dtype=np.int64).tolist(), counts) if c > 0]
    starved.sort(key=lambda s: (s[0], s[1]))  # SchedulerState keeps its keys ascending by (vid, object id); stable
    key = np.array([(v, k) for v, k, _ in starved], dtype=np.int64).reshape(-1, 2)
    return SchedulerState(key, np.array([c for _, _, c in starved], dtype=np.int64), cursor=(first, _BEFORE_ANY_OBJECT),
                          order_key=decision.tick)


def unscheduled_after(own: ControlMsg, sent: Iterable[int]) -> dict[int, int]:
    """A sender's starvation counters for its next control message, by object id: m + 1
    for each object of ``own`` still wanted (some y = (1 - v) r > 0, the instance's
    ``wanted``) that is not among its ``sent`` object ids this interval (a silent
    vehicle sent nothing), and no entry (m = 0) for the others; an object it no longer
    tracks is forgotten with its track."""
    om = own.objects
    ids = np.asarray(om.object_id).tolist()
    y = (1.0 - np.asarray(om.visibility, dtype=np.float64)) * np.asarray(om.relevance, dtype=np.float64)
    wanted = (y > 0.0).any(axis=1).tolist() if y.size else [False] * len(ids)
    u = own.unscheduled
    if type(u) is np.ndarray and u.dtype == np.int64 and u.shape == (len(ids),):
        counts = u.tolist()  # own.starvation() without its copies: m is max(count, 0)
    else:
        counts = own.starvation().tolist()
    sent_ids = {int(k) for k in sent}  # a set, not np.isin: ~10 objects, isin's sort cost 20 us
    return {int(k): max(c, 0) + 1 for k, w, c in zip(ids, wanted, counts) if w and k not in sent_ids}


def group_schedule(decision: Decision, config: AgreementConfig) -> tuple[Instance, SchedulerState, Schedule]:
    """The group's instance, the agreed state and the scheduler's schedule over them:
    identical on every vehicle whose ``decision.transmits``."""
    offers = {v: offers_of(m) for v, m in decision.messages.items()}
    instance = make_instance(
        offers, agreed_p(decision, config), vids=decision.members,  # and the senders, which make_instance adds
        bandwidth_bps=config.bandwidth_bps, frame_duration_s=config.frame_duration_s,
        decision_interval_s=len(decision.frames) * config.frame_duration_s,
    )
    state = agreed_state(decision)
    return instance, state, get(config.scheduler)(instance, state)


def plan(decision: Decision, config: AgreementConfig) -> tuple[PlannedTx, ...]:
    """The vehicle's own transmissions this interval (empty unless ``decision.transmits``):
    the scheduler run on its group's instance, laid out in its group's frames."""
    if not decision.transmits:
        return ()
    instance, _, schedule = group_schedule(decision, config)
    frame_s = instance.frame_bytes * 8.0 / instance.bandwidth_bps  # tdma_plan's frame_duration_s
    out = []
    for n, vid, object_id, _, start_s, _, size_bytes in tdma_rows(instance, schedule):  # tdma_plan's, as tuples
        if vid == decision.vid:
            frame = decision.frames[n]
            offset = start_s - n * frame_s
            out.append(_new_planned(object_id, frame * config.frame_duration_s + offset, size_bytes, frame))
    return tuple(out)


_new_planned = slots_constructor(PlannedTx)
