"""Typed records that read as their JSON form: the base of the package's summaries.

A summary (a run's, a stream's, the fusion's, a decider's counts) is a frozen dataclass: the code that makes
it and the code that reads it (a sink, the view, the command line) agree on its fields, which a type checker
sees. What it is written as (JSON lines, the view's page) is :meth:`JsonRecord.to_dict`. The record also
reads as that dict (``summary["windows"]``, ``dict(summary)``, ``summary == {...}``), read-only, so that a
script written against the JSON it wrote, or against the dicts these summaries were before, reads them
unchanged.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator, Mapping

__all__ = ["JsonRecord", "JsonValue"]

#: What a JSON document holds (the type of a record's :meth:`~JsonRecord.to_dict` values).
JsonValue = None | bool | int | float | str | list["JsonValue"] | tuple["JsonValue", ...] | Mapping[str, "JsonValue"]


class JsonRecord(Mapping[str, "JsonValue"]):
    """A read-only mapping view of a record's JSON form; subclasses are frozen dataclasses with ``eq=False``.

    Subclasses define :meth:`to_dict`; equality, ``[key]``, ``in``, ``len`` and iteration are those of its
    result, so a record equals the dict it is written as. Not hashable.
    """

    def to_dict(self) -> dict[str, JsonValue]:
        """Return the record as it is written (JSON-ready: its keys, in their order)."""
        raise NotImplementedError

    @functools.cached_property
    def _json(self) -> dict[str, JsonValue]:
        # built once per record for the mapping view (a frozen record's JSON does not change): ``dict(r)`` and
        # ``**r`` read every key; to_dict() itself still gives a fresh dict the caller may change
        return self.to_dict()

    def __getitem__(self, key: str) -> JsonValue:
        return self._json[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._json)

    def __len__(self) -> int:
        return len(self._json)
