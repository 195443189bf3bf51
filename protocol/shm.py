"""A key's payloads through shared memory on one host, with a small notice over Zenoh.

On one host the big per-tick payloads (each vehicle's scan, the proxy's bundles) cost
more in moving than in reading: the publisher's Zenoh threads write them to the hub,
the hub copies them out to every subscriber, and each receiver's threads reassemble
and copy them again. With a shared-memory directory (``--shm-dir``, a per-run
directory on tmpfs that ``autocast run`` makes), a writer puts the exact bytes it
would have published into a file there and publishes only ``InShm`` (the tick and the
size) on the key's twin, ``keys.in_shm(key)``; a reader decodes the bytes in place as
if Zenoh had carried them (a payload that cannot go into shared memory, the tmpfs
being full, goes on the twin itself). What a receiver decodes, verifies and acts on
is the same byte for byte; runs across hosts (and any process without the flag) use
Zenoh as before.

Each key has two files, ``<key with / as .>.0`` and ``.1``; tick k goes to file
``k % 2``: a 16-byte header (the tick plus one, 0 while it is being written; the
payload's size) and then the payload. A reader checks the header before and after it
decodes, so a payload overwritten meanwhile (a reader two ticks late, in real-time
mode) is dropped and counted, never half-read: sound where stores and loads keep their
order (x86; ``run_directory`` gives no directory elsewhere). In lock-step a writer is
never two ticks ahead of a reader that has not decoded its payload yet.
"""
from __future__ import annotations

import contextlib
import fcntl
import logging
import mmap
import os
import platform
import shutil
import struct
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

import zenoh

from protocol import keys
from protocol.codec import MalformedMessage, decode, encode
from protocol.messages import InShm
from protocol.session import DropCounter, deliver, typed_handler

log = logging.getLogger(__name__)

T = TypeVar("T")
Buffer = bytes | memoryview  # a part of a payload (``ShmPublisher.put_parts``)
HEADER = struct.Struct("<QQ")  # tick + 1 (0: being written, or never), payload size in bytes
TMPFS = Path("/dev/shm")
DIR_PREFIX = "autocast-"
MISSED_LINE = "shm_missed"  # the tag of a process's exit line of misses (``missed_counter``)
LOCK_NAME = ".launcher"  # in a run's directory: its launcher holds an flock on it
ORPHAN_AFTER_S = 60.0
ORDERED_STORES = ("x86_64", "AMD64", "i386", "i686")  # CPUs that keep stores (and loads) in program order


class ShmMiss(ValueError):
    """The payload a notice names is not (or no longer) in shared memory."""


def _nbytes(part: Buffer) -> int:
    """The size in bytes of a buffer (a ``bytes``, or a memoryview of any format)."""
    return part.nbytes if isinstance(part, memoryview) else len(part)


def _name(key: str, slot: int) -> str:
    """The file of ``key``'s ticks ``k`` with ``k % 2 == slot``."""
    return f"{key.replace('/', '.')}.{slot}"


