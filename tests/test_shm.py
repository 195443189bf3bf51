"""A key's payloads through shared memory (protocol.shm): what a reader copies out is
exactly what the writer put, or a counted miss, never half of one."""

from __future__ import annotations

import fcntl
import os
import threading
import time
from pathlib import Path

import pytest
import zenoh

from protocol import keys, shm
from protocol.codec import MalformedMessage, decode, encode
from protocol.messages import Command, InShm, Tick
from protocol.session import DropCounter, ZenohArgs, session_scope, typed_handler
from protocol.shm import ShmMiss, ShmPublisher, ShmReader, ShmWriter
from deploy.launch.run import free_endpoint

KEY = "ac/t/v/3/scan"


def _payload(tick: int, n: int) -> bytes:
    return bytes((tick * 7 + i) % 251 for i in range(n))


def test_each_tick_reads_back_exactly_as_written_as_payloads_grow_and_shrink(tmp_path):
    writer, reader = ShmWriter(tmp_path, KEY), ShmReader(tmp_path, KEY)
    for tick, n in enumerate([10, 5000, 3, 200_000, 0, 200_001, 17]):  # both files grow while the reader has them mapped
        notice = writer.write(tick, tick * 0.1, _payload(tick, n))
        assert notice == InShm(tick, tick * 0.1, n)
        assert reader.read(notice) == _payload(tick, n)
    writer.close()
    assert list(tmp_path.iterdir()) == []


def test_the_previous_tick_stays_readable_and_the_one_before_is_a_miss(tmp_path):
    writer, reader = ShmWriter(tmp_path, KEY), ShmReader(tmp_path, KEY)
    n0, n1, n2 = (writer.write(t, 0.0, _payload(t, 100)) for t in range(3))
    assert reader.read(n1) == _payload(1, 100)  # the other file: a reader one tick late loses nothing
    with pytest.raises(ShmMiss, match="tick 0"):
        reader.read(n0)  # tick 2 took its file
    assert reader.read(n2) == _payload(2, 100)


def test_a_payload_overwritten_while_it_is_copied_is_a_miss(tmp_path):
    writer = ShmWriter(tmp_path, KEY)
    notice = writer.write(0, 0.0, _payload(0, 1000))

    def meanwhile(view):  # a writer two ticks ahead takes the file while the reader decodes
        copied = bytes(view)
        writer.write(2, 0.2, _payload(2, 1000))
        return copied

    with pytest.raises(ShmMiss, match="overwritten while read"):
        ShmReader(tmp_path, KEY).read(notice, meanwhile)


def test_a_payload_that_fails_to_decode_because_it_was_overwritten_is_a_miss_not_malformed(tmp_path):
    writer = ShmWriter(tmp_path, KEY)
    notice = writer.write(0, 0.0, encode(Tick(0, 0.0, [1], [])))

    def torn(view):
        writer.write(2, 0.2, b"\xc1" * len(view))  # 0xc1 is never valid msgpack
        return decode(view, Tick)

    with pytest.raises(ShmMiss, match="overwritten while read"):
        ShmReader(tmp_path, KEY).read(notice, torn)
    notice = writer.write(4, 0.4, b"\xc1" * 8)
    with pytest.raises(MalformedMessage):  # there, whole, and not a message
        ShmReader(tmp_path, KEY).read(notice, lambda view: decode(view, Tick))


def test_notices_that_name_nothing_there_are_misses(tmp_path):
    writer, reader = ShmWriter(tmp_path, KEY), ShmReader(tmp_path, KEY)
    with pytest.raises(ShmMiss, match="no shared memory"):
        reader.read(InShm(0, 0.0, 10))  # nothing written yet
    writer.write(0, 0.0, _payload(0, 10))
    for bad in (InShm(0, 0.0, 11), InShm(0, 0.0, 9), InShm(2, 0.0, 10), InShm(-1, 0.0, 10), InShm(0, 0.0, 1 << 40)):
        with pytest.raises(ShmMiss):
            reader.read(bad)
    assert reader.read(InShm(0, 0.0, 10)) == _payload(0, 10)


def test_a_second_writer_of_a_key_never_truncates_nor_removes_the_first_ones_files(tmp_path):
    first, second = ShmWriter(tmp_path, KEY), ShmWriter(tmp_path, KEY)
    notice = first.write(0, 0.0, _payload(0, 4096))
    assert second.write(0, 0.0, b"x") is None and second.write(1, 0.1, b"x") is None  # it sends them itself
    second.close()
    assert ShmReader(tmp_path, KEY).read(notice) == _payload(0, 4096)


