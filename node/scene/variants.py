"""Variants of a scene made in code rather than in its file: the scene with one more sink.

A scene is frozen (:mod:`~supramodal.node.scene.specs`): a variant is a new scene made with
:func:`dataclasses.replace`. :func:`with_sink` adds a sink of any type; :func:`with_view` and
:func:`add_view` are ``--view PORT`` of ``supramodal run`` and ``supramodal record`` (a page in the
browser beside the scene's own sinks).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from supramodal.checks import fill
from supramodal.errors import InputError
from supramodal.node.runtime.sinks import QueuedSink
from supramodal.node.runtime.sinks.spec import sink_keys
from supramodal.node.runtime.sinks.view import SPEC as VIEW
from supramodal.node.runtime.sinks.view import ViewError, ViewSink
from supramodal.node.scene.registry import sink_spec
from supramodal.node.scene.specs import Scene, SceneError, SinkSettings, frozen

__all__ = ["add_view", "with_sink", "with_view"]


def with_sink(scene: Scene, kind: str, **options: Any) -> Scene:
    """``scene`` with a sink of type ``kind`` after its own: ``options`` checked against the sink's
    keys, the others at their defaults (as a ``[[sink]]`` table of the scene file would be; a sink of
    samples names its ``source``).

    Raises
    ------
    SceneError
        For a type no sink has, an unknown key, a value its key refuses, or a required key missing.
    """
    where = f"{scene.source}: [[sink]] #{len(scene.sinks) + 1}"
    try:
        spec = sink_spec(kind)
    except InputError as exc:   # as the schema says it
        raise SceneError(f"{where} type: {exc}") from None
    values = fill(where, options, sink_keys(spec), SceneError)
    return replace(scene, sinks=(*scene.sinks, SinkSettings(kind, frozen(values), len(scene.sinks))))


def with_view(scene: Scene, port: int) -> Scene:
    """``run --view PORT``: the scene with a view sink added (every stream, and the fusion)."""
    if any(s.type == VIEW.type for s in scene.sinks):
        raise ViewError(f"{scene.source} has a [[sink]] type = \"view\" already; leave out --view, or that sink")
    return with_sink(scene, VIEW.type, port=port)


def add_view(scene: Scene, sinks: list[Any] | None, port: int) -> tuple[Scene, list[Any] | None]:
    """``run --view PORT``: the scene with a view sink added, or (``--json``, whose ``sinks``
    replace the scene's) those sinks with a view beside them."""
    if isinstance(port, bool) or not VIEW.keys["port"].check(port):
        raise ViewError(f"--view {port!r}: expected a TCP port 0..65535 (0: any free one)")
    if sinks is not None:
        return scene, [*sinks, QueuedSink(ViewSink(port))]
    return with_view(scene, port), None
