"""drivers/timestamps.py's StampedBlocks: the blocks a live stream's judged steps make (LSL's and ROS 2's)."""

from __future__ import annotations

import math

import numpy as np

from supramodal.drivers.timestamps import StampedBlocks, Step


def _blocks():
    said = []
    return StampedBlocks(2, lambda: "BUS: stream x", "sender", 10.0, lambda *a: said.append(a)), said


def test_a_gap_is_filled_with_zeros_before_the_block_counted_flagged_and_said_at_its_frame():
    blocks, said = _blocks()
    a = blocks.block(np.ones((5, 2)), 1.0, 1.01, Step("first"))
    b = blocks.block(np.full((4, 2), 2.0), 2.0, 2.01, Step("gap", 0.003, 3))
    assert (a.start, a.filled, b.start) == (0, None, 5)
    assert np.array_equal(b.data, np.vstack([np.zeros((3, 2)), np.full((4, 2), 2.0)]))
    assert b.filled.tolist() == [True] * 3 + [False] * 4
    assert (blocks.frames, blocks.filled, blocks.gaps) == (12, 3, 1)
    assert said == [("gap", "BUS: stream x: 3 samples (3.0 ms) missing; filled with zeros", 5)]


def test_a_restart_marks_the_block_and_may_step_back_in_time_and_nothing_else_does():
    blocks, said = _blocks()
    blocks.block(np.ones((5, 2)), 5.0, 5.0, Step("first"))
    late = blocks.block(np.ones((5, 2)), 4.0, 5.1, Step("ok"))          # stamped before the last: held there
    assert late.timestamp == 5.0 and late.restarts == ()
    back = blocks.block(np.ones((5, 2)), 1.0, 5.2, Step("back", -4.0))
    assert back.restarts == (0,) and back.timestamp == 1.0 and blocks.restarts == 1
    long = blocks.block(np.ones((5, 2)), 30.0, 30.0, Step("long", 29.0))
    assert long.restarts == (0,) and long.filled is None and blocks.frames == 20
    assert [k for k, _, _ in said] == ["restart", "restart"]
    assert "stepped back 4000.0 ms (the sender restarted?)" in said[0][1]
    assert "more than max_gap (10 s): not filled" in said[1][1]


def test_a_backlog_is_dated_on_the_sample_clock_and_a_slip_is_only_counted():
    blocks, said = _blocks()
    assert blocks.last_stamp == -math.inf
    blocks.block(np.ones((5, 2)), 1.0, 1.0, Step("first"))
    b = blocks.block(np.ones((5, 2)), 3.0, 3.0, Step("backlog", 1.9, on_line=1.1))
    assert b.timestamp == 1.1 == blocks.last_stamp and b.filled is None and blocks.backlogs == 1
    blocks.block(np.ones((5, 2)), 1.2, 3.1, Step("slip", 0.02))
    assert blocks.slips == 1 and [k for k, _, _ in said] == ["backlog"]
