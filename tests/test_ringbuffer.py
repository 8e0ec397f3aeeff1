"""Tests of node.ringbuffer: wrap-around, overrun policies, readers, threads."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from supramodal.node.runtime.ringbuffer import Chunk, RingBuffer, RingClosed

POLICIES = ("drop-oldest", "drop-newest", "block")


def frames(start, n, channels=2):
    """Frames whose values encode their stream index: channel c holds index * (c + 1)."""
    idx = np.arange(start, start + n, dtype=np.float64)
    return idx[:, None] * np.arange(1, channels + 1)


def flags(start, n):
    return np.arange(start, start + n) % 3 == 0


def put(rb, start, n, **kwargs):
    """Write frames ``start .. start + n - 1`` with their flags."""
    return rb.write(frames(start, n), flags(start, n), **kwargs)


def check_chunk(chunk, channels=2):
    """The chunk's data and flags are exactly those of its stream indices."""
    n = chunk.data.shape[0]
    np.testing.assert_array_equal(chunk.data, frames(chunk.start, n, channels))
    np.testing.assert_array_equal(chunk.filled, flags(chunk.start, n))


# --- a reference model, checked against the ring in one thread --------------------------------

class Model:
    """What the ring must do, with lists: kept stream indices, one cursor per reader."""

    def __init__(self, capacity, policy):
        self.cap, self.policy = capacity, policy
        self.kept = []     # stream index of each stored frame, by storage position
        self.end = 0
        self.readers = []  # [cursor, lost, start, read]

    def space(self):
        if not self.readers:
            return float("inf")
        return self.cap - (len(self.kept) - min(r[0] for r in self.readers))

    def write(self, n):
        if self.policy == "drop-oldest":
            k = n
        else:
            k = int(min(n, self.space()))
        self.kept.extend(range(self.end, self.end + k))
        if self.policy == "drop-newest":
            for r in self.readers:
                r[1] += n - k
            self.end += n
        else:
            self.end += k
        limit = len(self.kept) - self.cap
        for r in self.readers:
            if r[0] < limit:
                r[1] += limit - r[0]
                r[0] = limit
        return k

    def add(self, position):
        stored = len(self.kept)
        cursor = stored if position == "newest" else max(0, stored - self.cap)
        start = self.kept[cursor] if cursor < stored else self.end
        self.readers.append([cursor, (self.end - start) - (stored - cursor), start, 0])

    def read(self, i, max_frames):
        r = self.readers[i]
        got = self.kept[r[0]:r[0] + max_frames]
        for j in range(1, len(got)):  # a read stops at a gap
            if got[j] != got[j - 1] + 1:
                got = got[:j]
                break
        r[0] += len(got)
        r[3] += len(got)
        return got


ops = st.lists(st.one_of(
    st.tuples(st.just("w"), st.integers(0, 45), st.booleans()),
    st.tuples(st.just("r"), st.integers(0, 3), st.integers(1, 40)),
    st.tuples(st.just("add"), st.sampled_from(["newest", "oldest"])),
), max_size=60)


@settings(max_examples=300, deadline=None)
@given(capacity=st.integers(1, 24), policy=st.sampled_from(POLICIES), ops=ops, initial=st.integers(0, 2))
def test_ring_matches_the_reference_model(capacity, policy, ops, initial):
    rb = RingBuffer(capacity, 2, overrun=policy)
    model = Model(capacity, policy)
    readers = []
    flagged = set()  # stream indices written with a True flag
    offered_filled = set()  # stream indices offered with a True filled flag, kept or refused
    for _ in range(initial):
        readers.append(rb.add_reader())
        model.add("newest")
    for op in ops:
        if op[0] == "w":
            _, n, with_flags = op
            start = model.end
            mask = flags(start, n) if with_flags else None
            # timeout=0: under 'block' the ring takes what fits now, as the model does
            kept = rb.write(frames(start, n), mask, timeout=0)
            assert kept == model.write(n)
            if with_flags:  # frames not taken under 'block' get these indices again later
                flagged.update(range(start, start + kept))
                offered = kept if policy == "block" else n
                offered_filled.update(k for k in range(start, start + offered) if k % 3 == 0)
        elif op[0] == "add":
            if len(readers) < 4:
                readers.append(rb.add_reader(position=op[1]))
                model.add(op[1])
        else:
            _, i, m = op
            if i >= len(readers):
                continue
            chunk = readers[i].read(m, timeout=0)
            want = model.read(i, m)
            if not want:
                assert chunk is None
                continue
            assert chunk.start == want[0] and chunk.data.shape == (len(want), 2)
            np.testing.assert_array_equal(chunk.data, frames(want[0], len(want)))
            np.testing.assert_array_equal(chunk.filled, [k in flagged and k % 3 == 0 for k in want])
        for reader, r in zip(readers, model.readers):
            assert reader.available == len(model.kept) - r[0]
            assert reader.lost == r[1]
            assert reader.position == (model.kept[r[0]] if r[0] < len(model.kept) else model.end)
    stats = rb.stats()
    assert stats["written"] == model.end
    assert stats["filled"] == len(offered_filled)
    assert stats["stored"] == len(model.kept)
    assert stats["refused"] == (model.end - len(model.kept) if policy == "drop-newest" else 0)
    rb.close()
    for reader, r in zip(readers, model.readers):  # drain: every frame read or counted lost
        while True:
            try:
                chunk = reader.read(timeout=0)
            except RingClosed:
                break
            np.testing.assert_array_equal(chunk.data, frames(chunk.start, chunk.data.shape[0]))
        s = reader.stats()
        assert s["start"] == r[2]
        assert s["read"] + s["lost"] == model.end - s["start"]
        # ... and of the filled frames offered from its start on, each read or counted lost as filled
        assert s["read_filled"] + s["lost_filled"] == sum(k >= s["start"] for k in offered_filled)
        assert s["lost_filled"] <= s["lost"]


