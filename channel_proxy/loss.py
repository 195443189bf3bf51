"""Per-link packet reception: the distance-based model and the seeded draws.

The model is the single source of truth for p_ij: the proxy draws losses from it and
agents may read it to fill ``p_deliver`` when they build a scheduling instance.

Curve ``shadowed`` (default), in the spirit of 3GPP TR 36.885's evaluation method:
received SNR falls with the WINNER+ B1 slope beyond the breakpoint (``10 n log10 d``,
n = 4) and is spread by log-normal shadowing of ``sigma_db``; a packet is received when
the SNR exceeds the QPSK threshold. With R the nominal radio range, where the PRR is
still ``prr_at_range`` (0.9),

    PRR(d) = Phi(z_R + 10 n log10(R / d) / sigma_db),   z_R = Phi^-1(prr_at_range)

With R = 170 m (urban), n = 4, sigma = 4 dB: 0.9998 at 100 m, 0.90 at 170 m, 0.72 at
200 m, 0.35 at 250 m, 0.12 at 300 m. Curve ``logistic`` is 1 / (1 + exp((d - d50) /
spread_m)) with d50 placed so that PRR(R) = ``prr_at_range``; curve ``fixed`` is a
constant ``p_fixed`` up to R. Beyond ``cutoff_m`` p is exactly 0 and the sender does not
interfere either: that receiver is out of range. The default cutoff is where the PRR
falls below 0.001 (465 m for the defaults; R for ``fixed``).

Draws are counter-based, not sequential: a loss decision is a hash of
(seed, tick, channel, sender, receiver, item), so the outcome of one packet never
depends on how many others came before it or in which order they arrived.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

CURVES = ("shadowed", "logistic", "fixed")
_GRID_POINTS = 4097
_FLOOR = 0.001  # the default cutoff: where the PRR falls below this

# channel ids in the draw key
CTRL = 0
DATA = 1
EMP_UP = 2
EMP_DOWN = 3


@dataclass(frozen=True, slots=True)
class PrrModel:
    """Packet reception ratio as a function of sender-receiver distance."""

    curve: str = "shadowed"
    range_m: float = 170.0  # R, the nominal range: PRR(R) = prr_at_range
    prr_at_range: float = 0.9
    exponent: float = 4.0  # n: path-loss exponent beyond the breakpoint (WINNER+ B1)
    sigma_db: float = 4.0  # log-normal shadowing (TR 36.885: 3 dB LOS, 4 dB NLOS)
    spread_m: float = 20.0  # logistic only
    p_fixed: float = 1.0  # fixed only
    cutoff_m: float | None = None  # nobody hears or is disturbed beyond; None: where PRR < 0.001
    _grid: np.ndarray = field(init=False, repr=False, compare=False)
    _max_range_m: float = field(init=False, repr=False, compare=False)
    _knots: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.curve not in CURVES:
            raise ValueError(f"unknown PRR curve {self.curve!r}; known: {', '.join(CURVES)}")
        if self.range_m <= 0 or self.sigma_db <= 0 or self.spread_m <= 0 or self.exponent <= 0:
            raise ValueError("range_m, exponent, sigma_db and spread_m must be positive")
        if not 0.0 <= self.p_fixed <= 1.0 or not 0.0 < self.prr_at_range < 1.0:
            raise ValueError("p_fixed must lie in [0, 1] and prr_at_range in (0, 1)")
        object.__setattr__(self, "_max_range_m", self._cutoff())
        object.__setattr__(self, "_knots", np.linspace(0.0, self.max_range_m, _GRID_POINTS))
        object.__setattr__(self, "_grid", self._exact(self._knots))

    @property
    def max_range_m(self) -> float:
        """Beyond this distance p is 0 (computed once: agents read it every interval)."""
        return self._max_range_m

    def _cutoff(self) -> float:
        if self.cutoff_m is not None:
            return float(self.cutoff_m)
        if self.curve == "fixed":
            return self.range_m
        if self.curve == "logistic":
            return self._d50() + self.spread_m * math.log(999.0)
        return self.range_m * 10.0 ** ((_probit(self.prr_at_range) - _probit(_FLOOR)) * self.sigma_db
                                       / (10.0 * self.exponent))

    def _d50(self) -> float:
        return self.range_m + self.spread_m * math.log(self.prr_at_range / (1.0 - self.prr_at_range))

    def _exact(self, d: np.ndarray) -> np.ndarray:
        if self.curve == "fixed":
            return np.full(d.shape, self.p_fixed)
        if self.curve == "logistic":
            return 1.0 / (1.0 + np.exp((d - self._d50()) / self.spread_m))
        z = _probit(self.prr_at_range) + 10.0 * self.exponent * np.log10(self.range_m / np.maximum(d, 1.0)) / self.sigma_db
        return np.array([0.5 * math.erfc(-x / math.sqrt(2.0)) for x in z.ravel()]).reshape(d.shape)  # Phi(z)

    def prr(self, distance_m: np.ndarray | float) -> np.ndarray:
        """p at each distance (vectorised: interpolated on a fine grid); 0 beyond the cutoff."""
        d = np.asarray(distance_m, dtype=np.float64)
        p = np.interp(d, self._knots, self._grid)
        return np.where(d <= self.max_range_m, p, 0.0)


def _probit(p: float) -> float:
    """Phi^-1(p) by bisection (no scipy dependency)."""
    lo, hi = -10.0, 10.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if 0.5 * math.erfc(-mid / math.sqrt(2.0)) < p:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def distances(xy: np.ndarray) -> np.ndarray:
    """(C, C) pairwise distances of (C, 2) positions; NaN rows (unknown position) stay NaN."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])


