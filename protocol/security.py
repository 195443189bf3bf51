"""Authenticated V2X messages: the run's authority, certificates, signing and checking.

After IEEE 1609.2, reduced to what a run needs. The run's authority (the launcher)
holds an Ed25519 key pair and gives each connected vehicle a key pair and a
``Certificate`` (run id, vehicle id, validity in sim time, public key, the authority's
signature). A vehicle sends each of its messages as a ``Signed`` envelope: the encoded
message, its certificate and its signature over a context string and the encoded
message, which holds the sender's ``vid``, ``tick`` and ``t_sim_s`` (Ed25519 binds the
signer's public key itself; docs/security.md). A receiver checks, in this order, and
drops and counts by reason what fails (``Rejections``):

- ``unsigned``: a plain message where a signed one is required;
- ``bad_certificate``: the certificate is not the run's authority's (or of another run,
  or outside its validity);
- ``wrong_key``: a valid certificate, but of another vehicle than the one the message
  comes from (the key it came on, its slot on the medium) or claims to be;
- ``bad_signature``: the signature does not verify (the bytes are not what the
  certificate's holder signed);
- ``replayed``: authentic, but of an interval already past or already heard from.

Object payloads are not signed one by one: a signed ``ControlMsg`` carries the digest
of each of its objects' payloads, and a payload is authentic if its sender's signed
control message of the same interval vouches for it (one signature per sender and
interval covers both; ``PayloadCheck``).

Every receiver of a broadcast checks the same signatures. The receivers of one run on
one host share what they found authentic (``Verdicts``: a table per control bundle in
a directory only the run's user can write), so each control message is verified about
once per host rather than once per receiver. What each check costs is in
docs/security.md.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import stat
import sys
import threading
from array import array
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from protocol.codec import MalformedMessage, decode, decode_fields, encode
from protocol.messages import DIGEST_BYTES, Certificate, ControlMsg, Signed

log = logging.getLogger(__name__)

MESSAGE_CONTEXT = b"autocast v2x message 1\x00"  # domain separation: a message signature is never a certificate's
CERTIFICATE_CONTEXT = b"autocast v2x certificate 1\x00"
REASONS = ("unsigned", "bad_certificate", "wrong_key", "bad_signature", "replayed")
REJECTED_LINE = "rejected"  # the tag of a process's exit line (Rejections.exit_line)
MAX_CERTIFICATES = 1024  # certificates remembered as checked; a flood of new ones only costs a check each
VERDICTS_DIR = "verified"  # Verdicts' directory, inside the one the run gives its receivers on a host


def payload_digest(payload: bytes) -> bytes:
    """What a control message vouches for an object payload with: SHA-256, its first 128
    bits. A signer hashes every object payload it may send (~88 KB an interval at 40
    vehicles), a receiver every one it fuses (~130, most of a few hundred bytes). On a
    CPU with SHA extensions (AMD since Zen, Intel since Ice Lake, most ARMv8) OpenSSL's
    SHA-256 takes about 70% of BLAKE2b-128's time on either; on one without, about
    1.8 times (docs/security.md, Costs)."""
    return hashlib.sha256(payload).digest()[:DIGEST_BYTES]


def certificate_tbs(run_id: str, vid: int, valid_from_s: float, valid_until_s: float, public_key: bytes) -> bytes:
    """The bytes the authority signs for a certificate."""
    return CERTIFICATE_CONTEXT + msgpack.packb([run_id, vid, float(valid_from_s), float(valid_until_s), public_key],
                                               use_bin_type=True)


def _raw_public(key: Ed25519PrivateKey) -> bytes:
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    return key.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)


def _raw_private(key: Ed25519PrivateKey) -> bytes:
    from cryptography.hazmat.primitives.serialization import Encoding, NoEncryption, PrivateFormat

    return key.private_bytes(Encoding.Raw, PrivateFormat.Raw, NoEncryption())


# ---------------------------------------------------------------------------- the authority


@dataclass(frozen=True, slots=True)
class Credentials:
    """What the authority gives one vehicle: its private key, its certificate and the
    authority's public key (to check everybody else's certificates)."""

    private_key: bytes  # 32 bytes, raw Ed25519
    certificate: Certificate
    authority: bytes  # 32 bytes, the authority's public key

    @property
    def vid(self) -> int:
        return self.certificate.vid

    def to_json(self) -> str:
        return json.dumps({"private_key": self.private_key.hex(), "authority": self.authority.hex(),
                           "certificate": msgpack.packb(_cert_fields(self.certificate), use_bin_type=True).hex()})

    @staticmethod
    def from_json(text: str) -> Credentials:
        d = json.loads(text)
        fields = msgpack.unpackb(bytes.fromhex(d["certificate"]), raw=False)
        return Credentials(bytes.fromhex(d["private_key"]), Certificate(*fields), bytes.fromhex(d["authority"]))

    def save(self, path: Path) -> None:
        """Written readable by its owner only."""
        path.touch(mode=0o600, exist_ok=False)
        path.write_text(self.to_json())

    @staticmethod
    def load(path: str | Path) -> Credentials:
        return Credentials.from_json(Path(path).read_text())


def _cert_fields(c: Certificate) -> list:
    return [c.run_id, c.vid, c.valid_from_s, c.valid_until_s, c.public_key, c.signature]


class Authority:
    """The run's certificate authority (the launcher): issues each vehicle's credentials."""

    def __init__(self, run_id: str, private_key: bytes | None = None) -> None:
        self.run_id = run_id
        self._key = Ed25519PrivateKey.from_private_bytes(private_key) if private_key else Ed25519PrivateKey.generate()
        self.public_key = _raw_public(self._key)

    def issue(self, vid: int, valid_from_s: float, valid_until_s: float,
              private_key: bytes | None = None) -> Credentials:
        """A new key pair for ``vid`` (or the given private key) and its certificate."""
        key = Ed25519PrivateKey.from_private_bytes(private_key) if private_key else Ed25519PrivateKey.generate()
        public = _raw_public(key)
        signature = self._key.sign(certificate_tbs(self.run_id, vid, valid_from_s, valid_until_s, public))
        cert = Certificate(self.run_id, vid, float(valid_from_s), float(valid_until_s), public, signature)
        return Credentials(_raw_private(key), cert, self.public_key)


class Signer:
    """Seals one vehicle's messages: ``seal(msg)`` is the encoded ``Signed`` envelope."""

    def __init__(self, credentials: Credentials) -> None:
        self.credentials = credentials
        self._key = Ed25519PrivateKey.from_private_bytes(credentials.private_key)

    def signature(self, body: bytes) -> bytes:
        """This vehicle's signature of an encoded message."""
        return self._key.sign(MESSAGE_CONTEXT + body)

    def seal(self, msg: Any) -> bytes:
        body = encode(msg)
        return encode(Signed(msg.tick, msg.t_sim_s, self.credentials.certificate, body, self.signature(body)))


