"""A key's payloads through shared memory on one host, with a small notice over Zenoh.

On one host the big per-tick payloads (each vehicle's scan, the proxy's bundles) cost
more in moving than in reading: the publisher's Zenoh threads write them to the hub,
the hub copies them out to every subscriber, and each receiver's threads reassemble
and copy them again. With a shared-memory directory (``--shm-dir``, a per-run
directory on tmpfs that ``autocast run`` makes), a writer puts the exact bytes it
would have published into a file there and publishes only ``InShm`` (the tick and the
size) on the key's twin, ``keys.in_shm(key)``; a reader copies the bytes out and
decodes them as if Zenoh had carried them. What a receiver decodes, verifies and acts
on is the same byte for byte; runs across hosts (and any process without the flag)
use Zenoh as before.

Each key has two files, ``<key with / as .>.0`` and ``.1``; tick k goes to file
``k % 2``: a 16-byte header (the tick plus one, 0 while it is being written; the
payload's size) and then the payload. A reader checks the header before and after its
copy, so a payload overwritten meanwhile (a reader two ticks late, in real-time mode)
is dropped and counted, never half-read. In lock-step a writer is never two ticks
ahead of a reader that has not copied its payload yet.
"""

from __future__ import annotations

import contextlib
import logging
import mmap
import os
import shutil
import struct
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import zenoh

from protocol import keys
from protocol.codec import MalformedMessage, decode, encode
from protocol.messages import InShm
from protocol.session import DropCounter, typed_handler

log = logging.getLogger(__name__)

T = TypeVar("T")
HEADER = struct.Struct("<QQ")  # tick + 1 (0: being written, or never), payload size in bytes
TMPFS = Path("/dev/shm")
DIR_PREFIX = "autocast-"


class ShmMiss(ValueError):
    """The payload a notice names is not (or no longer) in shared memory."""


def _path(directory: Path, key: str, tick: int) -> Path:
    return directory / f"{key.replace('/', '.')}.{tick % 2}"


