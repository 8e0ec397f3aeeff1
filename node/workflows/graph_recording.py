"""Recording a graph of several sources, and the scene that replays the recording.

Each source is recorded as a session of its own, ``NAME.SOURCE.wav`` + ``.json``, whose sidecar
also keeps every block's end frame and the time it was complete on the graph's common time
(``arrivals``). Beside them go the streams' models (``NAME.STREAM.npz``, and ``NAME.fused.npz`` for
early fusion: a model trained on the spot is kept, so the replay decides with the same one) and
``NAME.toml``: the same graph with each source a replay of its session at its recorded timing
(``timing = "recorded"``) and the
fusion weight the recording used. ``supramodal run NAME.toml --speed max`` then puts the
sources on common time as the live run did, drift and jitter included, and pairs and fuses the
same windows (all of them when nothing was decided alone live: a replay is a file, whose fusion waits
for both streams without a deadline).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from supramodal.errors import InputError
from supramodal.node.runtime.outputs import check_new_file
from supramodal.node.runtime.taps.recorder import SessionRecorder
from supramodal.node.scene.schema import Scene, scene_to_toml
from supramodal.node.scene.specs import ModelSpec
from supramodal.node.scene.variants import as_replay, relocated, with_absolute_paths
from supramodal.replay.session import session_paths


def recording_paths(folder, name: str, scene: Scene) -> dict:
    """Return what recording ``scene`` as ``name`` writes into ``folder`` besides the sessions.

    ``{"models": {stream: path}, "fused": path or None, "scene": path}``.
    """
    folder = Path(folder)
    early = scene.fusion is not None and scene.fusion.method == "early"
    return {"models": {spec.name: folder / f"{name}.{spec.name}.npz" for spec in scene.streams if spec.model.exists},
            "fused": folder / f"{name}.fused.npz" if early else None,
            "scene": folder / f"{name}.toml"}


def _files(paths: dict) -> list[Path]:
    return [*paths["models"].values(), *([paths["fused"]] if paths["fused"] else []), paths["scene"]]


def graph_recorders(scene: Scene, folder, name: str, overwrite: bool = False, label: str | None = None,
                    replace: bool = False, into=None) -> dict[str, SessionRecorder]:
    """Return one recorder per source of a graph scene, keeping the blocks' arrivals.

    Every file the recording would write is checked first (refused if it exists, unless ``overwrite``).

    ``label`` labels every source's whole recording; ``replace``: the labels given here and by
    :class:`GraphMarks` replace those a source's driver carries (a synthesised source's truth). ``into``: the
    folder the sessions are written into instead of ``folder``, whose files the caller puts in place (``supramodal
    record``: all of them once the replay scene is written there too, or none).
    """
    if Path(folder).is_dir():                       # else made at the first frames: nothing to replace
        sessions = [p for src in scene.sources for p in session_paths(Path(folder) / f"{name}.{src.name}")]
        for path in _files(recording_paths(folder, name, scene)) + (sessions if into is not None else []):
            check_new_file(path, overwrite, "the recording's file")
    return {src.name: SessionRecorder(folder if into is None else into, f"{name}.{src.name}",
                                      json.dumps({"scene": scene.source,
                                                  "source": {**src.table(), "buffer": dataclasses.asdict(src.buffer)}}),
                                      label=label, overwrite=overwrite, keep_arrivals=True, replace=replace)
            for src in scene.sources}


class GraphMarks:
    """Labels typed while a graph records, on the node's common time, for every source at once.

    A label starts at the common time of the newest sample any source has delivered (for live
    sources, the moment it is typed, less a block's delivery); each source's recorder maps it to
    its own frames through its clock when it writes its session
    (:meth:`~supramodal.node.runtime.taps.recorder.SessionRecorder.mark_at`). Thread-safe: :meth:`mark` may be
    called from a thread reading a terminal.

    Parameters
    ----------
    recorders : dict of str to SessionRecorder
        The graph's recorders (:func:`graph_recorders`), started by the graph.
    """

    def __init__(self, recorders: dict[str, SessionRecorder]) -> None:
        self.recorders = dict(recorders)

    def now(self) -> float:
        """Seconds of common time a label typed now starts at (0 before any sample)."""
        return max([0.0, *(r.newest_time() for r in self.recorders.values())])

    def mark(self, label: str | None) -> float:
        """Start ``label`` now on every source (``None``: end the current one); returns its time, s."""
        t = self.now()
        for recorder in self.recorders.values():
            recorder.mark_at(t, label)
        return t


def write_replay_scene(scene: Scene, graph, folder, name: str, overwrite: bool = False, into=None) -> Path:
    """Save the streams' models and write ``NAME.toml``, the scene that replays the recording; return its path.

    Called after ``graph`` (built from ``scene``) has recorded into ``folder``. ``into``: the folder the
    sessions were recorded into and these files are written into, to be put in ``folder`` by the caller
    (:func:`graph_recorders`); the scene names ``folder`` as its place.
    """
    folder = Path(folder)
    into = folder if into is None else Path(into)
    paths = recording_paths(into, name, scene)
    missing = [src.name for src in scene.sources if not (into / f"{name}.{src.name}.wav").exists()]
    if missing:
        raise InputError(f"no session was recorded for source(s) {missing} (no frame came): the recording "
                         "cannot be replayed in step, so no replay scene is written")
    # its files absolute (a bank file, a texture set): the replay scene is written into the recording's folder
    replay = as_replay(with_absolute_paths(scene), {src.name: f"{name}.{src.name}.wav" for src in scene.sources})
    streams = []
    for spec, stream in zip(replay.streams, graph.streams):
        if stream.model is not None and spec.name in paths["models"]:
            stream.model.save(paths["models"][spec.name])
            spec = dataclasses.replace(spec, model=ModelSpec(path=paths["models"][spec.name].name))
        streams.append(spec)
    fusion = replay.fusion
    if fusion is not None and graph.fusion.method == "early":
        graph.fusion.model.save(paths["fused"])           # a network trained on the spot, as trained
        fusion = dataclasses.replace(fusion, model=paths["fused"].name)
    elif fusion is not None:                               # the weights learned, as they were learned
        fusion = dataclasses.replace(fusion, **{key: getattr(graph.fusion, key)
                                                for key in ("weight", "sharpness", "correlation")})
    # The replay's sinks are the default ones; a relay (no stream) sends its recording on again.
    sent = [sink for sink in scene.sinks if sink.type == "lsl-signal"] if not graph.streams else []
    replay = dataclasses.replace(replay, streams=tuple(streams) + replay.streams[len(streams):], fusion=fusion,
                                 sinks=tuple(dataclasses.replace(sink, index=i) for i, sink in enumerate(sent)))
    replay = relocated(replay, folder / paths["scene"].name, base_dir=into)
    check_new_file(paths["scene"], overwrite, "the replay scene")
    paths["scene"].write_text(f"# Replays the recording {name} with its recorded timing (supramodal record).\n"
                              + scene_to_toml(replay))
    return paths["scene"]