def plain(msg: Any) -> bytes:
    """What a vehicle that does not sign sends: the message itself."""
    return encode(msg)


# ---------------------------------------------------------------------------- counting


@dataclass
class Rejections:
    """What a process dropped as not authentic: per stream (a key, or a bundle's items)
    and reason; the first of each and every 100th are logged."""

    counts: dict[str, dict[str, int]] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _version: int = 0

    def add(self, stream: str, reason: str, detail: str = "") -> None:
        assert reason in REASONS, reason
        with self._lock:
            per = self.counts.setdefault(stream, {})
            n = per[reason] = per.get(reason, 0) + 1
            self._version += 1
        if n == 1 or n % 100 == 0:
            log.warning("rejected #%d on %s: %s%s", n, stream, reason, f" ({detail})" if detail else "")

    @property
    def version(self) -> int:
        """Grows with every rejection: a cheap test of whether anything changed."""
        return self._version

    def summary(self) -> dict[str, Any]:
        """``{"total": n, "by_reason": {reason: n}, "by_stream": {stream: {reason: n}}}``."""
        with self._lock:
            by_stream = {s: dict(sorted(r.items())) for s, r in sorted(self.counts.items())}
        by_reason: dict[str, int] = {}
        for per in by_stream.values():
            for reason, n in per.items():
                by_reason[reason] = by_reason.get(reason, 0) + n
        return {"total": sum(by_reason.values()), "by_reason": dict(sorted(by_reason.items())),
                "by_stream": by_stream}

    def exit_line(self, process: str) -> str:
        """``rejected {"process": ..., "total": ..., "by_reason": ..., "by_stream": ...}``,
        gathered by the launcher into the outcome record (``processes.manager.exit_records``)."""
        return f"{REJECTED_LINE} " + json.dumps({"process": process, **self.summary()})


