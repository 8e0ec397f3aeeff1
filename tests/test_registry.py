"""A new driver, sink, tap or feature is one module (or one row) plus one line: a toy of each, defined in
this file alone, runs from a scene (a toy command: tests/test_cli.py).

Also: every driver type a scene may name has a spec that fits (its keys validate its defaults, its
type is its name), and the scene refuses a type no driver has, listing those there are.
"""

from __future__ import annotations

import re
import time

import numpy as np
import pytest

from supramodal.backends import make_filterbank
from supramodal.banks import whisker_bank
from supramodal.checks import Key, integer, positive
from supramodal.drivers.base import Block, DriverBase, DriverClosed
from supramodal.drivers.spec import Built, BuildContext, DriverSpec, OptionError
from supramodal.errors import InputError
from supramodal.features import FEATURE_TABLE, Feature
from supramodal.node.runtime.ringbuffer import RingClosed
from supramodal.node.runtime.taps import Tap
from supramodal.node.scene import registry
from supramodal.node.scene.build import build_node
from supramodal.node.scene.schema import SceneError, scene_from_dict
from supramodal.node.runtime.sinks.spec import NEEDS, SinkSpec, sink_keys
from supramodal.node.runtime.sinks import ListSink, Sink
from supramodal.pipeline import FeaturePipeline


class ToneDriver(DriverBase):
    """A driver no one in the package wrote: a sine on every channel, ``seconds`` long (the base
    gives the event log, the labels of a driver that has none and the context manager)."""

    def __init__(self, rate: float, channels: int, frequency: float, seconds: float, block: int) -> None:
        self.rate, self.channels, self.block = float(rate), int(channels), int(block)
        self._n = int(round(seconds * rate))
        self._frequency = frequency
        self._pos = 0
        self.opened = False

    def open(self) -> None:
        self.opened = True

    def close(self) -> None:
        self.opened = False

    def read(self, timeout: float | None = None) -> Block | None:
        if self._pos >= self._n:
            raise DriverClosed("the tone has ended")
        n = min(self.block, self._n - self._pos)
        t = (self._pos + np.arange(n)) / self.rate
        data = np.repeat(0.5 * np.sin(2 * np.pi * self._frequency * t)[:, None], self.channels, axis=1)
        block = Block(data=data, start=self._pos, arrival=time.monotonic())
        self._pos += n
        return block

    def stats(self) -> dict[str, int]:
        return {"frames": self._pos, "filled": 0}


def _build(options: dict, context: BuildContext) -> Built:
    if context.rate is None:
        raise OptionError("frequency: a tone needs a bank to set its rate")
    if options["frequency"] >= context.rate / 2:
        raise OptionError(f"frequency: {options['frequency']:g} Hz is above the bank's Nyquist frequency")
    return Built(ToneDriver(context.rate, context.channels, options["frequency"], options["seconds"],
                            options["block"]),
                 labels=((0.0, options["seconds"], "tone"),))


TONE = DriverSpec(type="tone", summary="a test tone", live=False, build=_build,
                  # every numeric key has both bounds (docs/architecture.md): the Nyquist frequency is the build's
                  keys={"frequency": Key(positive(20000.0), "Hz, > 0, up to 20000", 100.0),
                        "seconds": Key(positive(60.0), "seconds, up to 60", 1.0),
                        "block": Key(integer(1, 4096), "frames per block, 1..4096", 64)})


@pytest.fixture
def tone():
    registry.register_driver(TONE, replace=True)          # the one line
    yield TONE
    registry.DRIVERS.unregister("tone")


