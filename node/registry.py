"""The kinds of driver a scene may name, by type: one line each.

Like pyserial's ``protocol_handler_packages``: :data:`DRIVER_MODULES` maps a type to the module
that defines its :class:`~supramodal.drivers.spec.DriverSpec` (as ``SPEC``, or the attribute
after a colon), imported only when a scene names the type, so that a scene without a microphone
never loads sounddevice's module and one without a serial port never loads pyserial. A driver
defined outside the package is added with :func:`register_driver`.

A new driver is therefore one module (the driver and its spec) plus one line here.
"""

from __future__ import annotations

import importlib

from supramodal.checks import Key
from supramodal.drivers.spec import DriverSpec
from supramodal.errors import InputError

__all__ = ["DRIVER_MODULES", "MAPPING", "driver_spec", "driver_types", "register_driver", "source_keys"]

#: Type -> ``"module"`` or ``"module:attribute"`` holding the driver's spec.
DRIVER_MODULES = {
    "replay": "supramodal.replay.driver",
    "synth": "supramodal.node.synth_sources:SYNTH",
    "twosense": "supramodal.node.synth_sources:TWOSENSE",
    "serial": "supramodal.drivers.serial_whisker",
    "microphone": "supramodal.drivers.microphone",
    "xdf": "supramodal.replay.xdf",
    "lsl": "supramodal.drivers.lsl",
}

_registered: dict[str, DriverSpec] = {}


def _mapping(v) -> bool:
    return v in ("auto", "mono", "per-channel", "mean") or (isinstance(v, int) and not isinstance(v, bool) and v >= 0)


#: How the streams read a source's channels into their bank's (``supramodal.node.streams.channel_mapper``):
#: a key of every source, whatever its driver.
MAPPING = Key(_mapping, '"auto", "mono", "per-channel", "mean" or a channel index', "auto")


def register_driver(spec: DriverSpec, replace: bool = False) -> DriverSpec:
    """Make ``spec`` a type scenes may name (a driver defined outside the package); returns it.

    Raises
    ------
    InputError
        If the type is taken (by a built-in driver or an earlier registration) and not ``replace``.
    """
    if not isinstance(spec, DriverSpec):
        raise InputError(f"register_driver takes a DriverSpec, got {type(spec).__name__}")
    if not replace and (spec.type in DRIVER_MODULES or spec.type in _registered):
        raise InputError(f"a driver of type {spec.type!r} exists already; pass replace=True to replace it")
    _registered[spec.type] = spec
    return spec


def driver_types() -> list[str]:
    """Every type a scene may name, sorted."""
    return sorted({*DRIVER_MODULES, *_registered})


def driver_spec(kind) -> DriverSpec:
    """The spec of driver type ``kind``.

    Raises
    ------
    InputError
        For a type no driver has, listing those there are.
    """
    if isinstance(kind, str) and kind in _registered:
        return _registered[kind]
    where = DRIVER_MODULES.get(kind) if isinstance(kind, str) else None
    if where is None:
        raise InputError(f"expected one of {driver_types()}, got {kind!r}")
    module, _, attribute = where.partition(":")
    spec = getattr(importlib.import_module(module), attribute or "SPEC")
    if spec.type != kind:
        raise InputError(f"{where} defines driver type {spec.type!r}, not {kind!r}")
    return spec


def source_keys(spec: DriverSpec) -> dict[str, Key]:
    """A source's keys in a scene: its driver's, and how streams read it (``mapping``)."""
    return {**spec.keys, "mapping": MAPPING}