# ---------------------------------------------------------------------------- checking


class Verdicts:
    """What one run's receivers on one host found authentic, shared: each broadcast
    control message is verified about once per host, not once per receiver.

    Every vehicle that hears a control message checks the same signature: at 40
    vehicles, 39 Ed25519 verifications a message, each with the same result. The
    receivers of a run on one host share a table per control bundle (``table``): a
    file named by a hash of every frame of the bundle in order, holding per frame 0, or
    where its signed body lies once a receiver has found the frame authentic (a valid
    certificate's, its signature good, its body decoding whole as a ``ControlMsg`` of
    the certificate's vehicle and the envelope's tick and time, its digests one per
    object). A receiver takes such a frame's body as it is, and checks only what
    depends on itself (``vehicle_agent.guard.Guard.heard``). Only what passed is
    recorded: a forgery is verified, and counted, by every receiver it reaches.

    Whoever can write the directory can make every receiver on the host accept anything;
    it is made inside a directory the run's user alone may open (the run's shared-memory
    directory, or the one holding the vehicles' credentials), so that is only a process
    of the run's user on the host, which can already read every vehicle's key there and
    attach to the receivers themselves (docs/security.md, threat model). A directory
    that is not the user's own, or that others may write, is not used (``open``).
    """

    def __init__(self, directory: Path) -> None:
        self.directory = directory

    @staticmethod
    def open(parent: str | Path) -> Verdicts | None:
        """The run's verdicts in ``parent``/``VERDICTS_DIR`` (made if need be), or None
        (logged) if it or ``parent`` is not this user's alone: each receiver then
        verifies every signature itself."""
        directory = Path(parent) / VERDICTS_DIR
        try:
            directory.mkdir(mode=0o700, exist_ok=True)
            for d in (Path(parent), directory):
                st = d.lstat()
                if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o077:
                    log.warning("%s is not this user's alone: not sharing verified signatures", d)
                    return None
        except OSError as exc:
            log.warning("no shared verdicts in %s (%s): every signature verified here", parent, exc)
            return None
        return Verdicts(directory)

    def table(self, tick: int, frames: list[bytes], sweep: bool = False) -> VerdictTable:
        """The shared verdicts on interval ``tick``'s bundle of ``frames``, as they stand,
        open (``VerdictTable.close``). ``sweep``: also remove those of the intervals
        before the last (lock-step: every receiver is past them); one receiver an
        interval sweeps, in turn."""
        if sweep:
            try:
                old = [e.name for e in os.scandir(self.directory) if e.name.isdigit() and int(e.name) < tick - 1]
            except OSError:
                old = []
            for name in old:
                shutil.rmtree(self.directory / name, ignore_errors=True)
        return VerdictTable(f"{self.directory}/{tick}/{bundle_name(frames)}", len(frames))


def bundle_name(frames: list[bytes]) -> str:
    """A bundle's name: every frame of the bundle, in order, hashed (SHA-256: ~40 us for
    the ~73 KB of a 40-vehicle control bundle, each receiver each interval)."""
    h = hashlib.sha256(b"ac v2x bundle verdict\x00")
    h.update(array("I", map(len, frames)).tobytes())
    h.update(b"".join(frames))
    return h.hexdigest()


