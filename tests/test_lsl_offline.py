"""The LSL inlet's parts that need no network: the timestamp judge, the scene, and the error a
user without the ``lsl`` extra gets (these run in the core suite, pylsl or not)."""

import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from supramodal.drivers.lsl import ClockSteps, LSLUnavailable, TimestampSteps, import_pylsl
from supramodal.node.scene.build import build_node
from supramodal.node.cli import main
from supramodal.node.scene.schema import SceneError, scene_from_dict

RATE = 5000.0


@settings(max_examples=200)
@given(blocks=st.lists(st.tuples(st.integers(1, 400), st.floats(-0.02, 0.02), st.sampled_from([0, 0, 0, 1, 7, 400, 5000])),
                       min_size=1, max_size=40),
       t0=st.floats(0, 1e6))
def test_a_step_counts_exactly_the_samples_missing_and_nothing_within_the_jitter(blocks, t0):
    """Blocks stamped on the sender's sample clock, each delivered with up to 20 ms of jitter in
    its stamps (a sender stamping at push time), some after a loss: every loss longer than the
    tolerance is found with its exact length; jitter alone is never taken for a loss."""
    judge = TimestampSteps(RATE, tolerance=0.05, max_gap=10.0)
    index = 0
    for k, (size, jitter, lost) in enumerate(blocks):
        index += lost
        first = t0 + index / RATE + jitter
        last = first + (size - 1) / RATE
        step = judge.step(first, last)
        if k == 0:
            assert step.kind == "first"
        else:
            missing = lost / RATE + jitter - previous_jitter
            if missing > 0.05:
                # The samples the stamps say are missing, to the nearest; exactly those lost when
                # the stamps do not jitter.
                assert step.kind == "gap" and abs(step.samples - missing * RATE) <= 0.5 + 1e-6
                if jitter == previous_jitter == 0:
                    assert step.samples == lost
            else:
                assert step.kind in ("ok", "slip") and step.samples == 0
        previous_jitter = jitter
        index += size


def test_a_gap_beyond_max_gap_and_a_step_back_are_not_filled():
    judge = TimestampSteps(RATE, tolerance=0.05, max_gap=2.0)
    judge.step(0.0, 0.0098)
    assert judge.step(0.0100, 0.0198).kind == "ok"
    long = judge.step(3.0, 3.0098)
    assert long.kind == "long" and long.samples == 0 and long.seconds == pytest.approx(2.98)
    back = judge.step(1.0, 1.0098)
    assert back.kind == "back" and back.seconds < -1.9
    assert judge.step(1.0100, 1.02).kind == "ok"


def _lsl_scene(**driver):
    return scene_from_dict({"driver": {"type": "lsl", **driver}, "bank": {"kind": "whisker"},
                            "features": {"names": ["Af"]}})


def test_an_lsl_scene_must_name_the_stream():
    with pytest.raises(SceneError, match=r"type \"lsl\" needs the stream's name \(stream = \.\.\.\), stream_type or "
                                         "source_id"):
        build_node(_lsl_scene())
    with pytest.raises(SceneError, match=r"\[driver\] \(lsl\) resolve_timeout: expected seconds"):
        _lsl_scene(stream="w", resolve_timeout=0)


def test_without_the_extra_a_scene_naming_lsl_says_what_to_install(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "pylsl", None)           # as on a machine without pylsl
    with pytest.raises(LSLUnavailable, match=r'pip install "supramodal\[lsl\]"'):
        import_pylsl()
    scene = tmp_path / "lsl.toml"
    scene.write_text('[driver]\ntype = "lsl"\nstream = "whiskers"\n\n[bank]\nkind = "whisker"\n')
    assert main(["run", str(scene), "--quiet"]) != 0
    err = capsys.readouterr().err
    assert 'pip install "supramodal[lsl]"' in err and "PYLSL_LIB" in err


def _judge_all(judge, blocks):
    """Every block's step from a :class:`ClockSteps` (``blocks``: (samples, first, last)), flushed at the end."""
    steps = []
    for n, first, last in blocks:
        steps += judge.add(n, first, last)
    return steps + judge.flush()


@settings(max_examples=200)
@given(blocks=st.lists(st.tuples(st.integers(1, 400), st.floats(0.0, 0.02), st.sampled_from([0, 0, 0, 0, 1, 7, 400, 5000])),
                       min_size=1, max_size=60),
       t0=st.floats(0, 1e6))
