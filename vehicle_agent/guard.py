"""The agent's side of authenticated V2X (``protocol.security``): it seals what it sends
and lets through only what verifies.

Per interval: the control message vouches for every object payload the vehicle may
send (their digests), and is signed once; the command (and the ego's report) are
signed too. Of the control bundle the agent checks only its own row, the messages it
heard; of the data bundle only the payloads it decoded, each against its sender's
verified control message (heard, or else its slot's message in the control bundle,
checked only for that). Nothing else is decoded, so nothing else is verified.
"""

from __future__ import annotations

from protocol.codec import MalformedMessage
from protocol.messages import ControlMsg, CtrlBundle, Reception
from protocol.security import Credentials, PayloadCheck, Rejections, Signer, Verifier
from protocol.session import DropCounter
from vehicle_agent.payload import header_of

CTRL_STREAM = "ctrl bundle item"
DATA_STREAM = "data bundle item"


class Guard:
    """One vehicle's credentials at work: ``seal`` and the checks of the two bundles."""

    def __init__(self, credentials: Credentials, drops: DropCounter) -> None:
        self.vid = credentials.vid
        self.signer = Signer(credentials)
        self.rejections = Rejections()
        self.verifier = Verifier(credentials.authority, credentials.certificate.run_id, self.rejections)
        self._quiet = Verifier(credentials.authority, credentials.certificate.run_id)  # unheard: counted nowhere
        self.drops = drops

    def seal(self, msg) -> bytes:
        return self.signer.seal(msg)

    def heard(self, bundle: CtrlBundle | None, tick: int) -> tuple[list[ControlMsg] | None, PayloadCheck]:
        """The verified control messages this vehicle heard in ``bundle`` (None if there
        is no bundle or we are not a receiver: heard nothing), at most one per sender,
        and the interval's payload check, vouched by them."""
        check = PayloadCheck(tick, self.rejections, DATA_STREAM)
        frames = bundle.frames_heard_by(self.vid) if bundle is not None else None
        if frames is None:
            return None, check
        heard: list[ControlMsg] = []
        seen: set[int] = set()  # not check.vouched: a message whose digests do not fit its map vouches for nothing
        for sender, raw in frames:
            try:
                msg = self.verifier.open(raw, ControlMsg, sender, CTRL_STREAM,
                                         fresh=lambda m: m.tick == tick and m.vid not in seen)
            except MalformedMessage as err:
                self.drops.add(CTRL_STREAM, err)
                continue
            if msg is not None:
                heard.append(msg)
                seen.add(msg.vid)
                check.vouch(msg)
        return heard, check

    def payloads(self, received: list[Reception], check: PayloadCheck, bundle: CtrlBundle | None) -> list[bytes]:
        """The payloads of ``received`` their senders signed for this interval, in order."""
        out = []
        for r in received:
            if not check.vouched(r.sender) and bundle is not None:
                self._vouch_unheard(r.sender, check, bundle)
            if check.check(r.sender, r.payload, header_of(r.payload)):
                out.append(r.payload)
        return out

    def _vouch_unheard(self, sender: int, check: PayloadCheck, bundle: CtrlBundle) -> None:
        """A sender whose control message we did not hear: its slot's first message that
        verifies vouches for its payloads (used for nothing else; not counted as heard)."""
        for raw in bundle.frames_of(sender):
            try:
                msg = self._quiet.open(raw, ControlMsg, sender, CTRL_STREAM, fresh=lambda m: m.tick == check.tick)
            except MalformedMessage:
                continue
            if msg is not None:
                check.vouch(msg)
                return
