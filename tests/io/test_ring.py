"""The message ring and the shared blob: whole messages in order, across a fork; a full ring drops and counts,
never waits; a blob is read whole or not at all."""

from __future__ import annotations

import os

from compd.io.ring import MessageRing, SharedBlob


def test_messages_arrive_whole_and_in_order_across_the_ring_s_end() -> None:
    ring = MessageRing(256)
    got = []
    for i in range(200):  # many times round the ring: every copy that straddles its end
        assert ring.put(("row", i, "x" * (i % 40)))
        if i % 3 == 2:
            got += ring.take()
    got += ring.take()
    assert got == [("row", i, "x" * (i % 40)) for i in range(200)]
    assert ring.put_count == 200 and ring.dropped == 0 and not ring.pending()


def test_a_full_ring_drops_the_message_and_counts_it_and_the_reader_goes_on() -> None:
    ring = MessageRing(128)
    sent = 0
    while ring.put(("row", sent, "y" * 20)):
        sent += 1
    assert sent > 0 and ring.dropped == 1
    assert not ring.put(("row", -1, "y" * 20)) and ring.dropped == 2
    assert [m[1] for m in ring.take(limit=2)] == [0, 1]
    assert ring.put("room again")
    rest = ring.take()
    assert [m[1] for m in rest[:-1]] == list(range(2, sent)) and rest[-1] == "room again"


def test_a_forked_writer_and_a_parent_reader_share_the_ring() -> None:
    ring = MessageRing(4096)
    n = 5000
    pid = os.fork()
    if pid == 0:  # the writer: as the cycle, never waits; retries only to test every message
        code = 1
        try:
            for i in range(n):
                while not ring.put(i):
                    pass
            code = 0
        finally:
            os._exit(code)
    got: list[int] = []
    while len(got) < n:
        got += ring.take()
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0
    assert got == list(range(n))


def test_a_blob_holds_the_newest_bytes() -> None:
    blob = SharedBlob(16)
    assert blob.read() is None and blob.version == 0
    blob.publish(b"first")
    v = blob.version
    blob.publish(b"second one")
    assert blob.read() == b"second one" and blob.version > v and blob.version % 2 == 0
    pid = os.fork()
    if pid == 0:
        blob.publish(b"from the child")
        os._exit(0)
    os.waitpid(pid, 0)
    assert blob.read() == b"from the child"
    blob._head[0] += 1  # a writer that died half-way: never torn bytes
    assert blob.read() is None