def test_a_full_tmpfs_makes_a_payload_go_another_way_and_the_next_one_tries_again(tmp_path, monkeypatch):
    fallocate = os.posix_fallocate

    def full(fd, offset, length):
        raise OSError(28, "No space left on device")

    writer, reader = ShmWriter(tmp_path, KEY), ShmReader(tmp_path, KEY)
    monkeypatch.setattr(os, "posix_fallocate", full)
    assert writer.write(0, 0.0, b"payload") is None
    monkeypatch.setattr(os, "posix_fallocate", fallocate)
    assert reader.read(writer.write(2, 0.2, b"payload")) == b"payload"  # the same file, now with room
    monkeypatch.setattr(os, "posix_fallocate", full)
    assert writer.write(4, 0.4, b"x" * 10_000) is None  # it cannot grow: the payload goes another way
    assert writer.write(6, 0.6, b"small") is not None  # what fits still goes in
    assert writer.fallbacks == 2
    writer.close()
    assert list(tmp_path.iterdir()) == []


def _aged(path: Path) -> Path:
    old = time.time() - 2 * shm.ORPHAN_AFTER_S
    os.utime(path, (old, old))
    return path


def test_run_directory_is_removed_after_the_run_and_orphans_before_the_next(tmp_path):
    def run_dir(name: str) -> Path:
        path = tmp_path / f"{shm.DIR_PREFIX}1-{name}-abcd"
        path.mkdir()
        (path / shm.LOCK_NAME).touch()
        (path / "x.0").write_bytes(b"x")
        return path

    orphan = _aged(run_dir("old"))  # nobody holds its lock
    young = run_dir("young")  # just made: its launcher takes the lock right after
    alive = _aged(run_dir("alive"))
    held = os.open(alive / shm.LOCK_NAME, os.O_RDONLY)  # its launcher, in another pid namespace, say
    fcntl.flock(held, fcntl.LOCK_EX)
    stranger = tmp_path / f"{shm.DIR_PREFIX}somebody-else"  # no lock file: not a run's
    stranger.mkdir()
    _aged(stranger)
    try:
        with shm.run_directory("r1", parent=tmp_path) as path:
            assert path.is_dir() and path.name.startswith(f"{shm.DIR_PREFIX}{os.getpid()}-r1-")
            assert not orphan.exists() and young.exists() and alive.exists() and stranger.exists()
            _aged(path)
            assert shm.remove_orphans(tmp_path) == []  # ours is held while the run lasts
        assert not path.exists()
    finally:
        os.close(held)
    assert shm.remove_orphans(tmp_path) == [alive]  # its launcher let go
    with shm.run_directory("r2", parent=tmp_path / "missing") as none:
        assert none is None


@pytest.fixture
def sessions():
    endpoint = free_endpoint()
    with session_scope(ZenohArgs(listen=(endpoint,))) as hub, \
            session_scope(ZenohArgs(connect=(endpoint,))) as a, session_scope(ZenohArgs(connect=(endpoint,))) as b:
        yield hub, a, b


class Inbox:
    def __init__(self) -> None:
        self.items: list = []
        self._cv = threading.Condition()

    def put(self, key, msg) -> None:
        with self._cv:
            self.items.append((key, msg))
            self._cv.notify_all()

    def wait_for(self, n: int) -> list:
        with self._cv:
            assert self._cv.wait_for(lambda: len(self.items) >= n, timeout=60), self.items
            return list(self.items)


def _wait_matching(pub, want: bool) -> None:
    cv = threading.Event()
    listener = pub.declare_matching_listener(lambda status: cv.set() if status.matching == want else None)
    try:
        if pub.matching_status.matching != want:
            assert cv.wait(60)
    finally:
        listener.undeclare()


def test_payloads_cross_processes_sessions_through_shared_memory_and_bad_notices_are_counted(sessions, tmp_path,
                                                                                              monkeypatch):
    _, a, b = sessions
    key = keys.world_tick("t")
    pub = ShmPublisher(a, key, tmp_path)
    drops, missed, inbox, plain = DropCounter(), shm.missed_counter(), Inbox(), Inbox()
    sub = shm.subscribe(b, key, tmp_path, Tick, inbox.put, drops, missed)
    _wait_matching(pub._twin, True)
    assert not pub._pub.matching_status.matching  # the shared-memory reader does not listen on the key itself
    ticks = [Tick(t, t * 0.1, [1, 2, 3 + t], []) for t in range(4)]
    ticks[2] = Tick(2, 0.2, list(range(3000)), [])  # more than tick 0 left room for in its file
    pub.put(0, 0.0, encode(ticks[0]))
    assert inbox.wait_for(1) == [(key, ticks[0])]
    # a subscriber on the key itself (a recorder) makes the writer put it over Zenoh too
    zsub = b.declare_subscriber(key, typed_handler(Tick, plain.put, drops))
    _wait_matching(pub._pub, True)
    pub.put(1, 0.1, encode(ticks[1]))
    assert plain.wait_for(1) == [(key, ticks[1])]
    assert inbox.wait_for(2)[1] == (key, ticks[1])
    # a payload that cannot go into shared memory (a full tmpfs) still reaches the reader
    fallocate = os.posix_fallocate
    monkeypatch.setattr(os, "posix_fallocate", lambda *_: (_ for _ in ()).throw(OSError(28, "full")))
    pub.put(2, 0.2, encode(ticks[2]))
    monkeypatch.setattr(os, "posix_fallocate", fallocate)
    assert pub._writer.fallbacks == 1 and inbox.wait_for(3)[2] == (key, ticks[2])
    # garbage, a message of neither type, a notice of a tick that is not in shared memory,
    # and a notice of a payload that is garbage
    twin, block = keys.in_shm(key), zenoh.CongestionControl.BLOCK
    for bad in (b"\x00garbage", encode(Command(0, 0.0, 1, 0.0, 0.0)), encode(InShm(7, 0.7, 10)),
                encode(pub._writer.write(8, 0.8, b"\xc1not a tick"))):  # tick 8's file is not tick 3's
        a.put(twin, bad, congestion_control=block)
    pub.put(3, 0.3, encode(ticks[3]))  # after the bad ones, on the same link: it arrives last
    assert inbox.wait_for(4)[3] == (key, ticks[3])
    assert drops.by_key() == {twin: 2, key: 1}  # the garbage, the command; the garbage in shared memory
    assert missed.by_key() == {twin: 1}  # tick 7 is not there: a miss, not a malformed message
    assert missed.exit_line("x").startswith(f"{shm.MISSED_LINE} ")
    zsub.undeclare()
    sub.undeclare()
    pub.undeclare()
    assert list(Path(tmp_path).iterdir()) == []