class ShmWriter:
    """Writes one key's payloads into its two files; ``write`` returns the notice to publish.

    A file grows (``posix_fallocate``: a full tmpfs is ``OSError`` here, never a SIGBUS
    later) when a payload does not fit; ``write`` returns None if it cannot, and the
    caller publishes the payload over Zenoh instead."""

    def __init__(self, directory: Path | str, key: str) -> None:
        self.directory, self.key = Path(directory), key
        self._maps: list[tuple[int, mmap.mmap] | None] = [None, None]

    def write(self, tick: int, t_sim_s: float, payload: bytes) -> InShm | None:
        need = HEADER.size + len(payload)
        try:
            fd, mm = self._slot(tick, need)
        except OSError:
            return None
        HEADER.pack_into(mm, 0, 0, len(payload))
        mm[HEADER.size:need] = payload
        HEADER.pack_into(mm, 0, tick + 1, len(payload))
        return InShm(tick, t_sim_s, len(payload))

    def _slot(self, tick: int, need: int) -> tuple[int, mmap.mmap]:
        i = tick % 2
        slot = self._maps[i]
        if slot is not None and len(slot[1]) >= need:
            return slot
        if slot is None:  # never truncate a file someone may have mapped: a second writer gets Zenoh
            fd = os.open(_path(self.directory, self.key, tick), os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
        else:
            fd = slot[0]
            slot[1].close()
            self._maps[i] = None
        try:
            size = max(need + need // 4, mmap.PAGESIZE)  # room to grow a little without remapping
            os.posix_fallocate(fd, 0, size)
            mm = mmap.mmap(fd, size)
        except OSError:
            os.close(fd)
            raise
        self._maps[i] = (fd, mm)
        return fd, mm

    def close(self) -> None:
        """Unmap and remove the files (readers that have them open keep their copies)."""
        for i, slot in enumerate(self._maps):
            if slot is not None:
                slot[1].close()
                os.close(slot[0])
                self._maps[i] = None
        for tick in (0, 1):
            with contextlib.suppress(FileNotFoundError):
                _path(self.directory, self.key, tick).unlink()


class ShmReader:
    """Reads one key's payloads named by its notices."""

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
        mm = self._map(notice.tick, need)
        if (notice.tick + 1, notice.nbytes) != HEADER.unpack_from(mm, 0):
            raise ShmMiss(f"tick {notice.tick} ({notice.nbytes} bytes) is not in {self.key}'s shared memory")
        base = memoryview(mm)
        try:
            with base[HEADER.size:need] as view:
                out = convert(view)
        except ValueError:
            self._still_there(mm, notice)
            raise
        finally:
            base.release()
        self._still_there(mm, notice)
        return out

    def _still_there(self, mm: mmap.mmap, notice: InShm) -> None:
        if HEADER.unpack_from(mm, 0)[0] != notice.tick + 1:
            raise ShmMiss(f"tick {notice.tick} of {self.key} was overwritten while read")

    def _map(self, tick: int, need: int) -> mmap.mmap:
        i = tick % 2
        mm = self._maps[i]
        if mm is not None and len(mm) >= need:
            return mm
        if mm is not None:  # the writer grew the file
            mm.close()
            self._maps[i] = None
        try:
            fd = os.open(_path(self.directory, self.key, tick), os.O_RDONLY)
        except OSError as exc:
            raise ShmMiss(f"no shared memory for {self.key}: {exc.strerror}") from None
        try:
            size = os.fstat(fd).st_size
            if size < need:
                raise ShmMiss(f"{self.key}'s shared memory holds {size} bytes, the notice names {need}")
            mm = mmap.mmap(fd, size, prot=mmap.PROT_READ)
        finally:
            os.close(fd)
        self._maps[i] = mm
        return mm

    def close(self) -> None:
        for i, mm in enumerate(self._maps):
            if mm is not None:
                mm.close()
                self._maps[i] = None


class ShmPublisher:
    """A big publisher for one key: with a directory, each payload goes into shared
    memory and its notice on the twin key, and over Zenoh too only while some
    subscriber listens on the key itself (a recorder keeping it, a user's logger:
    Zenoh's matching status says so); without one, over Zenoh only, as
    ``protocol.session.reliable_publisher``."""

    def __init__(self, session: zenoh.Session, key: str, directory: Path | str | None) -> None:
        block = zenoh.CongestionControl.BLOCK
        self.key = key
        self._pub = session.declare_publisher(key, congestion_control=block)
        self._writer = ShmWriter(directory, key) if directory else None
        self._notice = session.declare_publisher(keys.in_shm(key), congestion_control=block) if directory else None

    def put(self, tick: int, t_sim_s: float, payload: bytes) -> None:
        notice = self._writer.write(tick, t_sim_s, payload) if self._writer is not None else None
        if notice is None or self._pub.matching_status.matching:
            self._pub.put(payload)
        if notice is not None:
            self._notice.put(encode(notice))

    def undeclare(self) -> None:
        self._pub.undeclare()
        if self._notice is not None:
            self._notice.undeclare()
            self._writer.close()


def subscribe(session: zenoh.Session, key: str, directory: Path | str | None, expected: type,
              on_msg: Callable[[str, Any], None], drops: DropCounter) -> Any:
    """Subscribe to ``key``'s messages of type ``expected``, as
    ``protocol.session.typed_handler`` does: over Zenoh, or with a directory through
    shared memory, subscribed to the twin key only (a subscriber on ``key`` itself
    would make the writer send it over Zenoh too), and decoded in place. A notice that
    is malformed or names no payload in shared memory is dropped and counted in
    ``drops`` on the twin key, a malformed payload on ``key``."""
    if not directory:
        return session.declare_subscriber(key, typed_handler(expected, on_msg, drops))
    reader = ShmReader(directory, key)
    twin = keys.in_shm(key)

    def on_notice(sample: zenoh.Sample) -> None:
        notice = None
        try:
            notice = decode(sample.payload.to_bytes(), InShm)
            msg = reader.read(notice, lambda view: decode(view, expected))
        except ShmMiss as err:
            drops.add(twin, err)
            return
        except MalformedMessage as err:
            drops.add(twin if notice is None else key, err)
            return
        try:
            on_msg(key, msg)
        except Exception:
            log.exception("handler for %s failed", key)

    return _Subscription(session.declare_subscriber(twin, on_notice), reader)


class _Subscription:
    def __init__(self, sub: Any, reader: ShmReader) -> None:
        self._sub, self._reader = sub, reader

    def undeclare(self) -> None:
        self._sub.undeclare()
        self._reader.close()


@contextlib.contextmanager
def run_directory(run_id: str, parent: Path = TMPFS) -> Iterator[Path | None]:
    """A fresh directory for one run's shared memory, removed on exit; None where there
    is no tmpfs (the run then goes over Zenoh only). Directories left by launchers
    that died (named after their pid) are removed first."""
    if not (parent.is_dir() and os.access(parent, os.W_OK)):
        yield None
        return
    remove_orphans(parent)
    path = Path(tempfile.mkdtemp(prefix=f"{DIR_PREFIX}{os.getpid()}-{run_id}-", dir=parent))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


def remove_orphans(parent: Path = TMPFS) -> list[Path]:
    """Remove the run directories whose launcher (the pid in the name) is gone."""
    gone = []
    for path in parent.glob(f"{DIR_PREFIX}*-*"):
        pid = path.name[len(DIR_PREFIX):].split("-", 1)[0]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(path, ignore_errors=True)
            gone.append(path)
    return gone


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def add_shm_arg(parser) -> None:
    parser.add_argument("--shm-dir", default=None, metavar="DIR",
                        help="the run's shared-memory directory (protocol.shm): the big payloads of one "
                             "host's processes go through it, their notices over Zenoh; every process of "
                             "the run that writes or reads them must be given the same (autocast run does)")
