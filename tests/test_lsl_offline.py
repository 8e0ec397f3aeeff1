"""The LSL inlet's parts that need no network: the timestamp judge, the scene, and the error a
user without the ``lsl`` extra gets (these run in the core suite, pylsl or not)."""

import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from supramodal.drivers.lsl import LSLUnavailable, TimestampSteps, import_pylsl
from supramodal.node.build import build_node
from supramodal.node.cli import main
from supramodal.node.scene import SceneError, scene_from_dict

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