# --- wrap-around and flags ------------------------------------------------------------------

def test_wrap_around_returns_contiguous_copies():
    rb = RingBuffer(8, 2)
    r = rb.add_reader()
    rb.write(frames(0, 6), flags(0, 6))
    assert r.read(4).start == 0
    rb.write(frames(6, 5), flags(6, 5))  # slots 6, 7, 0, 1, 2
    chunk = r.read()
    assert isinstance(chunk, Chunk) and chunk.start == 4 and chunk.data.shape == (7, 2)
    assert chunk.data.flags["C_CONTIGUOUS"] and chunk.data.base is None or chunk.data.base is not rb._data
    check_chunk(chunk)
    chunk.data[:] = -1  # a copy: the ring is untouched
    put(rb, 11, 1)
    assert r.read().start == 11


def test_flags_default_to_false_and_survive_buffering():
    rb = RingBuffer(5, 1)
    r = rb.add_reader()
    rb.write(np.ones(3))  # 1-D is one channel
    rb.write(np.ones((4, 1)), np.array([True, False, False, True]))
    assert r.lost == 2
    chunk = r.read()
    assert chunk.start == 2
    np.testing.assert_array_equal(chunk.filled, [False, True, False, False, True])


def test_write_refusals():
    rb = RingBuffer(4, 2, dtype=np.float32)
    with pytest.raises(ValueError, match=r"shape \(frames, 2\)"):
        rb.write(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="filled_mask"):
        rb.write(np.zeros((3, 2)), np.zeros(2, bool))
    with pytest.raises(ValueError, match="cannot store complex128"):
        rb.write(np.zeros((3, 2), complex))
    assert rb.write(np.zeros((0, 2))) == 0
    with pytest.raises(ValueError):
        RingBuffer(0, 2)
    with pytest.raises(ValueError):
        RingBuffer(4, 2, overrun="drop-everything")


# --- overrun policies, counted exactly ----------------------------------------------------------

def test_drop_oldest_advances_the_lagging_reader_and_counts_its_loss():
    rb = RingBuffer(10, 2, overrun="drop-oldest")
    slow, fast = rb.add_reader("slow"), rb.add_reader("fast")
    for k in range(5):
        assert put(rb, 7 * k, 7) == 7
        check_chunk(fast.read())
    chunk = slow.read()
    assert chunk.start == 25 and chunk.data.shape == (10, 2)  # expected 0: lost 25
    check_chunk(chunk)
    # flags(): every third index is filled; the slow reader lost 0..24 (9 filled) and read 25..34 (3)
    assert rb.stats()["readers"] == {
        "slow": {"start": 0, "read": 10, "lost": 25, "available": 0, "read_filled": 3, "lost_filled": 9},
        "fast": {"start": 0, "read": 35, "lost": 0, "available": 0, "read_filled": 12, "lost_filled": 0}}


def test_drop_oldest_block_larger_than_capacity_keeps_the_newest():
    rb = RingBuffer(4, 2)
    r = rb.add_reader()
    put(rb, 0, 10)
    chunk = r.read()
    assert chunk.start == 6 and r.lost == 6
    check_chunk(chunk)


