"""One validation vocabulary: what a key of a scene table, a bank file or a driver accepts, said once.

A table's schema is a mapping ``key -> Key``. A :class:`Key` holds a check (a predicate on the
value as TOML or JSON gives it), the words that say what it expects (they go into the error
message and into the docs' key tables) and its default: a value, ``None`` (the key's owner, a
driver or a bank, keeps its own default and is not passed the key) or :data:`REQUIRED`.
:func:`fill` validates a table against a schema and fills in the defaults; every refusal names
the table (``where``), the key, what was expected and what was given.

The predicates below are the words of the vocabulary. Numbers are always finite and never
booleans (TOML's ``true`` is not 1); integers are Python ints.

Pure Python; drivers, replay, the model's file readers and the node all use it.
"""

from __future__ import annotations

import math
import numbers
import unicodedata
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, TypeGuard

from supramodal.errors import InputError

__all__ = ["REQUIRED", "Key", "fill", "flag", "integer", "is_name", "is_number", "non_negative", "number", "one_of",
           "positive", "text", "texts", "NAME_HELP", "MAX_NAME"]


class _Required:
    def __repr__(self) -> str:
        return "REQUIRED"


#: The default of a key that a table must give.
REQUIRED: Any = _Required()

#: Longest name (of a source, a stream, an outlet prefix), characters.
MAX_NAME = 64
NAME_HELP = f"a name: letters, digits, '-' or '_', at most {MAX_NAME} characters"


@dataclass(frozen=True)
class Key:
    """One key of a table.

    Attributes
    ----------
    check : callable
        ``check(value) -> bool``: whether the value as parsed (TOML or JSON) is acceptable.
    expected : str
        What the key accepts, in words: the error message says "expected <expected>"; the docs'
        key tables print it.
    default : object
        The value when the key is absent; ``None``: the owner's own default applies (the key is
        not passed on); :data:`REQUIRED`: the table must give it.
    path : bool
        The value names a file, relative to the folder of the file the table is in (a scene's): a
        scene written elsewhere makes it absolute. Default False.
    words : tuple of str
        Values of a ``path`` key that name no file (``"-"``, stdout; ``"reference"``, the built-in
        texture set): kept as they are.
    """

    check: Callable[[Any], bool]
    expected: str
    default: Any = REQUIRED
    path: bool = False
    words: tuple[str, ...] = ()

    @property
    def required(self) -> bool:
        """Whether the key must be given (it has no default)."""
        return self.default is REQUIRED


Schema = Mapping[str, Key]


def fill(where: str, given: Any, keys: Schema, error: type[InputError] = InputError) -> dict[str, Any]:
    """Validate the table ``given`` against ``keys`` and fill in the defaults.

    Parameters
    ----------
    where : str
        The table, as the user wrote it (e.g. ``"scene.toml: [driver] (serial)"``); every message
        starts with it.
    given : dict
        The table as parsed.
    keys : mapping of str to Key
    error : type
        The exception raised (a subclass of :class:`~supramodal.errors.InputError`).

    Returns
    -------
    dict
        Every key of ``keys`` with its value (given, or the default; ``None`` for the owner's).

    Raises
    ------
    error
        For a table that is not a table, an unknown key, a value its check refuses, or a
        required key missing; the message names the key and what it expects.
    """
    if not isinstance(given, dict):
        raise error(f"{where} must be a table")
    unknown = sorted(set(given) - set(keys))
    if unknown:
        raise error(f"{where}: unknown key(s) {unknown}; allowed keys: {sorted(keys)}")
    out = {}
    for key, spec in keys.items():
        if key in given:
            value = given[key]
            if not spec.check(value):
                raise error(f"{where} {key}: expected {spec.expected}, got {value!r}")
            out[key] = value
        elif spec.required:
            raise error(f"{where}: missing required key {key!r} ({spec.expected})")
        else:
            out[key] = spec.default
    return out


# -- the words ---------------------------------------------------------------------------------------

def is_number(v: object) -> bool:
    """Whether ``v`` is a finite real number (Python's or NumPy's), not a bool; an int too large for a float is not."""
    if not isinstance(v, numbers.Real) or isinstance(v, bool) or type(v).__name__ == "bool_":
        return False
    try:
        return math.isfinite(v)
    except OverflowError:                   # an int beyond float's range: no sample rate or time is that
        return False


def number(lo: float = -math.inf, hi: float = math.inf, *, lo_open: bool = False,
           hi_open: bool = False) -> Callable[[Any], bool]:
    """Return a check for a finite number within ``[lo, hi]`` (an end excluded where ``lo_open`` / ``hi_open``)."""
    def check(v: Any) -> bool:
        if not is_number(v):
            return False
        return bool((v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi))
    return check


def positive(hi: float = math.inf) -> Callable[[Any], bool]:
    """Return a check for a finite number ``0 < v <= hi``."""
    return number(0.0, hi, lo_open=True)


def non_negative(hi: float = math.inf) -> Callable[[Any], bool]:
    """Return a check for a finite number ``0 <= v <= hi``."""
    return number(0.0, hi)


def integer(lo: int | None = None, hi: int | None = None) -> Callable[[Any], bool]:
    """Return a check for an int (not a bool) within ``[lo, hi]`` (an absent end: unbounded)."""
    return lambda v: (isinstance(v, int) and not isinstance(v, bool) and (lo is None or v >= lo)
                      and (hi is None or v <= hi))


def one_of(*choices: object) -> Callable[[Any], bool]:
    """One of ``choices`` (compared with ``==``, so ``1`` is not ``True``)."""
    return lambda v: any(v == c and type(v) is type(c) for c in choices)


def flag(v: object) -> bool:
    """Whether ``v`` is ``true`` or ``false``."""
    return isinstance(v, bool)


def text(v: object) -> TypeGuard[str]:
    """Whether ``v`` is a non-empty string."""
    return isinstance(v, str) and v != ""


def texts(v: object) -> bool:
    """Whether ``v`` is a list of strings (possibly empty)."""
    return isinstance(v, list) and all(isinstance(t, str) for t in v)


#: Longest class name (a model's class, a manifest's label), characters.
MAX_CLASS_NAME = 200
CLASS_NAME_HELP = (f"printable text of at most {MAX_CLASS_NAME} characters (no control characters, tabs, line "
                   "breaks or other invisible ones)")


#: Unicode categories no class name holds: control characters (a terminal's escapes, tabs, line breaks), format
#: characters (bidi overrides that turn text around, invisible joiners), surrogates, line and paragraph separators.
_NOT_IN_CLASS_NAMES = frozenset({"Cc", "Cf", "Cs", "Zl", "Zp"})


def is_class_name(v: object) -> bool:
    """Whether ``v`` is a class name (:data:`CLASS_NAME_HELP`).

    A class name is what a model decides and the node prints, shows and publishes. Freer than
    :func:`is_name` (a manifest's ``"rough, wet"``, any script), but never a terminal's escape sequence, a
    line break that forges another output line, or a character that turns text around.
    """
    return (text(v) and len(v) <= MAX_CLASS_NAME
            and not any(unicodedata.category(c) in _NOT_IN_CLASS_NAMES for c in v))


def is_name(v: object) -> bool:
    """Whether ``v`` is a name (:data:`NAME_HELP`): what becomes a stream name, a file name part or an outlet name."""
    return text(v) and len(v) <= MAX_NAME and all(c.isalnum() or c in "-_" for c in v)