def test_a_toy_driver_defined_here_runs_from_a_scene(tone):
    scene = scene_from_dict({"driver": {"type": "tone", "frequency": 120.0, "seconds": 0.55, "block": 77},
                             "bank": {"kind": "whisker"}, "features": {"names": ["Af"]}})
    src, stream = scene.only_source(), scene.only_stream()
    assert (src.type, dict(src.options), stream.mapping) == \
        ("tone", {"frequency": 120.0, "seconds": 0.55, "block": 77}, "auto")
    sink = ListSink()
    summary = build_node(scene, sinks_override=[sink]).run()
    windows = sink.windows
    assert len(windows) == 5                                  # 0.55 s of 100 ms windows
    af = [np.asarray(e.features["Af"]).ravel() for e in windows]
    assert all(np.all(np.isfinite(a)) and a.shape == (20,) for a in af)
    # A 120 Hz tone: the whisker whose centre frequency is nearest answers most (Af).
    from supramodal.banks import whisker_bank

    nearest = int(np.argmin(np.abs(whisker_bank().cf - 120.0)))
    assert all(int(np.argmax(a)) == nearest for a in af[1:])
    assert all(e.truth == "tone" for e in windows)
    fates = summary["frames"]
    assert fates["delivered"] == round(0.55 * 5000) and fates["dropped"] == 0


def test_a_toy_drivers_keys_are_checked_like_any_others(tone):
    with pytest.raises(SceneError, match=r"\[driver\] \(tone\) seconds: expected seconds, up to 60, got 1000"):
        scene_from_dict({"driver": {"type": "tone", "seconds": 1000}})
    with pytest.raises(SceneError, match=r"unknown key\(s\) \['path'\]"):
        scene_from_dict({"driver": {"type": "tone", "path": "x.wav"}})
    scene = scene_from_dict({"driver": {"type": "tone", "frequency": 4000.0}})
    with pytest.raises(SceneError, match=r"\[driver\] frequency: 4000 Hz is above the bank's Nyquist"):
        build_node(scene, sinks_override=[ListSink()])


def test_a_type_is_registered_once_unless_replaced(tone):
    with pytest.raises(ValueError, match="exists already"):
        registry.register_driver(TONE)
    with pytest.raises(ValueError, match="exists already"):
        registry.register_driver(DriverSpec(type="serial", keys={}, build=_build, live=True, summary="x"))


def test_an_unknown_type_is_refused_listing_the_types_there_are():
    # the types there are, from the registry (a new driver changes no test); the built-in ones among them
    assert set(registry.DRIVER_MODULES) <= set(registry.driver_types())
    with pytest.raises(SceneError, match=r"\[driver\] type: expected one of " + re.escape(str(registry.driver_types()))
                       + ", got 'tone'"):
        scene_from_dict({"driver": {"type": "tone"}})


@pytest.mark.parametrize("kind", sorted(registry.DRIVER_MODULES))
def test_every_built_in_spec_fits_its_type_and_its_own_defaults(kind):
    spec = registry.driver_spec(kind)
    assert spec.type == kind and spec.summary
    for key, k in registry.source_keys(spec).items():
        if not k.required and k.default is not None:
            assert k.check(k.default), (kind, key, k.default)
        assert k.expected, (kind, key)
    assert spec.overrun == ("drop-oldest" if spec.live and not spec.buffered else "block")