def test_without_a_directory_the_publisher_is_plain_zenoh(sessions):
    _, a, b = sessions
    key = keys.world_tick("t")
    pub = ShmPublisher(a, key, None)
    drops, inbox = DropCounter(), Inbox()
    sub = shm.subscribe(b, key, None, Tick, inbox.put, drops)
    _wait_matching(pub._pub, True)
    pub.put(0, 0.0, encode(Tick(0, 0.0, [1], [])))
    assert inbox.wait_for(1) == [(key, Tick(0, 0.0, [1], []))]
    sub.undeclare()
    pub.undeclare()


def test_a_payload_in_parts_reads_back_as_the_parts_joined(tmp_path, monkeypatch):
    import numpy as np
    writer, reader = ShmWriter(tmp_path, KEY), ShmReader(tmp_path, KEY)
    arr = np.arange(3000, dtype=np.uint16).reshape(100, 30)
    for tick, parts in enumerate([(b"head", memoryview(arr).cast("B")), (b"", b"x" * 7, b""), (b"only",), ()]):
        joined = b"".join(parts)
        notice = writer.write_parts(tick, tick * 0.1, parts)
        assert notice == InShm(tick, tick * 0.1, len(joined))
        assert reader.read(notice) == joined
    monkeypatch.setattr(os, "posix_fallocate", lambda *_: (_ for _ in ()).throw(OSError(28, "full")))
    assert writer.write_parts(4, 0.4, (b"y" * 100_000, memoryview(arr).cast("B"))) is None  # no room: the caller sends it
    assert writer.fallbacks == 1
    writer.close()


def test_put_parts_sends_what_put_of_the_joined_parts_sends(sessions, tmp_path, monkeypatch):
    _, a, b = sessions
    key = keys.world_tick("t")
    pub = ShmPublisher(a, key, tmp_path)
    drops, inbox, plain = DropCounter(), Inbox(), Inbox()
    sub = shm.subscribe(b, key, tmp_path, Tick, inbox.put, drops)
    _wait_matching(pub._twin, True)
    ticks = [Tick(t, t * 0.1, list(range(t * 1000)), []) for t in range(3)]

    def parts(tick):
        raw = encode(tick)
        return raw[:5], memoryview(bytearray(raw[5:]))

    pub.put_parts(0, 0.0, parts(ticks[0]))  # shared memory only
    assert inbox.wait_for(1) == [(key, ticks[0])]
    zsub = b.declare_subscriber(key, typed_handler(Tick, plain.put, drops))
    _wait_matching(pub._pub, True)
    pub.put_parts(1, 0.1, parts(ticks[1]))  # and, joined, on the key for its subscriber
    assert plain.wait_for(1) == [(key, ticks[1])]
    monkeypatch.setattr(os, "posix_fallocate", lambda *_: (_ for _ in ()).throw(OSError(28, "full")))
    pub.put_parts(2, 0.2, parts(ticks[2]))  # no room: joined, on the twin and on the key
    assert inbox.wait_for(3)[1:] == [(key, ticks[1]), (key, ticks[2])]
    assert plain.wait_for(2)[1] == (key, ticks[2])
    assert drops.total == 0
    zsub.undeclare()
    sub.undeclare()
    pub.undeclare()
    plain_pub, plain_in = ShmPublisher(a, key, None), Inbox()  # without a directory: joined, plain Zenoh
    _wait_matching(plain_pub._pub, False)  # zsub's undeclaration has reached a: a match now is plain_sub's
    plain_sub = shm.subscribe(b, key, None, Tick, plain_in.put, drops)
    _wait_matching(plain_pub._pub, True)
    plain_pub.put_parts(0, 0.0, parts(ticks[1]))
    assert plain_in.wait_for(1) == [(key, ticks[1])]
    plain_sub.undeclare()
    plain_pub.undeclare()
