"""Checked reads of a JSON-shaped mapping's fields: what each value is, to the type checker and at run time.

A sink's options (validated by the scene's schema before a build sees them) and the frames the ros2 sink sends
its publisher process (JSON it wrote itself) are mappings whose values the code knows the type of, but a type
checker sees only a JSON value. These say which type, in one place, and raise TypeError where a value is not
what its reader expects: a fault of the code that made the mapping (a schema that let another type through, a
frame written otherwise), not of the scene. A missing key raises KeyError, as ``m[key]`` does.
"""

from __future__ import annotations

import numbers
from collections.abc import Callable, Mapping
from typing import TypeGuard, TypeVar

import numpy as np

__all__ = ["bool_of", "float_of", "int_mapping_of", "int_of", "mapping_of", "mappings_of",
           "optional_float_of", "optional_int_of", "optional_str_of", "optional_strs_of", "str_mapping_of", "str_of",
           "strs_of"]


def _wrong(key: str, value: object, what: str) -> TypeError:
    return TypeError(f"{key!r}: {value!r} is not {what}")


T = TypeVar("T")


def _read(m: Mapping[str, object], key: str, guard: Callable[[object], TypeGuard[T]], what: str) -> T:
    """Return ``m[key]`` where ``guard`` accepts it; else a TypeError naming the key and ``what`` was expected."""
    value = m[key]
    if guard(value):
        return value
    raise _wrong(key, value, what)


def _is_str(v: object) -> TypeGuard[str]:
    return isinstance(v, str)


def _is_int(v: object) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_real(v: object) -> TypeGuard[numbers.Real]:
    return isinstance(v, numbers.Real) and not isinstance(v, bool | np.bool_)


def _is_bool(v: object) -> TypeGuard[bool]:
    return isinstance(v, bool)


def _is_strs(v: object) -> TypeGuard[list[str]]:
    return isinstance(v, list) and all(isinstance(x, str) for x in v)


def _is_mapping(v: object) -> TypeGuard[Mapping[str, object]]:
    return isinstance(v, Mapping) and all(isinstance(k, str) for k in v)


def _is_mappings(v: object) -> TypeGuard[list[Mapping[str, object]]]:
    return isinstance(v, list) and all(_is_mapping(x) for x in v)


def str_of(m: Mapping[str, object], key: str) -> str:
    """Return ``m[key]``, text."""
    return _read(m, key, _is_str, "text")


def optional_str_of(m: Mapping[str, object], key: str) -> str | None:
    """Return ``m[key]``, text or None."""
    return None if m[key] is None else str_of(m, key)


def int_of(m: Mapping[str, object], key: str) -> int:
    """Return ``m[key]``, an integer (not a bool)."""
    return _read(m, key, _is_int, "an integer")


def optional_int_of(m: Mapping[str, object], key: str) -> int | None:
    """Return ``m[key]``, an integer or None."""
    return None if m[key] is None else int_of(m, key)


def float_of(m: Mapping[str, object], key: str) -> float:
    """Return ``m[key]``, a real number (Python's or NumPy's, not a bool), as a float."""
    return float(_read(m, key, _is_real, "a number"))


def optional_float_of(m: Mapping[str, object], key: str) -> float | None:
    """Return ``m[key]``, a number as a float, or None."""
    return None if m[key] is None else float_of(m, key)


def bool_of(m: Mapping[str, object], key: str) -> bool:
    """Return ``m[key]``, true or false."""
    return _read(m, key, _is_bool, "true or false")


def strs_of(m: Mapping[str, object], key: str) -> list[str]:
    """Return ``m[key]``, a list of text (a copy)."""
    return list(_read(m, key, _is_strs, "a list of text"))


def optional_strs_of(m: Mapping[str, object], key: str) -> list[str] | None:
    """Return ``m[key]``, a list of text (a copy), or None."""
    return None if m[key] is None else strs_of(m, key)


def mapping_of(m: Mapping[str, object], key: str) -> Mapping[str, object]:
    """Return ``m[key]``, a mapping of text to values."""
    return _read(m, key, _is_mapping, "a mapping of text to values")


def mappings_of(m: Mapping[str, object], key: str) -> list[Mapping[str, object]]:
    """Return ``m[key]``, a list of mappings of text to values (a copy)."""
    return list(_read(m, key, _is_mappings, "a list of mappings of text to values"))


def _values_of(m: Mapping[str, object], key: str, guard: Callable[[object], TypeGuard[T]], what: str) -> dict[str, T]:
    """Return ``m[key]``, a mapping of text to values ``guard`` accepts (a copy); else a TypeError."""
    value = mapping_of(m, key)
    out = {k: v for k, v in value.items() if guard(v)}
    if len(out) == len(value):
        return out
    raise _wrong(key, value, what)


def str_mapping_of(m: Mapping[str, object], key: str) -> dict[str, str]:
    """Return ``m[key]``, a mapping of text to text (a copy)."""
    return _values_of(m, key, _is_str, "a mapping of text to text")


def int_mapping_of(m: Mapping[str, object], key: str) -> dict[str, int]:
    """Return ``m[key]``, a mapping of text to integers (a copy; counts by name)."""
    return _values_of(m, key, _is_int, "a mapping of text to integers")