def test_drop_newest_refuses_counts_and_leaves_a_visible_gap():
    rb = RingBuffer(10, 2, overrun="drop-newest")
    slow, fast = rb.add_reader("slow"), rb.add_reader("fast")
    assert put(rb, 0, 8) == 8
    assert put(rb, 8, 8) == 2   # 6 refused: indices 10..15
    assert put(rb, 16, 4) == 0  # 4 refused: 16..19, one gap with the last
    check_chunk(fast.read())
    first = slow.read()
    assert (first.start, len(first.data)) == (0, 10)
    assert put(rb, 20, 5) == 5
    after = slow.read()
    assert after.start == 20  # the gap: 10 frames lost, seen in the index
    check_chunk(after)
    assert fast.read().start == 20
    s = rb.stats()
    assert (s["written"], s["stored"], s["refused"]) == (25, 15, 10)
    assert s["readers"]["slow"]["lost"] == s["readers"]["fast"]["lost"] == 10


def test_drop_newest_with_no_reader_keeps_everything_it_can():
    rb = RingBuffer(4, 2, overrun="drop-newest")
    assert put(rb, 0, 10) == 10
    assert rb.stats()["refused"] == 0
    r = rb.add_reader(position="oldest")
    chunk = r.read()
    assert chunk.start == 6
    check_chunk(chunk)


def test_block_waits_for_the_slowest_reader():
    rb = RingBuffer(10, 2, overrun="block")
    r = rb.add_reader()
    assert put(rb, 0, 8) == 8
    assert put(rb, 8, 5, timeout=0) == 2  # 3 not taken, no index skipped
    assert put(rb, 10, 3, timeout=0.01) == 0
    result = []
    t = threading.Thread(target=lambda: result.append(put(rb, 10, 25)))
    t.start()
    got = []
    while len(got) < 35:
        chunk = r.read(7, timeout=10)
        check_chunk(chunk)
        got.extend(range(chunk.start, chunk.start + len(chunk.data)))
    t.join(10)
    assert result == [25] and got == list(range(35))
    assert rb.stats()["readers"]["reader0"]["lost"] == 0 and rb.stats()["refused"] == 0


def test_closing_a_reader_releases_a_blocked_writer():
    rb = RingBuffer(4, 1, overrun="block")
    r = rb.add_reader()
    rb.write(np.zeros(4))
    result = []
    t = threading.Thread(target=lambda: result.append(rb.write(np.zeros(3))))
    t.start()
    time.sleep(0.02)
    r.close()
    t.join(10)
    assert result == [3]
    with pytest.raises(RingClosed, match="reader 'reader0' is closed"):
        r.read(timeout=0)


def test_close_wakes_a_blocked_writer():
    rb = RingBuffer(4, 1, overrun="block")
    rb.add_reader()
    rb.write(np.zeros(4))
    errors = []

    def writer():
        try:
            rb.write(np.zeros(3))
        except RingClosed as e:
            errors.append(e)

    t = threading.Thread(target=writer)
    t.start()
    time.sleep(0.02)
    rb.close()
    t.join(10)
    assert not t.is_alive() and len(errors) == 1


# --- readers -------------------------------------------------------------------------------------

def test_several_readers_at_different_speeds():
    rb = RingBuffer(32, 2)
    readers = [rb.add_reader(f"every{k}") for k in (1, 2, 5)]
    expected = [0, 0, 0]
    received = [0, 0, 0]
    for step in range(1, 101):
        put(rb, 10 * (step - 1), 10)
        for i, (k, r) in enumerate(zip((1, 2, 5), readers)):
            if step % k == 0:
                chunk = r.read()
                check_chunk(chunk)
                assert chunk.start >= expected[i]
                expected[i] = chunk.start + len(chunk.data)
                received[i] += len(chunk.data)
    stats = rb.stats()["readers"]
    assert [stats[r.name]["lost"] for r in readers] == [0, 0, 100 * 10 - received[2]]
    assert stats["every5"]["lost"] == 20 * (50 - 32)  # each 5th step it held 50 of which 32 fit
    for i, r in enumerate(readers):
        assert stats[r.name]["read"] == received[i] == 1000 - stats[r.name]["lost"]


