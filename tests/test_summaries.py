"""The run's summaries as typed records (node/runtime/summaries.py, supramodal/records.py): the fields a sink
reads agree with the JSON a sink writes, for a one-stream node, a graph of two streams and a fusion; the record
reads as that JSON, read-only; the decider's counts keep their conditional keys."""

from __future__ import annotations

import json

import numpy as np
import pytest

from supramodal.banks import cochlea_bank, whisker_bank
from supramodal.decisions import DecisionCounts
from supramodal.node.runtime.fusion import LateFusion
from supramodal.node.runtime.graph import Graph
from supramodal.node.runtime.sinks import ListSink
from supramodal.node.runtime.sinks.jsonl import JsonLinesSink
from supramodal.node.runtime.sinks.text import TextSink
from supramodal.node.runtime.sources import Source
from supramodal.node.runtime.streams import Stream
from supramodal.node.runtime.summaries import Accuracy, FusionSummary, Health, RunSummary, StreamSummary
from supramodal.pipeline import FeaturePipeline
from supramodal.replay.driver import ReplayDriver, random_block_sizes


def _source(name, x, rate, seed):
    return Source(name, ReplayDriver((x, rate), speed="max", seed=seed, block_size=random_block_sizes(1, 700),
                                     on_notice=None), overrun="block")


def _written(kind, summary: RunSummary, path) -> str:
    """What the file sink ``kind`` writes for ``summary``."""
    sink = kind(str(path))
    sink.summary(summary)
    sink.close()
    return path.read_text()


def _jsonl_summary(summary: RunSummary, path) -> dict:
    """What the jsonl sink writes for ``summary``, read back."""
    line = json.loads(_written(JsonLinesSink, summary, path).splitlines()[-1])
    assert line.pop("summary") is True
    return line


def test_a_one_stream_node_s_record_has_its_stream_and_writes_it_flat(tmp_path):
    x = np.random.default_rng(0).standard_normal((5000 * 2 + 123, 1)) * 0.2
    source = _source("main", x, 5000.0, 1)
    sink = ListSink()
    summary = Graph([source], [Stream("main", source, FeaturePipeline(whisker_bank(), ("Af",)))], [sink]).run()
    assert isinstance(summary, RunSummary) and sink.final is summary
    one = summary.one_stream
    assert isinstance(one, StreamSummary) and summary.streams == {"main": one}
    assert one.windows == summary.windows == 20 and one.partial_window_samples == 123
    assert one.frames["stream"] == one.frames["delivered"] == 10123
    assert one.decisions is None and one.accuracy == Accuracy(None, 0, None)
    written = _jsonl_summary(summary, tmp_path / "s.jsonl")
    # the JSON keeps the one-source shape: the stream's counts at the top level, no "streams"
    assert "streams" not in written and written["windows"] == 20 and written["frames"]["stream"] == 10123
    assert written == json.loads(json.dumps(summary.to_dict()))
    # the record reads as its JSON form, read-only
    assert summary == summary.to_dict() and dict(summary) == summary.to_dict()
    assert summary["windows"] == 20 and "frames" in summary and "streams" not in summary
    assert summary.get("clock") is None and len(summary) == len(written)
    with pytest.raises(TypeError):
        summary["windows"] = 3  # type: ignore[index]


def test_a_graph_s_record_has_each_stream_and_writes_them_by_name(tmp_path):
    rng = np.random.default_rng(1)
    whiskers = _source("whiskers", rng.standard_normal((5000 * 3, 1)) * 0.2, 5000.0, 2)
    mic = _source("mic", rng.standard_normal((44100 * 2, 1)) * 0.1, 44100.0, 3)
    streams = [Stream("whiskers", whiskers, FeaturePipeline(whisker_bank(), ("Af",))),
               Stream("mic", mic, FeaturePipeline(cochlea_bank(), ("Af",)))]
    summary = Graph([whiskers, mic], streams, [ListSink()]).run()
    assert summary.one_stream is None and summary.fusion is None
    assert {k: s.windows for k, s in summary.streams.items()} == {"whiskers": 30, "mic": 20}
    assert summary.windows == 50 and summary.stream_seconds == pytest.approx(3.0)
    assert {s.source for s in summary.streams.values()} == {"whiskers", "mic"}
    written = _jsonl_summary(summary, tmp_path / "s.jsonl")
    assert written["windows"] == 50 and set(written["streams"]) == {"whiskers", "mic"}
    assert written["streams"]["mic"]["frames"]["stream"] == 88200 == summary.streams["mic"].frames["stream"]
    assert "source" not in written["streams"]["mic"]          # the record knows it; the JSON never had it
    assert summary["streams"]["whiskers"]["windows"] == 30
    # the text sink's block reads the same fields
    text = _written(TextSink, summary, tmp_path / "s.txt")
    assert "windows            50 on 2 streams" in text and "stream whiskers" in text and "stream mic" in text


def test_a_fusion_s_record_carries_its_accuracy_and_decisions_and_writes_them_flat():
    classes = ("a", "b")
    fusion = LateFusion(("x", "y"), (classes, classes), weight=0.5, max_wait=1.0)
    summary = fusion.summary()
    assert isinstance(summary, FusionSummary) and isinstance(summary.decisions, DecisionCounts)
    assert summary.inputs == ("x", "y") and summary.method == "late" and summary.weight == 0.5
    d = summary.to_dict()
    assert d["inputs"] == ["x", "y"] and d["window_accuracy"] is None and d["labelled_windows"] == 0
    assert d["unknown_windows"] == dict(summary.decisions.unknown_windows) and "accuracy" not in d
    assert json.loads(json.dumps(d)) == d and summary == d


@pytest.mark.parametrize(("counts", "keys"), [
    (DecisionCounts({"novel": 1}), ["unknown_windows"]),
    (DecisionCounts({}, changes=2), ["unknown_windows", "changes"]),
    (DecisionCounts({}, contacts_decided=3, windows_to_decide_median=None),
     ["unknown_windows", "contacts_decided", "windows_to_decide_median"]),
    (DecisionCounts({}, changes=0, contacts_decided=1, windows_to_decide_median=4.0),
     ["unknown_windows", "changes", "contacts_decided", "windows_to_decide_median"]),
])
def test_decision_counts_write_only_the_keys_that_apply(counts, keys):
    """A decider without a change detector has no ``changes``; one without a confidence threshold no decided
    counts, while one with it keeps ``windows_to_decide_median`` even when nothing was decided (None)."""
    assert list(counts.to_dict()) == keys and list(counts) == keys


def test_health_is_a_record_of_the_graph_s_counters():
    x = np.random.default_rng(4).standard_normal((5000, 1)) * 0.2
    source = _source("s", x, 5000.0, 5)
    graph = Graph([source], [Stream("w", source, FeaturePipeline(whisker_bank(), ("Af",)))], [ListSink()])
    summary = graph.run()
    health = graph.health()
    assert isinstance(health, Health) and health.fusion is None and health.clocks == {}
    assert health.streams["w"].windows == summary.streams["w"].windows == 10
    assert health.streams["w"].source == "s" and health.streams["w"].frames == summary.streams["w"].frames
    d = health.to_dict()
    assert d["streams"]["w"]["source"] == "s" and json.loads(json.dumps(d)) == d
