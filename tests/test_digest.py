"""supramodal.digest: values of the same content digest alike however they were made, and different content
differently; what it cannot name it refuses."""

from __future__ import annotations

import hashlib
import pickle
from dataclasses import dataclass

import numpy as np
import pytest

from supramodal.digest import MAX_DEPTH, feed


def _hex(x, objects=False) -> str:
    h = hashlib.sha256()
    feed(h, x, objects)
    return h.hexdigest()


@dataclass(frozen=True)
class _Set:
    names: tuple
    fs: float


class _Plain:
    def __init__(self, w):
        self.w = w
        self.shared = w                              # one array held twice: a pickle stores it once


def test_the_same_content_digests_alike_however_it_was_made():
    a = np.arange(12.0).reshape(3, 4)
    assert _hex(a) == _hex(a.copy()) == _hex(np.asfortranarray(a)) == _hex(a.T.copy().T)
    assert _hex({"b": 1, "a": [1, 2]}) == _hex({"a": [1, 2], "b": 1})
    assert _hex({3, 1, 2}) == _hex(set([2, 3, 1])) != _hex([1, 2, 3])
    assert _hex(_Set(("a",), 5000.0)) == _hex(_Set(("a",), 5000.0))
    plain = _Plain(np.ones(3))
    assert _hex(plain, objects=True) == _hex(pickle.loads(pickle.dumps(plain)), objects=True)


def test_different_content_digests_differently():
    a = np.arange(4.0)
    assert len({_hex(a), _hex(a.astype(np.float32)), _hex(a.reshape(2, 2)), _hex(a + 1e-15)}) == 4
    assert len({_hex(1), _hex(1.0), _hex(True), _hex("1"), _hex(b"1")}) == 5
    assert _hex([1, [2]]) != _hex([[1], 2]) and _hex((1, 2)) != _hex([1, 2])
    assert _hex(_Set(("a",), 5000.0)) != _hex(_Set(("a",), 5001.0))
    assert _hex(int) != _hex(float)


def test_what_it_cannot_name_is_refused():
    with pytest.raises(TypeError, match="_Plain"):
        _hex(_Plain(1))                              # a cache key takes no plain object unless asked
    for bad in (lambda: 0, np.array([object()]), open):
        with pytest.raises(TypeError):
            _hex(bad, objects=True)
    deep: list = []
    for _ in range(MAX_DEPTH + 2):
        deep = [deep]
    with pytest.raises(TypeError, match="deep"):
        _hex(deep)