class VerdictTable:
    """The verdicts on one bundle (``Verdicts.table``): a file named by the bundle's hash,
    holding a record for each frame found authentic at 16 times its place in the bundle:
    where its body lies in the bundle (place, offset and length in one 64-bit word,
    ``_word``), then that word's complement. A record is taken whole or not at all:
    a file's bytes not yet written read as zero, so a record read while it is being
    written, half of it zero, fails the complement unless it is whole. The table is read
    once, in one read (a directory holding a name per frame, listed and each name parsed,
    took 2.5 times as long); a frame not in it yet is looked up again (``has``) before
    the receiver checks it itself, and added (``put``) if it passes.

    A receiver about to check a frame itself first marks it (``claim``: a byte per place
    after the records), so that another receiver reaching it meanwhile checks its other
    frames first and looks it up again after (``claimed``): two receivers that reached
    the same frame together no longer check every following frame together. A mark is
    a hint, never a verdict: a frame still not listed when its turn comes again is
    checked by whoever reaches it. The file stays open until ``close``."""

    RECORD = 16
    PLACES = 1 << 16  # a bundle's frames at most (CtrlBundle's items are far fewer)
    CLAIMS_AT = RECORD * PLACES
    _FIELD = (1 << 24) - 1
    _ONES = (1 << 64) - 1

    def __init__(self, path: str, places: int | None = None) -> None:
        """``places``: the bundle's frames (None: as many as the file holds records for)."""
        self.path = path
        self._words: dict[int, int] = {}
        self._fd: int | None = None
        for _ in range(2):
            try:
                self._fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
                break
            except FileNotFoundError:
                try:
                    os.makedirs(os.path.dirname(path), mode=0o700, exist_ok=True)
                except OSError:
                    return
            except OSError:
                return
        if self._fd is None:
            return
        try:
            if places is None:
                places = min(os.fstat(self._fd).st_size, self.CLAIMS_AT) // self.RECORD
            data = os.pread(self._fd, self.RECORD * min(places, self.PLACES), 0)
        except OSError:
            return
        words, ones = array("Q", data[:len(data) - len(data) % self.RECORD]), self._ONES
        for place, (word, complement) in enumerate(zip(words[0::2], words[1::2])):
            if word ^ complement == ones and word >> 48 == place:  # whole, and in its place
                self._words[place] = word

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> VerdictTable:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __len__(self) -> int:
        return len(self._words)

    def places(self) -> list[int]:
        """The places of the frames listed when the table was read."""
        return sorted(self._words)

    @classmethod
    def _word(cls, at: int, off: int, n: int) -> int:
        return at << 48 | off << 24 | n

    def _record(self, at: int, off: int, n: int) -> bytes:
        word = self._word(at, off, n)
        return word.to_bytes(8, sys.byteorder) + (word ^ self._ONES).to_bytes(8, sys.byteorder)  # as read

    def _fits(self, at: int, off: int, n: int) -> bool:
        return self._fd is not None and at < self.PLACES and off <= self._FIELD and n <= self._FIELD

    def get(self, at: int) -> tuple[int, int] | None:
        """Where frame ``at``'s body lies (offset, length), if it was listed when read."""
        word = self._words.get(at)
        return None if word is None else ((word >> 24) & self._FIELD, word & self._FIELD)

    def has(self, at: int, off: int, n: int) -> bool:
        """Whether frame ``at`` (its body ``n`` bytes at ``off``) was found authentic since
        the table was read."""
        try:
            return self._fits(at, off, n) and os.pread(self._fd, self.RECORD, self.RECORD * at) == \
                self._record(at, off, n)
        except OSError:
            return False

    def put(self, at: int, off: int, n: int) -> None:
        """Record that frame ``at`` is authentic, its body ``n`` bytes at ``off`` (every
        receiver that records it writes the same record)."""
        if self._fits(at, off, n):
            try:
                os.pwrite(self._fd, self._record(at, off, n), self.RECORD * at)
            except OSError:
                pass

    def claimed(self, at: int) -> bool:
        """Whether another receiver has marked frame ``at`` as being checked."""
        try:
            return self._fits(at, 0, 0) and os.pread(self._fd, 1, self.CLAIMS_AT + at) == b"\x01"
        except OSError:
            return False

    def claim(self, at: int) -> None:
        """Mark frame ``at`` as being checked by this receiver."""
        if self._fits(at, 0, 0):
            try:
                os.pwrite(self._fd, b"\x01", self.CLAIMS_AT + at)
            except OSError:
                pass