class ShmWriter:
    """Writes one key's payloads into its two files; ``write`` returns the notice to publish.

    A file grows when a payload does not fit, its pages reserved first
    (``posix_fallocate``: a full tmpfs fails there, never with a SIGBUS later); a
    payload that does not fit a full tmpfs gets None from ``write``, and the next one
    tries again. Files are created, never truncated (someone may have them mapped): if
    another writer's are there already, every ``write`` returns None. The caller then
    sends the payload itself on the twin key (``ShmPublisher``)."""

    def __init__(self, directory: Path | str, key: str) -> None:
        self.directory, self.key = Path(directory), key
        self._fds: list[int | None] = [None, None]  # our files
        self._maps: list[mmap.mmap | None] = [None, None]
        self._foreign = False  # another writer's files are there
        self.fallbacks = 0  # payloads that did not go into shared memory

    def write(self, tick: int, t_sim_s: float, payload: bytes) -> InShm | None:
        return self.write_parts(tick, t_sim_s, (payload,))

    def write_parts(self, tick: int, t_sim_s: float, parts: Sequence[Buffer]) -> InShm | None:
        """``write`` of the payload that is ``parts`` (buffers of bytes) one after the
        other, each copied straight into the file: the caller need not join them."""
        size = sum(_nbytes(part) for part in parts)
        need = HEADER.size + size
        mm = self._room(tick % 2, need)
        if mm is None:
            self.fallbacks += 1
            if self.fallbacks == 1:
                log.warning("%s: a payload of %d bytes does not go through shared memory (%s); it goes over Zenoh",
                            self.key, size, "another writer's files" if self._foreign else "no room")
            return None
        HEADER.pack_into(mm, 0, 0, size)
        at = HEADER.size
        for part in parts:
            n = _nbytes(part)
            mm[at:at + n] = part
            at += n
        HEADER.pack_into(mm, 0, tick + 1, size)
        return InShm(tick, t_sim_s, size)

    def _room(self, i: int, need: int) -> mmap.mmap | None:
        mm = self._maps[i]
        if mm is not None and len(mm) >= need:
            return mm
        if self._foreign:
            return None
        try:
            if self._fds[i] is None:
                self._fds[i] = os.open(self.directory / _name(self.key, i), os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
            size = max(need + need // 4, mmap.PAGESIZE)  # room to grow a little without remapping
            os.posix_fallocate(self._fds[i], 0, size)
            grown = mmap.mmap(self._fds[i], size)
        except FileExistsError:
            self._foreign = True
            return None
        except OSError:
            return None
        self._maps[i] = grown  # the smaller map, if any, is unmapped once nothing refers to it
        return grown

    def close(self) -> None:
        """Remove our files (a reader that has one mapped keeps it until it lets go)."""
        self._maps = [None, None]
        for i, fd in enumerate(self._fds):
            if fd is not None:
                os.close(fd)
                with contextlib.suppress(FileNotFoundError):
                    (self.directory / _name(self.key, i)).unlink()
        self._fds = [None, None]


class ShmReader:
    """Reads one key's payloads named by its notices.

    Maps are never closed, only dropped (unmapped once nothing refers to them): Zenoh
    may still run a callback that reads one while its subscriber is undeclared."""

    def __init__(self, directory: Path | str, key: str) -> None:
        self.directory, self.key = Path(directory), key
        self._maps: list[mmap.mmap | None] = [None, None]

    def read(self, notice: InShm, convert: Callable[[memoryview], T] = bytes) -> T:
        """``convert`` of the payload of ``notice.tick``, read in place (by default a
        copy of its bytes); ``ShmMiss`` if it is not there whole. ``convert`` must keep
        nothing of the view it is given (``protocol.codec.decode`` keeps nothing of its
        input: msgpack copies what it reads), and is not called on a payload that is not
        there; one overwritten while it ran is a miss whatever it returned or raised."""
        if notice.tick < 0:
            raise ShmMiss(f"tick {notice.tick}")
        need = HEADER.size + notice.nbytes
        mm = self._map(notice.tick % 2, need)
        if (notice.tick + 1, notice.nbytes) != HEADER.unpack_from(mm, 0):
            raise ShmMiss(f"tick {notice.tick} ({notice.nbytes} bytes) is not in {self.key}'s shared memory")
        base = memoryview(mm)
        try:
            with base[HEADER.size:need] as view:
                out = convert(view)
        except Exception:
            self._still_there(mm, notice)
            raise
        finally:
            base.release()
        self._still_there(mm, notice)
        return out

    def _still_there(self, mm: mmap.mmap, notice: InShm) -> None:
        if HEADER.unpack_from(mm, 0)[0] != notice.tick + 1:
            raise ShmMiss(f"tick {notice.tick} of {self.key} was overwritten while read")

    def _map(self, i: int, need: int) -> mmap.mmap:
        mm = self._maps[i]
        if mm is not None and len(mm) >= need:
            return mm
        try:  # first use, or the writer grew the file
            fd = os.open(self.directory / _name(self.key, i), os.O_RDONLY)
        except OSError as exc:
            raise ShmMiss(f"no shared memory for {self.key}: {exc.strerror}") from None
        try:
            size = os.fstat(fd).st_size
            if size < need:
                raise ShmMiss(f"{self.key}'s shared memory holds {size} bytes, the notice names {need}")
            mm = mmap.mmap(fd, size, prot=mmap.PROT_READ)
        except OSError as exc:
            raise ShmMiss(f"{self.key}'s shared memory: {exc.strerror}") from None
        finally:
            os.close(fd)
        self._maps[i] = mm
        return mm

    def close(self) -> None:
        self._maps = [None, None]


class ShmPublisher:
    """A big publisher for one key. With a directory, each payload goes into shared
    memory and its ``InShm`` notice on the twin key (a payload that cannot goes on the
    twin itself: the readers listen there only), and on the key itself only while some
    subscriber listens there (a recorder keeping it, a user's logger: Zenoh's matching
    status says so). Without one, on the key, as ``protocol.session.reliable_publisher``.

    Zenoh tells a new publisher of the subscribers already there some time after it is
    declared, in order with the rest of what comes from the hub: declare it before the
    subscribers whose news lets its first put go (the world's: before the liveliness
    subscribers that start tick 0)."""

    def __init__(self, session: zenoh.Session, key: str, directory: Path | str | None) -> None:
        block = zenoh.CongestionControl.BLOCK
        self.key = key
        self._pub = session.declare_publisher(key, congestion_control=block)
        self._writer = ShmWriter(directory, key) if directory else None
        self._twin = session.declare_publisher(keys.in_shm(key), congestion_control=block) if directory else None

    def put(self, tick: int, t_sim_s: float, payload: bytes) -> None:
        if self._writer is None:
            self._pub.put(payload)
            return
        notice = self._writer.write(tick, t_sim_s, payload)
        self._twin.put(payload if notice is None else encode(notice))
        if self._pub.matching_status.matching:
            self._pub.put(payload)

    def put_parts(self, tick: int, t_sim_s: float, parts: Sequence[Buffer]) -> None:
        """``put`` of the payload that is ``parts`` one after the other (a message's
        encoded head and the raw bytes of its last array, say): into shared memory
        without joining them first; joined only for what goes over Zenoh."""
        if self._writer is None:
            self._pub.put(b"".join(parts))
            return
        notice = self._writer.write_parts(tick, t_sim_s, parts)
        payload = b"".join(parts) if notice is None else None
        self._twin.put(payload if notice is None else encode(notice))
        if self._pub.matching_status.matching:
            self._pub.put(b"".join(parts) if payload is None else payload)

    def undeclare(self) -> None:
        self._pub.undeclare()
        if self._writer is not None:
            self._twin.undeclare()
            self._writer.close()


def missed_counter() -> DropCounter:
    """Where a reader counts notices whose payload is no longer (or not) in shared
    memory: a reader two ticks late in real-time mode misses the tick it was told of,
    which is not a malformed message. A process prints it as it exits, ``shm_missed
    {...}``, and the launcher gathers it into the outcome record."""
    return DropCounter(tag=MISSED_LINE, what="payload no longer in shared memory")


def subscribe(session: zenoh.Session, key: str, directory: Path | str | None, expected: type,
              on_msg: Callable[[str, Any], None], drops: DropCounter, missed: DropCounter | None = None) -> Any:
    """Subscribe to ``key``'s messages of type ``expected``, as
    ``protocol.session.typed_handler`` does: over Zenoh, or with a directory through
    shared memory, subscribed to the twin key only (a subscriber on ``key`` itself
    would make the writer send it over Zenoh too), each ``InShm`` notice's payload
    decoded in place, and a payload the writer could not put there taken as it comes
    on the twin. What is neither is dropped and counted in ``drops`` on the twin key, a
    malformed payload in shared memory on ``key``; a notice whose payload is not there
    (overwritten, or never written) in ``missed`` (``drops`` without one)."""
    if not directory:
        return session.declare_subscriber(key, typed_handler(expected, on_msg, drops))
    reader = ShmReader(directory, key)
    twin = keys.in_shm(key)

    def on_notice(sample: zenoh.Sample) -> None:
        raw = sample.payload.to_bytes()
        try:
            notice = decode(raw, InShm)
        except MalformedMessage as not_a_notice:
            try:
                msg = decode(raw, expected)
            except MalformedMessage:
                drops.add(twin, not_a_notice)
                return
        else:
            try:
                msg = reader.read(notice, lambda view: decode(view, expected))
            except ShmMiss as err:
                (drops if missed is None else missed).add(twin, err)
                return
            except MalformedMessage as err:
                drops.add(key, err)
                return
        deliver(on_msg, key, msg)

    return _Subscription(session.declare_subscriber(twin, on_notice), reader)


class _Subscription:
    def __init__(self, sub: Any, reader: ShmReader) -> None:
        self._sub, self._reader = sub, reader

    def undeclare(self) -> None:
        self._sub.undeclare()
        self._reader.close()


@contextlib.contextmanager
def run_directory(run_id: str, parent: Path = TMPFS) -> Iterator[Path | None]:
    """A fresh directory for one run's shared memory, removed on exit, its lock held
    meanwhile; None where there is no tmpfs, or on a CPU that may reorder stores (the
    readers' header check relies on x86's order): the run then goes over Zenoh only.
    Directories whose launcher is gone are removed first (``remove_orphans``)."""
    if platform.machine() not in ORDERED_STORES or not (parent.is_dir() and os.access(parent, os.W_OK)):
        yield None
        return
    remove_orphans(parent)
    try:
        path = Path(tempfile.mkdtemp(prefix=f"{DIR_PREFIX}{os.getpid()}-{run_id}-", dir=parent))
    except OSError as exc:
        log.warning("no shared-memory directory in %s (%s): every payload goes over Zenoh", parent, exc)
        yield None
        return
    try:
        lock = os.open(path / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o600)
    except OSError as exc:
        shutil.rmtree(path, ignore_errors=True)
        log.warning("no lock in %s (%s): every payload goes over Zenoh", path, exc)
        yield None
        return
    try:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)
        os.close(lock)


def remove_orphans(parent: Path = TMPFS, launcher: tuple[int, str] | None = None) -> list[Path]:
    """Remove the run directories whose launcher is gone: nobody holds their lock. A
    launcher holds it while its run lasts, in whatever pid namespace it runs, and lets
    go with its last file descriptor however it ends. A directory changed in the last
    ``ORPHAN_AFTER_S`` is left alone (a launcher takes its lock just after making it),
    unless ``launcher`` (its pid and run id) names the one launcher whose directories to
    remove: one its caller has seen exit (a sweep whose launcher was killed)."""
    gone = []
    pattern = f"{DIR_PREFIX}*" if launcher is None else f"{DIR_PREFIX}{launcher[0]}-{launcher[1]}-*"
    for path in parent.glob(pattern):
        try:
            if launcher is None and time.time() - path.stat().st_mtime < ORPHAN_AFTER_S:
                continue
            fd = os.open(path / LOCK_NAME, os.O_RDONLY)
        except FileNotFoundError:  # no lock: not a run's directory of ours
            continue
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            continue  # its launcher runs
        finally:
            os.close(fd)
        shutil.rmtree(path, ignore_errors=True)
        gone.append(path)
    return gone


def add_shm_arg(parser) -> None:
    parser.add_argument("--shm-dir", default=None, metavar="DIR",
                        help="the run's shared-memory directory (protocol.shm): the big payloads of one "
                             "host's processes go through it, their notices over Zenoh; every process of "
                             "the run that writes or reads them must be given the same (autocast run does)")
