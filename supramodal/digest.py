"""A digest of a value's content.

It is what the cache of models trained on start keys its files by, and what the test suite's
once-per-run results are named by.

Two values digest alike when they hold the same content, however they were made: a model and its copy read
back from a file, a texture set built twice. Pure Python and numpy; no pickle (the content is read, never the
objects' own serialisation, whose bytes differ with how arrays are shared).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

__all__ = ["MAX_DEPTH", "feed"]

#: How deep values may nest (a list of dicts of dataclasses ...); deeper is refused, as a cycle would be.
MAX_DEPTH = 40


def feed(h: Any, x: Any, objects: bool = False, depth: int = 0) -> None:
    """Feed ``x``'s content to the hash ``h`` (a ``hashlib`` object).

    Parameters
    ----------
    h : hashlib hash
        Updated in place.
    x : object
        None, a bool, number, string or bytes (by type and repr); a numpy array (dtype, shape, bytes; not
        of objects); a list or tuple (item by item), a set (sorted by repr), a dict (sorted by the keys'
        repr); a dataclass instance (class and fields); a class (its qualified name); with ``objects``,
        also any other object that is not callable (class and attributes, ``__slots__`` too).
    objects : bool
        Whether plain objects are digested by their attributes (default False: refused, as a cache key
        should not take in what it cannot name).
    depth : int
        How deep this call is (the caller's: 0).

    Raises
    ------
    TypeError
        For anything else (a function, a lock, a file, an object array) or nesting deeper than
        :data:`MAX_DEPTH`.
    """
    if depth > MAX_DEPTH:
        raise TypeError("nested too deep")
    if x is None or isinstance(x, (bool, int, float, complex, str, bytes, np.generic)):
        h.update(f"{type(x).__name__}:{x!r};".encode())
    elif isinstance(x, np.ndarray):
        if x.dtype.hasobject:
            raise TypeError("an object array")
        h.update(f"ndarray:{x.dtype.str}:{x.shape};".encode())
        h.update(np.ascontiguousarray(x).tobytes())
    elif isinstance(x, (list, tuple, set, frozenset)):
        items = sorted(x, key=repr) if isinstance(x, (set, frozenset)) else x
        h.update(f"{type(x).__name__}:{len(items)}(".encode())
        for item in items:
            feed(h, item, objects, depth + 1)
        h.update(b")")
    elif isinstance(x, dict):
        h.update(f"dict:{len(x)}(".encode())
        for key in sorted(x, key=repr):
            feed(h, key, objects, depth + 1)
            feed(h, x[key], objects, depth + 1)
        h.update(b")")
    elif isinstance(x, type):
        h.update(f"type:{x.__module__}.{x.__qualname__};".encode())
    elif dataclasses.is_dataclass(x):
        h.update(f"{type(x).__module__}.{type(x).__qualname__}(".encode())
        for f in dataclasses.fields(x):
            feed(h, f.name, objects, depth + 1)
            feed(h, getattr(x, f.name), objects, depth + 1)
        h.update(b")")
    elif objects and hasattr(x, "__dict__") and not callable(x):
        h.update(f"object:{type(x).__module__}.{type(x).__qualname__}(".encode())
        state = dict(vars(x))
        for slot in getattr(type(x), "__slots__", ()):
            if hasattr(x, slot):
                state[slot] = getattr(x, slot)
        feed(h, state, objects, depth + 1)
        h.update(b")")
    else:
        raise TypeError(f"cannot digest a {type(x).__name__}")
