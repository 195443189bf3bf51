"""The modelling choices a run is made of, as one named profile.

Two profiles ship. ``ours`` (the default) is this system's engineering: compact
payloads, tracked and held objects, a decentralised schedule in groups. ``paper`` is
the model behind the paper's evaluation (its text first, the authors' evaluated code
where the text is silent; ``docs/models.md`` cites each value): an object's points
thinned to 5 cm columns, 24 bytes a point on the air, Agnostic in a fresh random order
every interval, no spare-airtime fill, a received object used in the interval it
arrives in only, the authors' LiDAR, one global schedule over one 100 ms frame, no channel loss.

Every setting can also be set alone on top of a profile (``autocast run --model paper
--model-set hold_s=1.0``). The world, the proxy and every agent resolve the same
``Model`` from the same name and settings, so the run's processes agree on it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

OBJECT_POINTS = ("all", "column")  # every point above the ground | one point per column of ``column_m``
AGNOSTIC_ORDERS = ("rotation", "shuffle")
CHANNEL_LOSSES = ("modelled", "none")  # the radio profile's reception model | every packet in range arrives


class ModelError(ValueError):
    """A bad model name or setting; the message starts with the field's name."""


@dataclass(frozen=True, slots=True)
class Model:
    """One value per modelling choice that differs between our model and the paper's."""

    name: str = "ours"
    object_points: str = "all"  # which of an object's points it offers and sends
    column_m: float = 0.05  # with object_points="column": one point per column this wide
    ground_cut_m: float = 0.25  # with object_points="column": points at most this high are left out (all: 0.25,
    # the perception's obstacle threshold)
    bytes_per_point: int = 6  # on the air: 6 (int16 centimetres) or 24 (three float64)
    agnostic_order: str = "rotation"  # agnostic's order: a rotating round robin, or a fresh shuffle every interval
    fill_spare: bool = True  # AutoCast fills the frames' spare airtime with the objects nobody needs
    hold_s: float = 1.0  # how long a received object stays in the fused view after its reception
    lidar_range_m: float = 100.0
    lidar_fov_up_deg: float = 2.0
    lidar_fov_down_deg: float = -24.8
    group_size: int = 4  # senders per agreement group; 0: one group of every member (a global schedule)
    channel_profile: str = "lte-direct"  # the V2V radio (channel_proxy.profiles), unless a run names its own
    emp_bytes_per_point: int = 6  # EMP's segments on the air
    channel_loss: str = "modelled"  # V2V and relay loss: the radio profile's reception model, or none at all

    def __post_init__(self) -> None:
        _check(self)

    def settings(self) -> dict[str, Any]:
        """Every setting but the name, as plain values (for records and metadata)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "name"}

    def differences(self, base: Model | None = None) -> dict[str, Any]:
        """The settings whose value differs from ``base`` (default: the profile it is named after)."""
        ref = (base or PROFILES.get(self.name, OURS)).settings()
        return {k: v for k, v in self.settings().items() if ref[k] != v}

    def label(self) -> str:
        """``paper``, or ``paper+hold_s=1.0`` when settings were changed on top of a profile."""
        extra = self.differences()
        return self.name + "".join(f"+{k}={_text(v)}" for k, v in sorted(extra.items()))

    def args(self) -> tuple[str, ...]:
        """The command-line flags that resolve to this model in another process."""
        flags: list[str] = ["--model", self.name]
        for k, v in sorted(self.differences().items()):
            flags += ["--model-set", f"{k}={_text(v)}"]
        return tuple(flags)


def _text(v: Any) -> str:
    return ("true" if v else "false") if isinstance(v, bool) else str(v)


def _check(m: Model) -> None:
    if m.object_points not in OBJECT_POINTS:
        raise ModelError(f"object_points: {m.object_points!r} is not one of {', '.join(OBJECT_POINTS)}")
    if m.agnostic_order not in AGNOSTIC_ORDERS:
        raise ModelError(f"agnostic_order: {m.agnostic_order!r} is not one of {', '.join(AGNOSTIC_ORDERS)}")
    if m.channel_loss not in CHANNEL_LOSSES:
        raise ModelError(f"channel_loss: {m.channel_loss!r} is not one of {', '.join(CHANNEL_LOSSES)}")
    if m.bytes_per_point not in (6, 24):
        raise ModelError(f"bytes_per_point: {m.bytes_per_point!r} is not 6 or 24")
    if m.emp_bytes_per_point < 1:
        raise ModelError(f"emp_bytes_per_point: {m.emp_bytes_per_point!r} is not >= 1")
    for name in ("column_m", "lidar_range_m"):
        v = getattr(m, name)
        if not (math.isfinite(v) and v > 0):
            raise ModelError(f"{name}: {v!r} is not a finite number > 0")
    for name in ("ground_cut_m", "hold_s"):
        v = getattr(m, name)
        if not (math.isfinite(v) and v >= 0):
            raise ModelError(f"{name}: {v!r} is not a finite number >= 0")
    for name in ("lidar_fov_up_deg", "lidar_fov_down_deg"):
        v = getattr(m, name)
        if not (math.isfinite(v) and -90 < v < 90):
            raise ModelError(f"{name}: {v!r} is not within (-90, 90)")
    if not m.lidar_fov_down_deg < m.lidar_fov_up_deg:
        raise ModelError(f"lidar_fov_up_deg: {m.lidar_fov_up_deg!r} is not above lidar_fov_down_deg "
                         f"({m.lidar_fov_down_deg!r})")
    if m.object_points == "all":  # the column settings shape nothing then: a changed one would be a label, not a model
        for name, default in (("column_m", 0.05), ("ground_cut_m", 0.25)):
            if getattr(m, name) != default:
                raise ModelError(f"{name}: applies with object_points=column only (all: every point above the "
                                 f"perception's 0.25 m)")
    if m.group_size < 0:
        raise ModelError(f"group_size: {m.group_size!r} is not >= 0")


OURS = Model()

# The paper's evaluation. Where each value comes from: docs/models.md.
PAPER = Model(
    name="paper",
    object_points="column",
    column_m=0.05,
    ground_cut_m=0.5,
    bytes_per_point=24,
    agnostic_order="shuffle",
    fill_spare=False,
    hold_s=0.0,
    lidar_range_m=50.0,
    lidar_fov_up_deg=4.0,
    lidar_fov_down_deg=-20.0,
    group_size=0,
    channel_profile="lte-direct-100ms",
    emp_bytes_per_point=24,
    channel_loss="none",
)

PROFILES: dict[str, Model] = {OURS.name: OURS, PAPER.name: PAPER}
DEFAULT = OURS.name
SETTINGS = tuple(f.name for f in dataclasses.fields(Model) if f.name != "name")


def resolve(name: str = DEFAULT, settings: Mapping[str, Any] | Iterable[str] = ()) -> Model:
    """The profile ``name`` with ``settings`` on top: a mapping of setting to value, or
    ``KEY=VALUE`` texts as the command line gives them. Raises ``ModelError`` naming the
    field."""
    base = PROFILES.get(name) if isinstance(name, str) else None
    if base is None:
        raise ModelError(f"model: {name!r} is not one of {', '.join(PROFILES)}")
    if not isinstance(settings, Mapping):
        pairs: dict[str, Any] = {}
        for text in settings:
            key, sep, value = str(text).partition("=")
            if not sep:
                raise ModelError(f"model_set: {text!r} is not KEY=VALUE")
            pairs[key.strip()] = value.strip()
        settings = pairs
    values: dict[str, Any] = {}
    types = {f.name: f.type for f in dataclasses.fields(Model)}
    for key, value in settings.items():
        if key not in SETTINGS:
            raise ModelError(f"{key}: unknown model setting (known: {', '.join(SETTINGS)})")
        values[key] = _coerce(key, value, types[key])
    return dataclasses.replace(base, **values)


def _coerce(key: str, value: Any, kind: str) -> Any:
    if kind == "bool":
        if isinstance(value, bool):
            return value
        text = str(value).lower()
        if text in ("true", "1", "yes", "on"):
            return True
        if text in ("false", "0", "no", "off"):
            return False
        raise ModelError(f"{key}: {value!r} is not true or false")
    if kind == "int":
        if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
            raise ModelError(f"{key}: {value!r} is not an integer")
        try:
            return int(value)
        except (TypeError, ValueError):
            raise ModelError(f"{key}: {value!r} is not an integer") from None
    if kind == "float":
        try:
            out = float(value)
        except (TypeError, ValueError):
            raise ModelError(f"{key}: {value!r} is not a number") from None
        if isinstance(value, bool):
            raise ModelError(f"{key}: {value!r} is not a number")
        return out
    return str(value)


def add_model_args(ap) -> None:
    """``--model`` and ``--model-set`` on a process's parser."""
    ap.add_argument("--model", default=DEFAULT, help=f"the modelling profile: {' | '.join(PROFILES)} "
                                                     f"(default {DEFAULT}; docs/models.md)")
    ap.add_argument("--model-set", action="append", default=[], metavar="KEY=VALUE",
                    help="change one setting of the profile (repeatable): " + ", ".join(SETTINGS))


def model_from(args) -> Model:
    return resolve(args.model, args.model_set)


def lidar_config(model: Model):
    """The LiDAR every vehicle carries under ``model`` (``LidarConfig``'s other fields as they are)."""
    from protocol.messages import LidarConfig

    return LidarConfig(range_m=model.lidar_range_m, fov_up_deg=model.lidar_fov_up_deg,
                       fov_down_deg=model.lidar_fov_down_deg)
