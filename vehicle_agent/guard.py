"""The agent's side of authenticated V2X (``protocol.security``): it seals what it sends
and lets through only what verifies.

Per interval: the control message vouches for every object payload the vehicle may
send (their digests), and is signed once; the command (and the ego's report) are
signed too. Of the control bundle the agent checks only its own row, the messages it
heard; of the data bundle only the payloads it decoded, each against its sender's
verified control message (heard, or else its slot's message in the control bundle,
checked only for that). Nothing else is decoded, so nothing else is verified.
A control message another vehicle on the host found authentic this interval is not
verified again (``protocol.security.Verdicts``).
"""

from __future__ import annotations

import numpy as np

from protocol.codec import MalformedMessage
from protocol.messages import ControlMsg, CtrlBundle, Reception
from protocol.security import (Credentials, PayloadCheck, Rejections, Signer, Verdicts, Verifier, body_span,
                               fits)
from protocol.session import DropCounter
from vehicle_agent.agreement import HeardControl
from vehicle_agent.payload import DATA_STREAM, header_of

CTRL_STREAM = "ctrl bundle item"


class Guard:
    """One vehicle's credentials at work: ``seal`` and the checks of the two bundles."""

    def __init__(self, credentials: Credentials, drops: DropCounter, verdicts: Verdicts | None = None) -> None:
        """``verdicts``: what the host's receivers of the run found authentic, shared (None: check all here)."""
        self.vid = credentials.vid
        self.signer = Signer(credentials)
        self.rejections = Rejections()
        self.verdicts = verdicts
        run_id = credentials.certificate.run_id
        self.verifier = Verifier(credentials.authority, run_id, self.rejections)
        self._quiet = Verifier(credentials.authority, run_id)  # unheard: counted nowhere
        self.drops = drops

    def seal(self, msg) -> bytes:
        return self.signer.seal(msg)

    def heard(self, bundle: CtrlBundle | None, tick: int,
              ) -> tuple[list[ControlMsg | HeardControl] | None, PayloadCheck]:
        """The verified control messages this vehicle heard in ``bundle`` (None if there
        is no bundle or we are not a receiver: heard nothing), at most one per sender,
        and the interval's payload check, vouched by them.

        With the host's verdicts (``protocol.security.Verdicts``), a frame the bundle's
        table lists (another vehicle on the host found it authentic: certificate,
        signature, a body that decodes whole, of the certificate's vehicle and the
        envelope's tick, vouching for its payloads) is left only the checks that depend
        on the receiver, in ``Verifier.open``'s order and with its reasons: the slot it
        came in (``wrong_key``) and its interval, once per sender (``replayed``). It is
        read as far as every vehicle needs it (``HeardControl``, as without signing);
        ``decide`` opens its group's. Any other frame is opened here in full, and listed
        if it passes; one another vehicle is opening (``VerdictTable.claimed``) waits,
        with the frames after it in its sender's slot, until the others are done."""
        check = PayloadCheck(tick, self.rejections, DATA_STREAM)
        receivers = bundle.receivers.tolist() if bundle is not None else []
        if self.vid not in receivers:
            return None, check
        places = np.flatnonzero(bundle.heard[receivers.index(self.vid)]).tolist()  # by place in the bundle
        senders, messages = bundle.senders.tolist(), bundle.messages
        table = None
        if self.verdicts is not None:  # the receivers sweep the old tables in turns
            table = self.verdicts.table(tick, messages, sweep=receivers[tick % len(receivers)] == self.vid)
        heard: list[tuple[int, ControlMsg | HeardControl]] = []
        seen: set[int] = set()  # not check.vouched: a message whose digests do not fit its map vouches for nothing
        try:
            rotated = table is not None and len(table) < len(places)
            if rotated:  # each vehicle starts where the others do not; a sender's frames stay in order
                places.sort(key=lambda at: (senders[at] < self.vid, at))
            later: list[int] = []  # frames another vehicle is opening, and those after them in their slot
            waiting: set[int] = set()  # their senders
            for at in places:
                sender = senders[at]
                if sender in waiting:
                    later.append(at)
                    continue
                span = table.get(at) if table is not None else None
                found = None
                if span is None and table is not None:  # verified since we read the table?
                    found = body_span(messages[at])
                    if found is not None:
                        if table.has(at, *found):
                            span = found
                        elif table.claimed(at):
                            later.append(at)
                            waiting.add(sender)
                            continue
                        else:
                            table.claim(at)
                self._hear(at, sender, messages[at], span, found, table, tick, heard, seen)
            for at in later:  # listed by now, or opened here
                found = body_span(messages[at])
                span = found if found is not None and table.has(at, *found) else None
                self._hear(at, senders[at], messages[at], span, found, table, tick, heard, seen)
        finally:
            if table is not None:
                table.close()
        if rotated or later:
            heard.sort(key=lambda h: h[0])
        msgs = [msg for _, msg in heard]
        check.vouch_all(msgs)
        return msgs, check

    def _hear(self, at: int, sender: int, raw: bytes, span: tuple[int, int] | None, found: tuple[int, int] | None,
              table, tick: int, heard: list, seen: set[int]) -> None:
        """Frame ``at`` of ``sender``'s slot into ``heard`` (and its sender into ``seen``)
        if it passes: the receiver's own checks of a listed frame (its body at ``span``),
        else every check (and listed, its body at ``found``, if it passes); else counted."""
        try:
            if span is not None:
                msg = HeardControl.read(raw[span[0]:span[0] + span[1]])
                if msg.vid != sender:  # = its certificate's vehicle
                    self.rejections.add(CTRL_STREAM, "wrong_key",
                                        f"vehicle {msg.vid}'s certificate on vehicle {sender}'s")
                    return
                if msg.tick != tick or sender in seen:
                    self.rejections.add(CTRL_STREAM, "replayed", f"vehicle {sender}, tick {msg.tick}")
                    return
            else:
                msg = self.verifier.open(raw, ControlMsg, sender, CTRL_STREAM,
                                         fresh=lambda m: m.tick == tick and m.vid not in seen)
                if msg is None:
                    return
                if found is not None and fits(msg):  # read in part, it must vouch as it would whole
                    table.put(at, *found)
        except MalformedMessage as err:
            self.drops.add(CTRL_STREAM, err)
            return
        heard.append((at, msg))
        seen.add(sender)

    def payloads(self, received: list[Reception], check: PayloadCheck, bundle: CtrlBundle | None) -> list[bytes]:
        """The payloads of ``received`` their senders signed for this interval, in order."""
        if bundle is not None:
            for sender in sorted({r.sender for r in received}):
                if not check.vouched(sender):
                    self._vouch_unheard(sender, check, bundle)
        return check.passed([(r.sender, r.payload) for r in received], header_of)

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