def test_naming_a_driver_type_loads_only_its_module():
    """A scene without a microphone never loads sounddevice's module, without a serial port never pyserial."""
    import subprocess
    import sys

    code = ("import sys; from supramodal.node.scene.schema import scene_from_dict; "
            "scene_from_dict({'driver': {'type': 'synth'}}); "
            "print(sorted(m for m in ('serial', 'sounddevice', 'supramodal.drivers.microphone', "
            "'supramodal.drivers.serial_whisker', 'supramodal.drivers.lsl', 'supramodal.node.runtime.sinks.lsl', 'pylsl') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_the_docs_key_tables_are_the_schemas():
    """README.md and docs/node.md hold tables made from the schema (python -m supramodal.node.scene.docs):
    a key added, removed or reworded without regenerating them fails here."""
    from pathlib import Path

    from supramodal.node.scene import docs as scene_docs

    root = Path(__file__).resolve().parents[1]
    assert scene_docs.check(root) == [], "the docs' key tables are stale: run python -m supramodal.node.scene.docs"
    made = scene_docs.blocks()
    assert all(f"`{kind}`" in made["driver-types"] for kind in registry.driver_types())
    assert "| `timing` |" in made["driver-keys"] and "| `labels` |" in made["driver-keys"]
    node_md = (root / "docs/node.md").read_text()
    assert all(f'`type = "{kind}"`' in node_md for kind in registry.driver_types())


class TallySink(Sink):
    """A sink no one in the package wrote: counts each stream's windows and decisions."""

    def __init__(self, label: str, tallies: dict) -> None:
        self.label, self.tallies = label, tallies
        self.closed = False

    def emit(self, event) -> None:
        key = (self.label, event.stream, event.decision)
        self.tallies[key] = self.tallies.get(key, 0) + 1

    def close(self) -> None:
        self.closed = True


TALLIES: dict = {}
TALLY = SinkSpec(type="tally", summary="counts windows", keys={"label": Key(lambda v: isinstance(v, str), "a label", "t")},
                 build=lambda options, context: TallySink(options["label"], TALLIES))


@pytest.fixture
def tally():
    registry.register_sink(TALLY, replace=True)          # the one line
    TALLIES.clear()
    yield TALLY
    registry.SINKS.unregister("tally")


def test_a_toy_sink_defined_here_runs_from_a_scene_beside_the_built_in_ones(tone, tally, tmp_path):
    scene = scene_from_dict({"driver": {"type": "tone", "frequency": 120.0, "seconds": 0.55},
                             "sink": [{"type": "tally", "label": "x"}, {"type": "jsonl", "path": "w.jsonl"}]},
                            str(tmp_path / "s.toml"), tmp_path)
    assert (scene.sinks[0].type, dict(scene.sinks[0].options)) == ("tally", {"label": "x", "from": None})
    build_node(scene).run()
    assert TALLIES == {("x", "main", None): 5}            # no model: feature windows, no decision
    assert len((tmp_path / "w.jsonl").read_text().splitlines()) == 5 + 1     # and the summary
    with pytest.raises(SceneError, match=r"\[\[sink\]\] #1 label: expected a label, got 3"):
        scene_from_dict({"driver": {"type": "tone"}, "sink": [{"type": "tally", "label": 3}]})
    with pytest.raises(SceneError, match=r"\[\[sink\]\] #1 from: no stream 'elsewhere'"):
        scene_from_dict({"driver": {"type": "tone"}, "sink": [{"type": "tally", "from": "elsewhere"}]})


@pytest.mark.parametrize("kind", sorted(registry.SINK_MODULES))
def test_every_built_in_sink_spec_fits_its_type_and_its_own_defaults(kind):
    spec = registry.sink_spec(kind)
    assert spec.type == kind and spec.summary and spec.listens in ("windows", "samples")
    assert spec.needs in NEEDS
    for key, k in sink_keys(spec).items():
        if not k.required and k.default is not None:
            assert k.check(k.default), (kind, key, k.default)


# -- a tap: a sink of a source's samples -------------------------------------------------------------------------

class SquaresTap(Tap):
    """A tap no one in the package wrote: reads its source's raw frames and sums their squares, per channel."""

    name = "squares"
    track = False                   # it reads neither the blocks' arrivals nor the driver's marks

    def __init__(self, sums: dict) -> None:
        self.sums = sums

    def run(self, feed) -> None:
        while True:
            try:
                got = feed.reader.read(timeout=0.05)
            except RingClosed:
                return
            if got is not None:
                data = got[1]
                self.sums["frames"] = self.sums.get("frames", 0) + data.shape[0]
                self.sums["squares"] = self.sums.get("squares", 0.0) + (np.asarray(data, np.float64) ** 2).sum(axis=0)


SUMS: dict = {}
SQUARES = SinkSpec(type="squares", summary="sums a source's squared samples", keys={}, listens="samples",
                   needs="sources", build=lambda options, context: SquaresTap(SUMS))


def test_a_toy_tap_defined_here_reads_its_source_from_a_scene(tone):
    registry.register_sink(SQUARES, replace=True)          # the one line
    SUMS.clear()
    try:
        scene = scene_from_dict({"driver": {"type": "tone", "frequency": 120.0, "seconds": 0.55, "block": 77},
                                 "sink": [{"type": "squares"}]})
        assert scene.sinks[0].type == "squares" and dict(scene.sinks[0].options) == {"source": "main"}   # the only source
        summary = build_node(scene, sinks_override=None).run()
    finally:
        registry.SINKS.unregister("squares")
    n = round(0.55 * 5000)
    assert SUMS["frames"] == n and summary["taps"]["squares"]["frames"]["delivered"] == n
    # every raw frame, against the tone written out: 0.5 sin(2 pi 120 t) on each of the whisker array's 20 channels
    plain = sum((0.5 * np.sin(2 * np.pi * 120.0 * k / 5000.0)) ** 2 for k in range(n))
    np.testing.assert_allclose(SUMS["squares"], np.full(20, plain), rtol=1e-6)


# -- a feature: one row of FEATURE_TABLE -------------------------------------------------------------------------

#: A feature no one in the package wrote: how many peaks a window holds, per channel.
PEAK_COUNT = Feature("n", "the number of peaks", False, lambda amp, freq: np.ones_like(amp), "peaks")


def _plain_peaks(y: np.ndarray, length: int, windows: int) -> tuple[np.ndarray, np.ndarray]:
    """Per window and channel, the count and the sum of the peaks of the filterbank's output ``y`` by their
    definition, one sample at a time: above 0, above the sample before (0 before the stream), not below the one
    after; a peak at sample k counts in the window of its detection, k + 1."""
    count, total = np.zeros((windows, y.shape[0])), np.zeros((windows, y.shape[0]))
    for c in range(y.shape[0]):
        left = 0.0
        for k in range(y.shape[1] - 1):
            mid, right = y[c, k], y[c, k + 1]
            if left < mid >= right and mid > 0 and (k + 1) // length < windows:
                count[(k + 1) // length, c] += 1
                total[(k + 1) // length, c] += mid
            left = mid
    return count, total


def test_a_toy_feature_defined_here_is_computed_by_the_pipeline(monkeypatch):
    bank = whisker_bank()
    with pytest.raises(InputError, match=r"unknown feature\(s\) \['n'\]"):
        FeaturePipeline(bank, ("n", "A"))
    monkeypatch.setitem(FEATURE_TABLE, "n", PEAK_COUNT)                  # the one row
    x = 0.1 * np.random.default_rng(5).standard_normal(2750)             # noise: each channel its own count
    pipe = FeaturePipeline(bank, ("n", "A"), 0.1)
    got = pipe.run(x, block=333)
    count, total = _plain_peaks(make_filterbank(bank).process(x), pipe.window_samples, 5)
    assert len(got) == 5 and got.features == ("n", "A")
    np.testing.assert_array_equal(got.feature("n"), count)
    assert len(np.unique(count)) > 5                                      # not one count everywhere
    np.testing.assert_allclose(got.feature("A"), total, rtol=1e-12)


def test_a_toy_feature_defined_here_runs_from_a_scene(tone, monkeypatch):
    d = {"driver": {"type": "tone", "frequency": 120.0, "seconds": 0.55}, "features": {"names": ["n", "Af"]}}
    with pytest.raises(SceneError, match=r"\[features\] names: expected a list of distinct names"):
        scene_from_dict(d)
    monkeypatch.setitem(FEATURE_TABLE, "n", PEAK_COUNT)                  # the one row
    sink = ListSink()
    build_node(scene_from_dict(d), sinks_override=[sink]).run()
    got = np.array([np.asarray(e.features["n"]).ravel() for e in sink.windows])
    # what the pipeline makes of the tone offline, and a 120 Hz tone's 12 periods per 100 ms once the filters settle
    x = 0.5 * np.sin(2 * np.pi * 120.0 * np.arange(2750) / 5000.0)
    offline = FeaturePipeline(whisker_bank(), ("n", "Af")).run(x)
    np.testing.assert_array_equal(got, offline.feature("n"))
    np.testing.assert_array_equal(got[1:], 12.0)
    np.testing.assert_allclose([np.asarray(e.features["Af"]).ravel() for e in sink.windows], offline.feature("Af"),
                               rtol=1e-9)