def test_the_clock_model_finds_each_loss_and_fills_nothing_for_delays(blocks, t0):
    """Blocks stamped when they were pushed: their last sample's time on the sender's clock plus a
    delay of 0-20 ms, some after a loss. Every loss beyond the tolerance is filled, sized within
    the delays' spread (exactly when there is no delay), before the block that follows it; delays
    alone are never taken for a loss; one step per block, in order."""
    judge = ClockSteps(RATE, tolerance=0.05, max_gap=10.0)
    index, stamped, losses = 0, [], []
    for size, delay, lost in blocks:
        if stamped:
            index += lost
        losses.append(lost if stamped else 0)
        last = t0 + (index + size - 1) / RATE + delay
        stamped.append((size, last - (size - 1) / RATE, last))
        index += size
    steps = _judge_all(judge, stamped)
    assert len(steps) == len(blocks) and steps[0].kind == "first"
    # A loss within the tolerance is not seen (not filled): it shifts the stamps of what follows
    # by its length, as a delay would, until it leaves the clock model's envelope.
    unseen = sum(x for x in losses if x / RATE <= 0.05)
    exact = all(d == 0 for _, d, _ in blocks) and unseen == 0
    for step, lost in zip(steps[1:], losses[1:]):
        if lost / RATE > 0.05 + 0.02:
            assert step.kind == "gap" and abs(step.samples - lost) <= 0.02 * RATE + unseen + 1, (step, lost)
            if exact:
                assert step.samples == lost
        elif (lost + unseen) / RATE <= 0.05 - 0.02:
            assert step.kind in ("ok", "slip", "backlog") and step.samples == 0, (step, lost)
    assert judge.index == sum(s for s, _, _ in blocks) + sum(s.samples for s in steps)


@settings(max_examples=100)
@given(chunk=st.integers(20, 100), hold_at=st.integers(11, 200), hold=st.floats(0.1, 5.0), pull=st.integers(1, 10),
       delay=st.floats(0.0, 0.01))
def test_a_backlog_stamped_at_push_time_is_no_gap_and_is_dated_by_the_sample_clock(chunk, hold_at, hold, pull, delay):
    """Issue 26 item 9: a sender pushing chunks stamped at push time holds for ``hold`` seconds,
    then pushes the backlog at once (every stamp the flush's instant) and goes on; the inlet pulls
    ``pull`` chunks at a time. Nothing is filled; the backlog's blocks are dated on the sample
    clock (within the pushes' delay), never by their stamps."""
    judge = ClockSteps(RATE, tolerance=0.05, max_gap=10.0)
    chunks = []
    total = hold_at * chunk + int(hold * RATE) + 50 * chunk
    flush_at = hold_at * chunk / RATE + hold
    for k in range(total // chunk):
        last_index = (k + 1) * chunk - 1
        due = (last_index + 1) / RATE + delay
        chunks.append((chunk, max(due, flush_at) if k >= hold_at else due, last_index))
    steps, blocks = [], []
    for i in range(0, len(chunks), pull):
        group = chunks[i:i + pull]
        n = sum(c[0] for c in group)
        blocks.append(group[-1][2])
        steps += judge.add(n, group[-1][1] - (n - 1) / RATE, group[-1][1])
    steps += judge.flush()
    assert len(steps) == len(blocks)
    assert all(s.samples == 0 and s.kind in ("first", "ok", "slip", "backlog") for s in steps), steps
    assert judge.index == len(chunks) * chunk
    for s, last_index in zip(steps, blocks):
        if s.on_line is not None:
            assert abs(s.on_line - (last_index + 1) / RATE) <= delay + 1e-9


def test_json_replacing_the_lsl_sinks_is_what_the_start_up_line_says(tmp_path, capsys):
    """Issue 26 item 11: ``run --json`` replaces the scene's sinks (an LSL signal outlet too), but
    the start-up line still said "source a sent on as LSL"."""
    scene = tmp_path / "relay.toml"
    scene.write_text('[[source]]\nname = "a"\ntype = "synth"\nseconds = 0.5\n\n[[sink]]\ntype = "lsl-signal"\n')
    assert main(["run", str(scene), "--json", "--speed", "max"]) == 0
    err = capsys.readouterr().err
    assert "sent on as LSL (" not in err, err
    assert "--json: JSON Lines on stdout instead of the scene's sinks (lsl-signal; nothing sent on as LSL)" in err


def test_liblsl_gets_the_users_config_with_a_quiet_log_unless_it_has_a_log_of_its_own(tmp_path, monkeypatch):
    """Issue 36 item 6: what the node gives liblsl before its first use (drivers/lsl.py): the user's
    configuration file whole, with ``[log] level`` added (its INFO lines are not the node's user's
    business); untouched where it has a ``[log]`` section of its own, or a line liblsl refuses (its own
    error says which); the file found where liblsl looks for it."""
    from supramodal.drivers.lsl import LIBLSL_LOG_LEVEL, liblsl_config_file, quiet_config

    added = f"[log]\nlevel = {LIBLSL_LOG_LEVEL}\n"
    lab = "[lab]\nSessionID = bench\n; a comment\n\n[ports]\nIPv6 = disable"
    assert quiet_config(None) == added
    assert quiet_config(lab) == lab + "\n" + added
    assert quiet_config("[log]\nfile = lsl.log\n") is None
    assert quiet_config("[lab]\nSessionID\n") is None                     # no "=": liblsl refuses it
    assert quiet_config("[lab\n") is None
    monkeypatch.chdir(tmp_path)                                           # no lsl_api.cfg here
    own = tmp_path / "own.cfg"
    own.write_text(lab)
    (tmp_path / "home" / "lsl_api").mkdir(parents=True)
    (tmp_path / "home" / "lsl_api" / "lsl_api.cfg").write_text(lab)
    assert liblsl_config_file({"LSLAPICFG": str(own), "HOME": str(tmp_path / "home")}) == own
    assert liblsl_config_file({"HOME": str(tmp_path / "home")}) == tmp_path / "home" / "lsl_api" / "lsl_api.cfg"
