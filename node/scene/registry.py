"""The kinds of driver and of sink a scene may name, by type: one line each.

Like pyserial's ``protocol_handler_packages``: :data:`DRIVER_MODULES` maps a type to the module
that defines its :class:`~supramodal.drivers.spec.DriverSpec` (as ``SPEC``, or the attribute
after a colon), imported only when a scene names the type, so that a scene without a microphone
never loads sounddevice's module and one without a serial port never loads pyserial. A driver
defined outside the package is added with :func:`register_driver`.

A new driver is therefore one module (the driver and its spec) plus one line here. Sinks are
registered the same way (:class:`SinkSpec`, :data:`SINK_MODULES`, :func:`register_sink`).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, Protocol, TypeVar

from supramodal.checks import Key, is_name, text
from supramodal.drivers.spec import DriverSpec
from supramodal.errors import InputError

__all__ = ["DRIVER_MODULES", "SINK_MODULES", "Registry", "SinkContext", "SinkSpec", "driver_spec",
           "driver_types", "register_driver", "register_sink", "sink_keys", "sink_spec", "sink_types", "source_keys"]

#: Type -> ``"module"`` or ``"module:attribute"`` holding the driver's spec.
DRIVER_MODULES = {
    "replay": "supramodal.replay.driver",
    "synth": "supramodal.node.scene.synth_sources:SYNTH",
    "twosense": "supramodal.node.scene.synth_sources:TWOSENSE",
    "serial": "supramodal.drivers.serial_whisker",
    "microphone": "supramodal.drivers.microphone",
    "xdf": "supramodal.replay.xdf",
    "lsl": "supramodal.drivers.lsl",
}


class _Typed(Protocol):
    """A spec: what it has of its own type name (DriverSpec, SinkSpec)."""

    @property
    def type(self) -> str: ...


SpecT = TypeVar("SpecT", bound=_Typed)


class Registry(Generic[SpecT]):
    """Specs by type: built-in ones named by module (imported when first asked for), others
    registered at run time.

    Parameters
    ----------
    what : str
        What the specs are, in messages ("driver", "sink").
    modules : dict of str to str
        Type -> ``"module"`` or ``"module:attribute"`` (default attribute ``SPEC``).
    spec_type : type
        The class every spec is an instance of.
    """

    def __init__(self, what: str, modules: dict[str, str], spec_type: type[SpecT]) -> None:
        self.what, self.modules, self.spec_type = what, modules, spec_type
        self.registered: dict[str, SpecT] = {}

    def register(self, spec: object, replace: bool = False) -> SpecT:
        if not isinstance(spec, self.spec_type):
            raise InputError(f"register_{self.what} takes a {self.spec_type.__name__}, got {type(spec).__name__}")
        if not replace and (spec.type in self.modules or spec.type in self.registered):
            raise InputError(f"a {self.what} of type {spec.type!r} exists already; pass replace=True to replace it")
        self.registered[spec.type] = spec
        return spec

    def unregister(self, kind: str) -> None:
        """Forget a type registered at run time (a built-in one stays)."""
        self.registered.pop(kind, None)

    def types(self) -> list[str]:
        return sorted({*self.modules, *self.registered})

    def spec(self, kind: object) -> SpecT:
        if isinstance(kind, str) and kind in self.registered:
            return self.registered[kind]
        where = self.modules.get(kind) if isinstance(kind, str) else None
        if where is None:
            raise InputError(f"expected one of {self.types()}, got {kind!r}")
        module, _, attribute = where.partition(":")
        spec: SpecT = getattr(importlib.import_module(module), attribute or "SPEC")
        if spec.type != kind:
            raise InputError(f"{where} defines {self.what} type {spec.type!r}, not {kind!r}")
        return spec


DRIVERS = Registry("driver", DRIVER_MODULES, DriverSpec)


def register_driver(spec: DriverSpec, replace: bool = False) -> DriverSpec:
    """Make ``spec`` a type scenes may name (a driver defined outside the package); returns it.

    Raises
    ------
    InputError
        If the type is taken (by a built-in driver or an earlier registration) and not ``replace``.
    """
    return DRIVERS.register(spec, replace)


def driver_types() -> list[str]:
    """Every driver type a scene may name, sorted."""
    return DRIVERS.types()


def driver_spec(kind: object) -> DriverSpec:
    """The spec of driver type ``kind``; an :class:`InputError` for a type no driver has, listing
    those there are."""
    return DRIVERS.spec(kind)


def source_keys(spec: DriverSpec) -> dict[str, Key]:
    """A source's keys in a scene: its driver's (how a stream reads it, ``mapping``, is the stream's)."""
    return dict(spec.keys)


# -- sinks ---------------------------------------------------------------------------------------------

#: Type -> the module holding the sink's spec (``SPEC``, or the attribute after a colon).
SINK_MODULES = {
    "text": "supramodal.node.runtime.sinks.text",
    "jsonl": "supramodal.node.runtime.sinks.jsonl",
    "lsl": "supramodal.node.runtime.sinks.lsl",
    "lsl-signal": "supramodal.node.runtime.taps.lsl_signal",
    "view": "supramodal.node.runtime.sinks.view",
}
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

    pipeline: Any
    classes: tuple[str, ...]


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
    plans : dict
        Stream name -> its :class:`StreamPlan`, for sinks that need the plans (made before any
        model is trained); ``"fused"`` is not among them.
    sources : dict
        Source name -> ``(driver, its node.scene.specs.SourceSpec, [(bank, mapping)] of the streams
        that read it)``, for sinks that need the sources.
    stream_names : tuple of str
        The names of the streams whose windows the sink will receive (``Scene.window_names``): known to
        every sink, whatever it needs (a page lays out its panels in that order, not in the order the
        first windows happen to arrive).
    """

    where: str
    resolve: Callable[[str], Path] = Path
    overwrite: bool = False
    streams: Mapping[str, Any] = field(default_factory=dict)
    fused_classes: tuple[str, ...] | None = None
    sources: Mapping[str, Any] = field(default_factory=dict)
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
    build: Callable[[Mapping[str, Any], SinkContext], Any]
    summary: str
    listens: str = "windows"
    needs: str = "nothing"
    unique: tuple[str, ...] = ()


SINKS = Registry("sink", SINK_MODULES, SinkSpec)

#: ``from``: the streams a sink of windows listens to.
FROM = Key(lambda v: text(v) or isinstance(v, list) and bool(v) and all(text(x) for x in v),
           'a stream name or a list of them ("fused": the fusion block\'s decisions; default: every stream)', None)
#: ``source``: the source whose samples a sink of samples sends.
SOURCE = Key(is_name, "the name of the [[source]] whose samples it sends (default: the scene's only source)", None)


def register_sink(spec: SinkSpec, replace: bool = False) -> SinkSpec:
    """Make ``spec`` a sink type scenes may name (a sink defined outside the package); returns it."""
    return SINKS.register(spec, replace)


def sink_types() -> list[str]:
    """Every sink type a scene may name, sorted."""
    return SINKS.types()


def sink_spec(kind: object) -> SinkSpec:
    """The spec of sink type ``kind``; an :class:`InputError` for a type no sink has."""
    return SINKS.spec(kind)


def sink_keys(spec: SinkSpec) -> dict[str, Key]:
    """A sink's keys in a scene: its own, and what it listens to (``from`` or ``source``)."""
    return {**spec.keys, **({"source": SOURCE} if spec.listens == "samples" else {"from": FROM})}
