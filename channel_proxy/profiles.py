"""Radio profiles by name: bandwidth, frame structure, control capacity, reception model.

Add one with ``register_profile(ChannelProfile(name=..., ...))`` (or a new entry in
``PROFILES``); ``python -m channel_proxy --profile NAME`` and agents that build their
scheduling instances from the same profile then agree on B, T_n and N.
"""

from __future__ import annotations


from dataclasses import dataclass, field, replace

from channel_proxy.loss import PrrModel
from protocol import plugins


@dataclass(frozen=True, slots=True)
class ChannelProfile:
    """One radio technology as the proxy plays it."""

    name: str
    bandwidth_bps: float  # B of the data channel
    frame_duration_s: float  # T_n
    decision_interval_s: float = 0.1  # T_d; N = T_d / T_n frames
    ctrl_bandwidth_bps: float = 7.2e6  # the control channel's own resource pool
    ctrl_window_s: float = 0.1  # airtime of the control pool per interval
    prr: PrrModel = field(default_factory=PrrModel)
    description: str = ""

    def __post_init__(self) -> None:
        if self.bandwidth_bps <= 0 or self.frame_duration_s <= 0 or self.decision_interval_s <= 0:
            raise ValueError(f"profile {self.name!r}: bandwidth and durations must be positive")
        if self.frame_duration_s > self.decision_interval_s + 1e-12:
            raise ValueError(f"profile {self.name!r}: T_n exceeds T_d")

    @property
    def n_frames(self) -> int:
        return int(self.decision_interval_s / self.frame_duration_s + 1e-9)

    @property
    def frame_bytes(self) -> int:
        """S_f = B T_n / 8."""
        return int(self.bandwidth_bps * self.frame_duration_s / 8.0)

    @property
    def data_capacity_bytes(self) -> int:
        """What the data channel carries in one decision interval: B x N x T_n / 8."""
        return int(round(self.bandwidth_bps * self.n_frames * self.frame_duration_s / 8.0))

    @property
    def ctrl_capacity_bytes(self) -> int:
        return int(self.ctrl_bandwidth_bps * self.ctrl_window_s / 8.0)


PROFILES: dict[str, ChannelProfile] = {}
LOSSLESS = PrrModel(curve="fixed", p_fixed=1.0, range_m=1e6)  # every packet arrives, at any distance


def register_profile(profile: ChannelProfile) -> ChannelProfile:
    if profile.name in PROFILES:
        raise ValueError(f"channel profile {profile.name!r} already exists")
    PROFILES[profile.name] = profile
    return profile


def get_profile(name: str, channel_loss: str = "modelled") -> ChannelProfile:
    """A registered profile, or the ``ChannelProfile`` at an import path ``package.module:NAME``;
    with ``channel_loss="none"`` (a model's setting, ``protocol.model``) its reception model is
    replaced by one that loses nothing (capacity, frames and collisions stay)."""
    profile = _named_profile(name)
    return profile if channel_loss == "modelled" else replace(profile, prr=LOSSLESS)


def _named_profile(name: str) -> ChannelProfile:
    if name in PROFILES:
        return PROFILES[name]
    if plugins.is_import_path(name):
        try:
            profile = plugins.load(name)
        except plugins.PluginError as exc:
            raise KeyError(str(exc)) from None
        if not isinstance(profile, ChannelProfile):
            raise KeyError(f"{name!r} is a {type(profile).__name__}, not a ChannelProfile")
        return profile
    raise KeyError(f"unknown channel profile {name!r}; known: {', '.join(sorted(PROFILES))} "
                   "(or package.module:NAME)")


register_profile(ChannelProfile(
    "lte-direct", 7.2e6, 0.01,
    description="LTE-Direct QPSK 10 MHz (~7.2 Mbps), TDMA mode 4, ten 10 ms frames per 100 ms; R = 170 m urban",
))
register_profile(ChannelProfile(
    "lte-direct-100ms", 7.2e6, 0.1,
    description="as lte-direct with one 100 ms frame per interval",
))
register_profile(ChannelProfile(
    "dsrc", 6.0e6, 0.1, ctrl_bandwidth_bps=6.0e6,
    prr=PrrModel(range_m=150.0, sigma_db=4.0),
    description="DSRC / 802.11p 10 MHz QPSK 1/2 (6 Mbps), no frame structure; R = 150 m urban",
))
register_profile(ChannelProfile(
    "ideal", 7.2e6, 0.01, prr=LOSSLESS,
    description="7.2 Mbps, no channel loss, unlimited range (collisions and capacity still apply)",
))
register_profile(ChannelProfile(
    "emp-v2i", 50e6, 0.1, ctrl_bandwidth_bps=50e6,
    prr=PrrModel(range_m=300.0, sigma_db=4.0),
    description="EMP's V2I edge relay: 50 Mbps shared by uploads and forwards, R = 300 m around the relay",
))
