"""Every Zenoh key expression, built by one function each.

``ac/<run>/...``: one run's keys never mix with another's. ``vid`` may be ``"*"`` for
subscribers that want every vehicle. No other module builds a key string by hand.
"""

from __future__ import annotations

import re

_RUN_ID = re.compile(r"^[A-Za-z0-9_\-]+$")


def _run(run: str) -> str:
    if not _RUN_ID.match(run):
        raise ValueError(f"run id {run!r}: use letters, digits, '-' and '_' only")
    return f"ac/{run}"


def _vid(vid: int | str) -> str:
    if vid == "*" or (isinstance(vid, int) and vid >= 0):
        return str(vid)
    raise ValueError(f"vehicle id {vid!r}: a non-negative int or '*'")


def world_tick(run: str) -> str:
    return f"{_run(run)}/world/tick"


def world_map(run: str) -> str:
    return f"{_run(run)}/world/map"


def world_truth(run: str) -> str:
    """Ground truth per tick (``WorldTruth``): recorded, never read by agents."""
    return f"{_run(run)}/world/truth"


def world_outcome(run: str) -> str:
    return f"{_run(run)}/world/outcome"


def mission(run: str, vid: int | str) -> str:
    return f"{_run(run)}/v/{_vid(vid)}/mission"


def scan(run: str, vid: int | str) -> str:
    return f"{_run(run)}/v/{_vid(vid)}/scan"


def cmd(run: str, vid: int | str) -> str:
    return f"{_run(run)}/v/{_vid(vid)}/cmd"


def report(run: str, vid: int | str) -> str:
    """The ego's per-tick report of its fused view, for the judge."""
    return f"{_run(run)}/v/{_vid(vid)}/report"


def rejected(run: str, vid: int | str) -> str:
    """What an agent rejected as not authentic so far (``Rejected``), for the log."""
    return f"{_run(run)}/v/{_vid(vid)}/rejected"


def alive(run: str, vid: int | str) -> str:
    """Liveliness token key: present while the agent's session is up."""
    return f"{_run(run)}/alive/v/{_vid(vid)}"


def _net(run: str, channel: int | str, domain: int | str) -> str:
    """``ac/<run>/net`` for domain 0 on channel 0 (every map of one domain: a run's keys
    as they always were), ``ac/<run>/net/c<channel>/d<domain>`` for any other domain,
    ``ac/<run>/net/**`` for every domain (either one ``"*"``)."""
    if channel == "*" or domain == "*":
        return f"{_run(run)}/net/**"
    for name, value in (("channel", channel), ("domain", domain)):
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise ValueError(f"{name} {value!r}: a non-negative int or '*'")
    if channel == 0 and domain == 0:
        return f"{_run(run)}/net"
    return f"{_run(run)}/net/c{channel}/d{domain}"


def net_ctrl_tx(run: str, vid: int | str, channel: int | str = 0, domain: int | str = 0) -> str:
    """A vehicle's control message in a scheduler domain, into the channel proxy."""
    return f"{_net(run, channel, domain)}/ctrl/tx/{_vid(vid)}"


def net_ctrl_rx(run: str, channel: int | str = 0, domain: int | str = 0) -> str:
    """Who heard which control message of a domain, out of the channel proxy (one for all receivers)."""
    return f"{_net(run, channel, domain)}/ctrl/rx"


def net_data_tx(run: str, vid: int | str, channel: int | str = 0, domain: int | str = 0) -> str:
    return f"{_net(run, channel, domain)}/data/tx/{_vid(vid)}"


def net_data_rx(run: str, channel: int | str = 0, domain: int | str = 0) -> str:
    """Who decoded which object payload of a domain, out of the channel proxy (one for all receivers)."""
    return f"{_net(run, channel, domain)}/data/rx"


def channel_domain_of(key: str) -> tuple[int, int]:
    """The (channel, domain) of a ``net`` key: (0, 0) for the plain keys."""
    parts = str(key).split("/")
    try:
        at = parts.index("net") + 1
    except ValueError:
        raise ValueError(f"no net key: {key!r}") from None
    ch, dom = (parts[at:at + 2] + ["", ""])[:2]
    if ch[:1] == "c" and dom[:1] == "d" and ch[1:].isdigit() and dom[1:].isdigit():
        return int(ch[1:]), int(dom[1:])
    return 0, 0


def net_part(key: str) -> str:
    """What a ``net`` key names below its channel and domain, alike in every domain:
    ``ctrl/tx/3``, ``data/rx``, ``stats``, ``emp/up/4``; "" for a key outside ``net``."""
    parts = str(key).split("/")
    if "net" not in parts:
        return ""
    rest = parts[parts.index("net") + 1:]
    if channel_domain_of(key) != (0, 0) or rest[:2] == ["c0", "d0"]:
        rest = rest[2:]
    return "/".join(rest)


def net_stats(run: str) -> str:
    return f"{_run(run)}/net/stats"


def vid_of(key: str) -> int:
    """The vehicle id in a per-vehicle key (``.../v/<vid>/...`` or ``.../net/.../<vid>``)."""
    parts = str(key).split("/")
    try:
        if "net" in parts:
            return int(parts[-1])
        return int(parts[parts.index("v") + 1])
    except (ValueError, IndexError):
        raise ValueError(f"no vehicle id in key {key!r}") from None


def net_emp_up(run: str, vid: int | str) -> str:
    """A vehicle's Voronoi segment, up to the EMP edge relay."""
    return f"{_run(run)}/net/emp/up/{_vid(vid)}"


def net_emp_down(run: str, vid: int | str) -> str:
    """What the EMP edge relay forwarded to a vehicle."""
    return f"{_run(run)}/net/emp/down/{_vid(vid)}"


def proxy_alive(run: str) -> str:
    """The channel proxy's liveliness token: present once it is subscribed and serving."""
    return f"{_run(run)}/alive/proxy"


def participant_alive(run: str, name: str) -> str:
    """Liveliness token of a participant the world was told to wait for (``--wait-for
    NAME``): any process of a run besides the agents and the proxy (a test's peer, a
    user's logger), declared once it is ready for tick 0."""
    if name != "*" and not _RUN_ID.match(name):
        raise ValueError(f"participant name {name!r}: use letters, digits, '-' and '_' only")
    return f"{_run(run)}/alive/p/{name}"


def alive_any(run: str) -> str:
    """Every liveliness token of a run: agents, the proxy, participants."""
    return f"{_run(run)}/alive/**"


def in_shm(key: str) -> str:
    """The twin of ``key`` that carries ``InShm`` notices when its payloads go through
    shared memory (``protocol.shm``)."""
    return f"{key}/shm"


def everything(run: str) -> str:
    """All of a run's keys, for the recorder."""
    return f"{_run(run)}/**"
