"""scene_to_toml writes a bank table with only the keys its kind has (issue 26, item 6), so that
what it prints (``run --print-scene``, the replay scene ``record`` writes) loads back."""

from __future__ import annotations

import copy
import tomllib
from dataclasses import replace

import pytest

from supramodal.bankfile import BANK_KEYS
from supramodal.node.scene.schema import scene_from_dict, scene_to_toml


def _banks(text: str) -> list[dict]:
    d = tomllib.loads(text)
    return [st["bank"] for st in d["stream"]] if "stream" in d else [d["bank"]]


def test_a_cochlea_bank_is_written_without_the_whisker_banks_rows():
    """A graph scene changed in code (the microphone stream's bank copied from the whiskers' one,
    rows and all, then made a cochlea): the cochlea table holds no rows, the whisker one keeps
    its own, and the text loads back to the same banks."""
    d = {"source": [{"name": "w", "type": "synth"}, {"name": "m", "type": "synth"}],
         "stream": [{"name": "w", "source": "w", "bank": {"kind": "whisker", "rows": "ABC", "mean_B": 120.0}},
                    {"name": "m", "source": "m", "bank": {"kind": "cochlea", "channels": 12}}]}
    scene = scene_from_dict(d, "two.toml")
    w, m = scene.streams
    mic = replace(m.bank, recipe={**w.bank.recipe, "channels": 12})
    assert mic.recipe["rows"] == "ABC"                        # what the spec carries
    text = scene_to_toml(replace(scene, streams=(w, replace(m, bank=mic))))
    whisker, cochlea = _banks(text)
    assert whisker == {"kind": "whisker", "rows": "ABC", "mean_B": 120.0}
    assert cochlea == {"kind": "cochlea", "channels": 12}
    assert set(cochlea) - {"kind"} <= set(BANK_KEYS["cochlea"])
    again = scene_from_dict(tomllib.loads(text), "two.toml")
    assert "rows" not in again.streams[1].bank.recipe and again.streams[1].bank.recipe["channels"] == 12


@pytest.mark.parametrize("bank, written", [
    ({"kind": "cochlea", "f_low": 50.0, "f_high": 4000.0}, {"kind": "cochlea", "f_low": 50.0, "f_high": 4000.0}),
    ({"kind": "whisker", "rows": "AB"}, {"kind": "whisker", "rows": "AB"}),
    ({"file": "bank.json"}, {"file": "bank.json"}),       # a bank file alone: its kind is the file's
])
def test_a_one_source_scene_writes_only_its_banks_keys_and_reads_back(bank, written):
    scene = scene_from_dict({"driver": {"type": "synth"}, "bank": copy.deepcopy(bank)}, "one.toml")
    text = scene_to_toml(scene)
    assert _banks(text) == [written]
    again = scene_from_dict(tomllib.loads(text), "one.toml")
    assert again.only_stream().bank == scene.only_stream().bank