class Verifier:
    """Opens ``Signed`` envelopes from the run's vehicles against the authority's key.

    ``open`` returns the verified, decoded message, or None after counting why not (a
    payload that is neither a valid envelope nor a plain message of the expected type is
    malformed, counted by the caller's ``DropCounter`` as before). Thread-safe: the
    world checks commands on Zenoh's threads.
    """

    def __init__(self, authority: bytes, run_id: str, rejections: Rejections | None = None) -> None:
        self.run_id = run_id
        self.rejections = rejections if rejections is not None else Rejections()
        self._authority = Ed25519PublicKey.from_public_bytes(authority)
        self._certs: dict[Certificate, Ed25519PublicKey | None] = {}  # None: checked and refused
        self._lock = threading.Lock()

    def _key_of(self, cert: Certificate) -> Ed25519PublicKey | None:
        """The certificate's public key if the authority issued it for this run."""
        with self._lock:
            if cert in self._certs:
                return self._certs[cert]
        key = None
        if cert.run_id == self.run_id and len(cert.public_key) == 32:
            try:
                self._authority.verify(cert.signature, certificate_tbs(cert.run_id, cert.vid, cert.valid_from_s,
                                                                       cert.valid_until_s, cert.public_key))
                key = Ed25519PublicKey.from_public_bytes(cert.public_key)
            except (InvalidSignature, ValueError):
                key = None
        with self._lock:
            if len(self._certs) >= MAX_CERTIFICATES:
                self._certs.clear()
            self._certs[cert] = key
        return key

    def open(self, raw: bytes, expected: type, sender: int, stream: str,
             fresh: Callable[[Any], bool] | None = None) -> Any:
        """The message in ``raw`` if it is a ``Signed`` ``expected`` from vehicle
        ``sender`` (the key or slot it came on) that ``fresh`` accepts (its interval);
        else None, counted under ``stream`` by reason. Raises ``MalformedMessage`` for
        what is neither an envelope nor a plain ``expected``, or whose signed body does
        not decode."""
        try:
            env = decode(raw, Signed)
        except MalformedMessage:
            decode(raw, expected)  # raises if it is not even a plain message of the type
            self.rejections.add(stream, "unsigned")
            return None
        cert = env.certificate
        key = self._key_of(cert)
        if key is None or not cert.valid_from_s <= env.t_sim_s <= cert.valid_until_s:
            self.rejections.add(stream, "bad_certificate", f"vehicle {cert.vid}")
            return None
        if cert.vid != sender:
            self.rejections.add(stream, "wrong_key", f"vehicle {cert.vid}'s certificate on vehicle {sender}'s")
            return None
        try:
            key.verify(env.signature, MESSAGE_CONTEXT + env.body)
        except InvalidSignature:
            self.rejections.add(stream, "bad_signature", f"vehicle {sender}")
            return None
        msg = decode(env.body, expected)
        if getattr(msg, "vid", sender) != sender:
            self.rejections.add(stream, "wrong_key", f"vehicle {sender} signed a message of vehicle {msg.vid}")
            return None
        if msg.tick != env.tick or msg.t_sim_s != env.t_sim_s:
            self.rejections.add(stream, "bad_signature", "the envelope's tick is not the signed one")
            return None
        if fresh is not None and not fresh(msg):
            self.rejections.add(stream, "replayed", f"vehicle {sender}, tick {msg.tick}")
            return None
        return msg


def body_span(raw: bytes) -> tuple[int, int] | None:
    """Where the signed body lies in a ``Signed`` envelope's bytes (offset, length); None
    if ``raw`` is no envelope."""
    try:
        body = decode(raw, Signed).body
    except MalformedMessage:
        return None
    return raw.find(body), len(body)


def fits(msg: ControlMsg) -> bool:
    """Whether ``msg``'s digests are one ``DIGEST_BYTES`` row of bytes per object of its
    map (the codec checks each array's dtype and shape, but not that the digests have a
    row per object: a vehicle may sign fewer). A message that does not fit vouches for
    nothing."""
    ids, digests = msg.objects.object_id, msg.digests
    return ids.ndim == 1 and digests.dtype == np.uint8 and digests.shape == (len(ids), DIGEST_BYTES)


