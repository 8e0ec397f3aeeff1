"""The kinds of driver and of sink a scene may name, by type: one line each.

Like pyserial's ``protocol_handler_packages``: :data:`DRIVER_MODULES` maps a type to the module
that defines its :class:`~supramodal.drivers.spec.DriverSpec` (as ``SPEC``, or the attribute
after a colon), imported only when a scene names the type, so that a scene without a microphone
never loads sounddevice's module and one without a serial port never loads pyserial. A driver
defined outside the package is added with :func:`register_driver`.

A new driver is therefore one module (the driver and its spec) plus one line here. Sinks are
registered the same way (:data:`SINK_MODULES`, :func:`register_sink`); a sink's spec,
:class:`~supramodal.node.runtime.sinks.spec.SinkSpec`, lives beside the sinks in
``supramodal.node.runtime.sinks.spec``, as a driver's does beside the drivers.
"""

from __future__ import annotations

import importlib
from typing import Generic, Protocol, TypeVar

from supramodal.checks import Key
from supramodal.drivers.spec import DriverSpec
from supramodal.errors import InputError

# A sink's spec lives beside the sinks (the runtime), as a driver's beside the drivers; its names are
# re-exported here for code written against this module (the package imports them from there).
from supramodal.node.runtime.sinks.spec import (
    FROM,
    NEEDS,
    SOURCE,
    SinkContext,
    SinkSpec,
    SourcePlan,
    StreamPlan,
    sink_keys,
)

__all__ = ["DRIVER_MODULES", "FROM", "NEEDS", "SINK_MODULES", "SOURCE", "Registry", "SinkContext", "SinkSpec",
           "SourcePlan", "StreamPlan", "driver_spec", "driver_types", "register_driver", "register_sink", "sink_keys",
           "sink_spec", "sink_types", "source_keys"]

#: Type -> ``"module"`` or ``"module:attribute"`` holding the driver's spec.
DRIVER_MODULES = {
    "replay": "supramodal.replay.driver",
    "synth": "supramodal.node.scene.synth_sources:SYNTH",
    "twosense": "supramodal.node.scene.synth_sources:TWOSENSE",
    "serial": "supramodal.drivers.serial_whisker",
    "microphone": "supramodal.drivers.microphone",
    "xdf": "supramodal.replay.xdf",
    "lsl": "supramodal.drivers.lsl",
    "ros2": "supramodal.drivers.ros2",
}


class _Typed(Protocol):
    """A spec: what it has of its own type name (DriverSpec, SinkSpec)."""

    @property
    def type(self) -> str: ...


SpecT = TypeVar("SpecT", bound=_Typed)


class Registry(Generic[SpecT]):
    """Specs by type: built-in ones named by module (imported when first asked for), others registered at run time.

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
        """Register ``spec`` under its type, at run time, and return it.

        Raises
        ------
        InputError
            ``spec`` is not a :attr:`spec_type`, or its type exists already (built in or registered) and
            ``replace`` is False.
        """
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
        """Return every type, built in or registered, sorted."""
        return sorted({*self.modules, *self.registered})

    def spec(self, kind: object) -> SpecT:
        """Return the spec of type ``kind``: a registered one, else the built-in one, its module imported now.

        Raises
        ------
        InputError
            For a type there is no spec of (listing those there are), or a module whose spec has another type.
        """
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
    """Return the spec of driver type ``kind``.

    An :class:`InputError` for a type no driver has, listing those there are.
    """
    return DRIVERS.spec(kind)


def source_keys(spec: DriverSpec) -> dict[str, Key]:
    """Return a source's keys in a scene: its driver's (how a stream reads it, ``mapping``, is the stream's)."""
    return dict(spec.keys)


# -- sinks ---------------------------------------------------------------------------------------------

#: Type -> the module holding the sink's spec (``SPEC``, or the attribute after a colon).
SINK_MODULES = {
    "text": "supramodal.node.runtime.sinks.text",
    "jsonl": "supramodal.node.runtime.sinks.jsonl",
    "lsl": "supramodal.node.runtime.sinks.lsl",
    "ros2": "supramodal.node.runtime.sinks.ros2",
    "lsl-signal": "supramodal.node.runtime.taps.lsl_signal",
    "view": "supramodal.node.runtime.sinks.view",
}
SINKS = Registry("sink", SINK_MODULES, SinkSpec)


def register_sink(spec: SinkSpec, replace: bool = False) -> SinkSpec:
    """Make ``spec`` a sink type scenes may name (a sink defined outside the package); returns it."""
    return SINKS.register(spec, replace)


def sink_types() -> list[str]:
    """Every sink type a scene may name, sorted."""
    return SINKS.types()


def sink_spec(kind: object) -> SinkSpec:
    """Return the spec of sink type ``kind``; an :class:`InputError` for a type no sink has."""
    return SINKS.spec(kind)