def link_probabilities(xy: np.ndarray, model: PrrModel, extra_loss: float = 0.0) -> np.ndarray:
    """(C, C) p_ij from positions, times (1 - extra_loss); p_ii = 1; unknown positions give 0."""
    return probabilities_at(distances(xy), model, extra_loss)


def probabilities_at(d: np.ndarray, model: PrrModel, extra_loss: float = 0.0) -> np.ndarray:
    """``link_probabilities`` from the pairwise ``distances`` (the proxy works them out
    once an interval for both channels and the range)."""
    known = ~np.isnan(d)
    p = np.where(known, model.prr(np.where(known, d, np.inf)), 0.0) * (1.0 - extra_loss)
    np.fill_diagonal(p, 1.0)
    return p


def in_range(xy: np.ndarray, model: PrrModel) -> np.ndarray:
    """(C, C) bool: j is within the cutoff of i (hears it at all, or is disturbed by it); i reaches itself."""
    return within_cutoff(distances(xy), model)


def within_cutoff(d: np.ndarray, model: PrrModel) -> np.ndarray:
    """``in_range`` from the pairwise ``distances``."""
    r = np.where(np.isnan(d), False, d <= model.max_range_m)
    np.fill_diagonal(r, True)
    return r


# ------------------------------------------------------------------------ seeded draws

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64's finaliser: a bijective avalanche on uint64."""
    x = x ^ (x >> np.uint64(30))
    x = x * _M1
    x = x ^ (x >> np.uint64(27))
    x = x * _M2
    return x ^ (x >> np.uint64(31))


def keyed_uniform(seed: int, *keys: np.ndarray | int) -> np.ndarray:
    """Uniform [0, 1) draws, one per element of the broadcast ``keys``; each draw is a
    pure function of (seed, key tuple), independent of every other draw."""
    arrays = [np.atleast_1d(np.asarray(k)).astype(np.int64).view(np.uint64) for k in keys]
    shape = np.broadcast_shapes(*(a.shape for a in arrays)) if arrays else (1,)
    # each key mixes in at the shape it broadcasts to so far, not at the draws' full
    # shape: the same uint64 operations on every element (a draw's hash is its own key
    # tuple's), but a link draw's (sender, receiver, item) keys mix a (T, 1) head once
    # per sender, not per link (the proxy draws T x C of them every interval)
    h = np.full((1,) * len(shape), np.uint64(seed & 0xFFFFFFFFFFFFFFFF))
    with np.errstate(over="ignore"):
        h = _mix(h + _GOLDEN)
        for a in arrays:
            h = _mix(h ^ (a + _GOLDEN))
    h = np.broadcast_to(h, shape)
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


@njit(cache=True)
def _mix_one(x):
    """``_mix`` of one uint64."""
    x = x ^ (x >> np.uint64(30))
    x = x * _M1
    x = x ^ (x >> np.uint64(27))
    x = x * _M2
    return x ^ (x >> np.uint64(31))


@njit(cache=True)
def _keyed_uniform_1d(seed, tick, keys):
    out = np.empty(len(keys))
    head = _mix_one(_mix_one(seed + _GOLDEN) ^ (np.uint64(tick) + _GOLDEN))
    for i in range(len(keys)):
        h = _mix_one(head ^ (np.uint64(keys[i]) + _GOLDEN))
        out[i] = np.float64(h >> np.uint64(11)) * (1.0 / 9007199254740992.0)
    return out


def keyed_uniform_1d(seed: int, tick: int, keys: np.ndarray) -> np.ndarray:
    """``keyed_uniform(seed, tick, keys)`` for one tick and a 1-D int64 ``keys``, in one
    pass: the same hash, the same floats (numpy's elementwise version spent ~25 calls on
    40 keys; the agents draw their grouping with it every interval)."""
    return _keyed_uniform_1d(np.uint64(seed & 0xFFFFFFFFFFFFFFFF), np.int64(tick),
                             np.ascontiguousarray(keys, dtype=np.int64))


def bernoulli(p: np.ndarray, seed: int, *keys: np.ndarray | int) -> np.ndarray:
    """bool: success with probability ``p``, drawn from the keyed generator."""
    return keyed_uniform(seed, *keys) < np.asarray(p)