def test_reader_added_later_starts_at_newest_or_oldest():
    rb = RingBuffer(8, 2)
    put(rb, 0, 5)
    newest, oldest = rb.add_reader(position="newest"), rb.add_reader(position="oldest")
    put(rb, 5, 5)
    assert newest.read().start == 5
    chunk = oldest.read()
    assert chunk.start == 2 and oldest.lost == 2  # two of its frames were overwritten
    check_chunk(chunk)
    with pytest.raises(ValueError, match="already attached"):
        rb.add_reader(newest.name)


def test_min_frames_waits_for_a_hop():
    rb = RingBuffer(64, 2)
    r = rb.add_reader()
    put(rb, 0, 5)
    assert r.read(min_frames=8, timeout=0) is None
    put(rb, 5, 5)
    chunk = r.read(max_frames=8, min_frames=8, timeout=0)
    assert (chunk.start, len(chunk.data)) == (0, 8)
    rb.close()
    assert len(r.read(min_frames=8).data) == 2  # the remainder at the end
    with pytest.raises(RingClosed):
        r.read()


def test_close_wakes_a_waiting_reader_and_ends_after_draining():
    rb = RingBuffer(8, 2)
    r = rb.add_reader()
    outcome = []

    def reader():
        try:
            while True:
                outcome.append(r.read())
        except RingClosed as e:
            outcome.append(e)

    t = threading.Thread(target=reader)
    t.start()
    put(rb, 0, 3)
    time.sleep(0.02)
    rb.close()
    t.join(10)
    assert not t.is_alive()
    assert isinstance(outcome[-1], RingClosed)
    assert sum(len(c.data) for c in outcome[:-1]) == 3
    with pytest.raises(RingClosed):
        put(rb, 3, 1)


def test_read_timeout_returns_none():
    rb = RingBuffer(8, 2)
    r = rb.add_reader()
    assert r.read(timeout=0) is None
    assert r.read(timeout=0.01) is None


# --- threads: a million frames ---------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("policy", POLICIES)
def test_threaded_million_frames_arrive_in_order_or_are_counted_lost(policy):
    channels, total = 20, 1_000_000
    rb = RingBuffer(4096, channels, overrun=policy)
    names = ("fast", "jittery", "slow")
    readers = [rb.add_reader(n) for n in names]
    results = {}
    rng = np.random.default_rng(7)
    sizes = []
    left = total
    while left:
        sizes.append(min(left, int(rng.integers(1, 400))))
        left -= sizes[-1]

    def writer():
        start = 0
        for n in sizes:
            idx = np.arange(start, start + n, dtype=np.float64)
            block = np.repeat(idx[:, None], channels, axis=1)
            rb.write(block, idx.astype(np.int64) % 7 == 0)
            start += n
        rb.close()

    def consume(reader, seed, pause):
        r_rng = np.random.default_rng(seed)
        expected, received, gaps, bad = 0, 0, 0, 0
        while True:
            try:
                chunk = reader.read(int(r_rng.integers(1, 600)), timeout=5)
            except RingClosed:
                break
            if chunk is None:
                continue
            n = len(chunk.data)
            assert chunk.start >= expected
            gaps += chunk.start - expected
            idx = np.arange(chunk.start, chunk.start + n)
            # every frame is the one its index says, flags included
            bad += int(np.count_nonzero(chunk.data != idx[:, None]))
            bad += int(np.count_nonzero(chunk.filled != (idx % 7 == 0)))
            received += n
            expected = chunk.start + n
            if pause and r_rng.random() < pause:
                time.sleep(0.0005)
        results[reader.name] = (received, gaps, bad, expected)

    threads = [threading.Thread(target=consume, args=(r, i, p)) for i, (r, p) in
               enumerate(zip(readers, (0.0, 0.02, 0.2)))]
    for t in threads:
        t.start()
    w = threading.Thread(target=writer)
    w.start()
    w.join(120)
    for t in threads:
        t.join(120)
    assert not w.is_alive() and not any(t.is_alive() for t in threads)
    stats = rb.stats()
    assert stats["written"] == total
    for name in names:
        received, gaps, bad, expected = results[name]
        s = stats["readers"][name]
        assert bad == 0
        assert s["read"] == received
        assert received + s["lost"] == total          # every frame arrived or was counted lost
        assert s["lost"] == gaps + (total - expected)  # and each loss was visible as a gap
        # every filled frame (index % 7 == 0) was read or counted among the filled frames lost
        assert s["read_filled"] + s["lost_filled"] == len(range(0, total, 7))
        if policy == "block":
            assert s["lost"] == 0 and received == total
    if policy == "drop-newest":
        assert all(stats["readers"][n]["lost"] == stats["refused"] for n in names)