@dataclass
class PayloadCheck:
    """Object payloads of one interval against the signed control messages vouching for them.

    ``vouch(msg)`` registers a verified control message (heard, or taken from the
    interval's bundle only to check payloads): a ``ControlMsg``, or one read in part
    (``vid``, and its bytes as ``raw``) because another receiver on the host found it
    authentic and fitting (``Verdicts``). ``check(sender, payload)``
    is True if the payload is one ``sender`` signed for this interval, else counts why
    not and is False: no control message of the sender (``unsigned``), a header naming
    another sender (``wrong_key``) or interval (``replayed``), bytes whose digest is none
    of those the sender signed (``bad_signature``: points changed, an object it did not
    list). The payload's header (sender, object id, tick) is inside the digested bytes.
    Bytes the sender signed that are no object payload (no valid header) are authentic:
    they pass, and the decoder drops them as malformed, as it drops a plain run's.
    A second copy of a payload is what its sender signed (a vehicle may send an object
    twice in an interval, and fusion keeps one reception per object): it passes.
    """

    tick: int
    rejections: Rejections
    stream: str = "data bundle item"
    _vouchers: dict[int, Any] = field(default_factory=dict)  # sender -> its verified control message
    _digests: dict[int, set[bytes]] = field(default_factory=dict)  # sender -> what it vouched for, once asked

    def vouch(self, msg: Any) -> None:
        """A whole message that does not fit (``fits``) vouches for nothing; one read in
        part fits (a bundle's table lists no message that does not)."""
        if msg.vid in self._vouchers or (isinstance(msg, ControlMsg) and not fits(msg)):
            return
        self._vouchers[msg.vid] = msg

    def vouch_all(self, msgs: list[Any]) -> None:
        for msg in msgs:
            self.vouch(msg)

    def vouched(self, sender: int) -> bool:
        return sender in self._vouchers

    def _digests_of(self, sender: int) -> set[bytes] | None:
        got = self._digests.get(sender)
        if got is None:
            msg = self._vouchers.get(sender)
            if msg is None:
                return None
            rows = msg.digests if isinstance(msg, ControlMsg) else decode_fields(msg.raw, ControlMsg, ("digests",))[0]
            flat = rows.tobytes()
            got = self._digests[sender] = {flat[i:i + DIGEST_BYTES] for i in range(0, len(flat), DIGEST_BYTES)}
        return got

    def passed(self, received: list[tuple[int, bytes]],
               header_of: Callable[[bytes], tuple[int, int, int] | None]) -> list[bytes]:
        """The payloads of ``received`` ((sender, payload), in order) that ``check``
        passes; the same counts, in one loop (an agent checks ~150 a tick at 40 vehicles)."""
        out = []
        digests_of, digest, check = self._digests, payload_digest, self.check
        for sender, payload in received:
            digests = digests_of.get(sender)
            header = header_of(payload)
            if digests is not None and header is not None and header[0] == sender and header[2] == self.tick \
                    and digest(payload) in digests:
                out.append(payload)
            elif check(sender, payload, header):  # resolves the sender's digests, or counts why not
                out.append(payload)
        return out

    def check(self, sender: int, payload: bytes, header: tuple[int, int, int] | None) -> bool:
        """``header``: the payload's (sender, object id, tick), or None if it has none."""
        digests = self._digests_of(sender)
        if digests is None:
            self.rejections.add(self.stream, "unsigned", f"no signed control message of vehicle {sender}")
            return False
        if header is None:
            if payload_digest(payload) in digests:  # its sender's own word, malformed: for the decoder to drop
                return True
            self.rejections.add(self.stream, "bad_signature", f"vehicle {sender}: not an object payload")
            return False
        claimed, oid, tick = header
        if claimed != sender:
            self.rejections.add(self.stream, "wrong_key", f"vehicle {claimed}'s object from vehicle {sender}")
            return False
        if tick != self.tick:
            self.rejections.add(self.stream, "replayed", f"vehicle {sender}'s object of tick {tick}")
            return False
        if payload_digest(payload) not in digests:
            self.rejections.add(self.stream, "bad_signature", f"vehicle {sender}, object {oid}")
            return False
        return True


def with_digests(msg: ControlMsg, payloads: dict[int, bytes]) -> ControlMsg:
    """``msg`` vouching for ``payloads`` (object id -> the payload it will send if scheduled)."""
    rows = [payload_digest(payloads[oid]) for oid in msg.objects.object_id.tolist()]
    digests = np.frombuffer(b"".join(rows), dtype=np.uint8).reshape(-1, DIGEST_BYTES) if rows else \
        np.zeros((0, DIGEST_BYTES), dtype=np.uint8)
    return replace(msg, digests=digests)


def opened(msg: Any) -> Any:
    """A ``Signed`` envelope's body decoded without checking it (for viewers and reports
    of a finished log); any other message as it is."""
    if isinstance(msg, Signed):
        try:
            return decode(msg.body)
        except MalformedMessage:
            return None
    return msg
