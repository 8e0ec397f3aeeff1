"""What a scene needs to know of a kind of sink, in one object: :class:`SinkSpec`.

It is the sinks' counterpart of ``supramodal.drivers.spec``.

Each sink module (:mod:`supramodal.node.runtime.sinks.text`, ...; a tap a scene names too:
:mod:`supramodal.node.runtime.taps.lsl_signal`) defines its spec as the module attribute ``SPEC``:
the ``type`` a scene names it by, its keys (:class:`supramodal.checks.Key`), how to build it from
validated options, what it listens to (windows or a source's samples) and what must be built
before it. The registry (``supramodal.node.scene.registry``: ``SINK_MODULES``, ``register_sink``)
maps each type to the module holding its spec and imports that module only when a scene names the
type.

A spec's ``build`` never imports the scene: it is given a :class:`SinkContext` (the sink's table in
messages, the scene's folder, and what it needs of the streams, their plans or the sources, as
:class:`StreamPlan` and :class:`SourcePlan`) and returns the sink (or tap). It raises
``supramodal.drivers.spec.OptionError`` for an option that cannot be honoured (the node says which
table it was in).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from supramodal.checks import Key, is_name, text
from supramodal.drivers.spec import OptionError
from supramodal.node.runtime.fields import strs_of

if TYPE_CHECKING:   # the annotations' names only
    from supramodal.banks import Bank
    from supramodal.drivers.base import Driver
    from supramodal.node.runtime.streams import Stream
    from supramodal.pipeline import FeaturePipeline

__all__ = ["FROM", "NEEDS", "SOURCE", "OptionValue", "Options", "SinkContext", "SinkSpec", "SourcePlan", "StreamPlan",
           "listened", "option_from", "sink_keys", "stream_outputs"]

#: A scene option's value once its table's schema (:class:`supramodal.checks.Key`) has checked it: what TOML
#: gives but its dates and times (no key's check takes one), or a key's default (None for some). A build
#: reads each as its key's type with the checked readers of :mod:`supramodal.node.runtime.fields`.
OptionValue = None | bool | int | float | str | list["OptionValue"] | Mapping[str, "OptionValue"]
#: A sink's or source's options: its keys, validated, defaults filled in (read-only).
Options = Mapping[str, OptionValue]

#: What a sink may need built before it is made: nothing (it is made first, so that a file is
#: checked before any training), the streams' plans (their pipelines and classes, known before any
#: model is trained: a sink that must exist before the start-up work, such as an LSL outlet that
#: consumers resolve while the node trains), the streams (their banks, features and models), or the
#: sources.
NEEDS = ("nothing", "plans", "streams", "sources")


@dataclass(frozen=True)
class StreamPlan:
    """A stream as it is known before its model is trained or loaded into the graph.

    Attributes
    ----------
    pipeline : supramodal.pipeline.FeaturePipeline
        Its bank, features and window.
    classes : tuple of str
        The classes its model decides among, in the model's order (empty without a model).
    """

    pipeline: FeaturePipeline
    classes: tuple[str, ...]


@dataclass(frozen=True)
class SourcePlan:
    """A source as a sink of its samples sees it (built, before the run).

    Attributes
    ----------
    driver : supramodal.drivers.base.Driver
        Its driver, built (its ``rate`` and ``channels``).
    type : str
        Its driver type (the scene's ``[[source]] type``).
    options : mapping
        Its driver's keys, validated, defaults filled in (read-only).
    signal_type : str or None
        What its samples are as an LSL content type, as its driver's spec says
        (``supramodal.drivers.spec.DriverSpec.signal_type``); None where the spec does not say.
    read_by : tuple of (Bank, mapping)
        The bank and the ``mapping`` of each stream that reads it, in the scene's order (empty for a
        source only sent on: a relay's).
    """

    driver: Driver
    type: str
    options: Options
    signal_type: str | None = None
    read_by: tuple[tuple[Bank, str | int], ...] = ()


@dataclass(frozen=True)
class SinkContext:
    """What a sink spec's ``build`` may use besides its options.

    Attributes
    ----------
    where : str
        The sink's table in messages (``"s.toml: [[sink]] #2"``).
    resolve : callable
        ``resolve(path) -> Path``, relative to the scene file's folder.
    overwrite : bool
        Whether a file sink may replace an existing file (``run --force``).
    streams : dict
        Stream name -> the built ``node.runtime.streams.Stream`` (its pipeline and model), for sinks that
        need the streams; ``"fused"`` is not among them.
    fused_classes : tuple of str or None
        The fusion's classes, when the scene has one.
    fused_inputs : tuple of str
        The streams the fusion takes (empty: no fusion).
    plans : dict
        Stream name -> its :class:`StreamPlan`, for sinks that need the plans (made before any
        model is trained); ``"fused"`` is not among them.
    sources : dict
        Source name -> its :class:`SourcePlan` (its driver, driver type and options, and the streams
        that read it), for sinks that need the sources.
    stream_names : tuple of str
        The names of the streams whose windows the sink will receive (``Scene.window_names``): known to
        every sink, whatever it needs (a page lays out its panels in that order, not in the order the
        first windows happen to arrive).
    """

    where: str
    resolve: Callable[[str], Path] = Path
    overwrite: bool = False
    streams: Mapping[str, Stream] = field(default_factory=dict)
    fused_classes: tuple[str, ...] | None = None
    fused_inputs: tuple[str, ...] = ()
    sources: Mapping[str, SourcePlan] = field(default_factory=dict)
    plans: Mapping[str, StreamPlan] = field(default_factory=dict)
    stream_names: tuple[str, ...] = ()


@dataclass(frozen=True)
class SinkSpec:
    """A kind of sink as a scene sees it.

    Attributes
    ----------
    type : str
        The name a scene gives it (``[[sink]] type``).
    keys : mapping of str to Key
        Its keys besides ``type`` and ``from`` (what it listens to: added for a sink of windows)
        or ``source`` (added for a sink of samples).
    build : callable
        ``build(options, context) -> Sink`` (or a ``node.runtime.taps.Tap`` for a sink of samples),
        ``options`` validated (a read-only mapping); raises ``drivers.spec.OptionError`` naming the key.
    summary : str
        One line for the docs.
    listens : {"windows", "samples"}
        A sink of the streams' window events (routed by ``from``), or of a source's samples (a tap
        on the ring of ``source``).
    needs : {"nothing", "plans", "streams", "sources"}
        What must be built before it (:data:`NEEDS`).
    unique : tuple of str
        Keys whose values two sinks of this type may not share (one outlet name for two outlets).
    """

    type: str
    keys: Mapping[str, Key]
    # A Sink, or a Tap for a sink of samples: ``object`` to this module, which the sinks' package imports (an
    # import of either here, even for the type checker only, would close a cycle; tests/test_layers.py).
    build: Callable[[Options, SinkContext], object]
    summary: str
    listens: str = "windows"
    needs: str = "nothing"
    unique: tuple[str, ...] = ()


#: ``from``: the streams a sink of windows listens to.
FROM = Key(lambda v: text(v) or isinstance(v, list) and bool(v) and all(text(x) for x in v),
           'a stream name or a list of them ("fused": the fusion block\'s decisions; default: every stream)', None)
#: ``source``: the source whose samples a sink of samples sends.
SOURCE = Key(is_name, "the name of the [[source]] whose samples it sends (default: the scene's only source)", None)


def listened(listens: str | list[str] | None, streams: Collection[str]) -> list[str]:
    """Return the streams a sink of windows listens to: its ``from``, each checked to be among ``streams``.

    ``from`` None: every one of ``streams``, in their order. ``streams`` has ``"fused"`` where the scene
    has a fusion.

    Raises
    ------
    OptionError
        Naming ``from``, the streams that are not there and those that are.
    """
    names = list(streams) if listens is None else [listens] if isinstance(listens, str) else list(listens)
    unknown = [n for n in names if n not in streams]
    if unknown:
        raise OptionError(f"from: no stream {unknown}; the scene has {list(streams)}")
    return names


def stream_outputs(outputs: Sequence[str], has_features: bool, has_classes: bool) -> list[str]:
    """Return, of a sink's ``outputs``, those one stream has.

    ``"features"`` where it has feature columns, the others (its decisions, its posteriors) where it has a
    model's classes: a stream without a model has only the features, the fusion only the others.
    """
    return [o for o in outputs if (has_features if o == "features" else has_classes)]


def sink_keys(spec: SinkSpec) -> dict[str, Key]:
    """Return a sink's keys in a scene: its own, and what it listens to (``from`` or ``source``)."""
    return {**spec.keys, **({"source": SOURCE} if spec.listens == "samples" else {"from": FROM})}


def option_from(options: Options) -> str | list[str] | None:
    """Return a sink of windows' ``from`` (:data:`FROM`): a stream name, a list of them, or None (every stream)."""
    value = options["from"]
    return value if value is None or isinstance(value, str) else strs_of(options, "from")
