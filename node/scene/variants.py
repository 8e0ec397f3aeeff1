"""Variants of a scene made in code rather than in its file.

A scene is frozen (:mod:`~supramodal.node.scene.specs`): a variant is a new scene made with
:func:`dataclasses.replace`, each new table checked as the scene file's would be, never by writing the
scene out and reading it back. :func:`with_sink` adds a sink of any type; :func:`with_view` and
:func:`add_view` are ``--view PORT`` of ``supramodal run`` and ``supramodal record`` (a page in the
browser beside the scene's own sinks); :func:`with_models` and :func:`with_fusion` give streams model
files and a fusion (``train --fusion``, ``evaluate --model``); :func:`with_absolute_paths` and
:func:`relocated` make a scene that is written into another folder (the scenes ``train --fusion`` and
``record`` write).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

from supramodal.checks import Key, fill
from supramodal.errors import InputError
from supramodal.node.runtime.sinks import QueuedSink
from supramodal.node.runtime.sinks.spec import sink_keys
from supramodal.node.runtime.sinks.view import SPEC as VIEW
from supramodal.node.runtime.sinks.view import ViewError, ViewSink
from supramodal.node.scene.registry import driver_spec, sink_spec
from supramodal.node.scene.schema import driver_table, fusion_from_table
from supramodal.node.scene.specs import ModelSpec, Options, Scene, SceneError, SinkSettings, frozen

__all__ = ["add_view", "as_replay", "relocated", "with_absolute_paths", "with_fusion", "with_models", "with_sink",
           "with_view"]


def with_sink(scene: Scene, kind: str, **options: Any) -> Scene:
    """Return ``scene`` with a sink of type ``kind`` after its own.

    ``options`` are checked against the sink's keys, the others at their defaults (as a ``[[sink]]`` table
    of the scene file would be; a sink of samples names its ``source``).

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
    """Return the scene with a view sink added, for ``run --view PORT``; or those ``sinks`` with a view beside them.

    The latter with ``--json``, whose ``sinks`` replace the scene's.
    """
    if isinstance(port, bool) or not VIEW.keys["port"].check(port):
        raise ViewError(f"--view {port!r}: expected a TCP port 0..65535 (0: any free one)")
    if sinks is not None:
        return scene, [*sinks, QueuedSink(ViewSink(port))]
    return with_view(scene, port), None


def with_models(scene: Scene, models: Mapping[str, str | Path]) -> Scene:
    """Return ``scene`` with the streams named in ``models`` (``{stream: model file}``) deciding with those files.

    The files are made absolute. When two are named and the scene fuses other streams or none, the scene
    gets a ``[fusion]`` of those two (late, its defaults).

    Raises
    ------
    InputError
        A name no stream of the scene has, or no model file at a path (saying how to train one).
    """
    names = [st.name for st in scene.streams]
    unknown = sorted(set(models) - set(names))
    if unknown:
        raise InputError(f"{scene.source}: --model names stream(s) {unknown}; its streams are {names}")
    files = {}
    for name, given in models.items():
        path = Path(given).expanduser().resolve()
        if not path.is_file():
            raise InputError(f"--model {name}={given}: no model file there; train it first "
                             f"(supramodal train --scene ... --stream {name} --out FILE)")
        files[name] = str(path)
    scene = replace(scene, streams=tuple(replace(st, model=ModelSpec(path=files[st.name])) if st.name in files else st
                                         for st in scene.streams))
    fused = None if scene.fusion is None else set(scene.fusion.streams)
    if len(models) == 2 and fused != set(models):
        scene = with_fusion(scene, streams=list(models))
    return scene


def with_fusion(scene: Scene, **table: Any) -> Scene:
    """Return ``scene`` with the ``[fusion]`` ``table`` gives, validated against the scene's streams.

    ``table``'s keys are as a scene file's, the others at their defaults; it is validated as a file's would be.

    Raises
    ------
    SceneError
        For a key or value the ``[fusion]`` table refuses (a stream the scene has not, or one without
        a model, ...).
    """
    return replace(scene, fusion=fusion_from_table(table, scene.source, scene.streams))


def with_absolute_paths(scene: Scene) -> Scene:
    """Return ``scene`` with every file it names relative to its folder made absolute (symbolic links resolved).

    These are the keys marked ``path`` of its sources' drivers and of its sinks (but for the words such a key
    takes, ``"-"`` or ``"reference"``), its banks' files, its models' and its early fusion's. A scene written
    into another folder then names the same files.
    """
    def absolute(value: str | None) -> str | None:
        return value if value is None else str(scene.resolve(value).resolve())

    def options(values: Options, keys: Mapping[str, Key]) -> Options:
        return frozen({k: absolute(v) if k in keys and keys[k].path and isinstance(v, str)
                       and v not in keys[k].words else v for k, v in values.items()})

    sources = tuple(replace(src, options=options(src.options, driver_spec(src.type).keys)) for src in scene.sources)
    streams = tuple(replace(st, bank=replace(st.bank, file=absolute(st.bank.file)),
                            model=replace(st.model, path=absolute(st.model.path)))
                    for st in scene.streams)
    sinks = tuple(replace(sink, options=options(sink.options, sink_keys(sink_spec(sink.type))))
                  for sink in scene.sinks)
    fusion = scene.fusion
    if fusion is not None and fusion.model is not None:
        fusion = replace(fusion, model=absolute(fusion.model))
    return replace(scene, sources=sources, streams=streams, sinks=sinks, fusion=fusion)


def relocated(scene: Scene, path: str | Path, base_dir: str | Path | None = None) -> Scene:
    """Return ``scene`` as the file ``path``: messages name it; its relative paths resolve against ``base_dir``.

    ``base_dir`` is by default ``path``'s folder. Its paths are not changed: see :func:`with_absolute_paths`.
    """
    old, new = scene.source, str(path)

    def where(text: str) -> str:
        return new + text[len(old):] if text.startswith(old) else text

    return replace(scene, source=new, base_dir=Path(path).resolve().parent if base_dir is None else Path(base_dir),
                   sources=tuple(replace(src, where=where(src.where)) for src in scene.sources),
                   streams=tuple(replace(st, where=where(st.where)) for st in scene.streams))


def as_replay(scene: Scene, sessions: Mapping[str, str]) -> Scene:
    """Return ``scene`` with each source a replay of its recorded session, at its recorded times.

    ``sessions``: ``{source: session path}``, every source named. The times: ``timing = "recorded"``,
    ``speed = "max"``, in step with the others; its ring waits rather than drops (``overrun = "auto"``: a
    file need lose nothing). The streams read the sessions with their mappings, as recorded.
    """
    missing = sorted({src.name for src in scene.sources} - set(sessions))
    if missing:
        raise InputError(f"{scene.source}: no session given for source(s) {missing}")
    sources = []
    for src in scene.sources:
        table = {"type": "replay", "path": str(sessions[src.name]), "timing": "recorded", "speed": "max"}
        kind, options = driver_table(src.where, table)
        sources.append(replace(src, type=kind, options=frozen(options), buffer=replace(src.buffer, overrun="auto")))
    return replace(scene, sources=tuple(sources))
