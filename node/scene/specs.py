"""A scene's parts as typed, frozen values: what :mod:`~supramodal.node.scene.schema` makes of a scene file.

They are all that the builder, the command line and the workflows read of it.

Every value here has been validated (the schema's key tables say what each key accepts and its
default); nothing is changed after loading: a variant of a scene is made with
:func:`dataclasses.replace`. A driver's and a sink's own keys stay a read-only mapping
(:data:`Options`): only their spec, in the module that defines the driver or the sink, reads them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

from supramodal.bankfile import BANK_KEYS
from supramodal.decisions import DEFAULT_DECISION, DecisionRules
from supramodal.errors import InputError
from supramodal.model import DEFAULT_AUGMENT_SPREAD, GainAugment
from supramodal.node.runtime.sinks.spec import Options as RuntimeOptions
from supramodal.node.runtime.sinks.spec import OptionValue


class SceneError(InputError):
    """A scene file is unreadable or does not fit the schema; the message names the key."""

#: A driver's or a sink's validated keys (defaults filled in), read-only: what a sink's build takes.
Options = RuntimeOptions


def frozen(values: Mapping[str, OptionValue]) -> Options:
    """Return a read-only copy of ``values``."""
    return MappingProxyType(dict(values))


EMPTY: Options = frozen({})


@dataclass(frozen=True)
class BufferSpec:
    """A source's ring (``[buffer]``, or ``[source.buffer]`` in the graph form).

    Attributes
    ----------
    seconds : float
        Capacity, seconds of the source.
    overrun : {"auto", "drop-oldest", "drop-newest", "block"}
        What a full ring does; "auto" is the driver's policy.
    """

    seconds: float
    overrun: str


@dataclass(frozen=True)
class BankSpec:
    """A stream's bank (``[bank]``): a bank file, or a kind's recipe with the keys the scene sets.

    Attributes
    ----------
    kind : {"whisker", "cochlea"}
    file : str or None
        A bank file (relative to the scene's folder); it describes the whole bank.
    recipe : mapping
        The recipe keys of ``kind`` (``supramodal.bankfile.BANK_KEYS``) the scene sets; a key left
        out, or None, takes the bank's own default.
    """

    kind: str
    file: str | None = None
    recipe: Options = field(default_factory=lambda: EMPTY)

    def table(self) -> dict[str, object]:
        """Return the ``[bank]`` table as a scene file writes it.

        The file alone, or the kind and the keys of its recipe that are set (only those the kind has,
        whatever a spec made in code holds, so that the file loads back).
        """
        if self.file is not None:
            return {"file": self.file}
        keys = BANK_KEYS[self.kind]
        return {"kind": self.kind, **{k: v for k, v in self.recipe.items() if k in keys and v is not None}}


@dataclass(frozen=True)
class FeaturesSpec:
    """A stream's features and window (``[features]``; each key's meaning is the schema's)."""

    names: tuple[str, ...]
    window: float
    peak_mode: str
    peak_threshold: float
    dtype: str
    chunk: float
    nonfinite: str


@dataclass(frozen=True)
class ModelSpec:
    """A stream's model (``[model]``).

    Attributes
    ----------
    path : str or None
        A model file: loaded, or written when trained on start.
    train_on_start : bool
        Train at start-up (on the synthesised texture set, or the bank's reference set).
    augment_copies, augment_spread, augment_gains
        The gain augmentation of a model trained at start-up (0 copies: none; :meth:`gain_augment`).
    """

    path: str | None = None
    train_on_start: bool = False
    augment_copies: int = 0
    augment_spread: float = DEFAULT_AUGMENT_SPREAD
    augment_gains: str = "auto"

    def gain_augment(self) -> GainAugment | None:
        """Return the :class:`supramodal.model.GainAugment` of a model trained at start-up, or None without one.

        Gains ``"auto"``: by the bank.
        """
        if not self.augment_copies:
            return None
        per_channel = {"auto": None, "per-channel": True, "shared": False}[self.augment_gains]
        return GainAugment(self.augment_copies, float(self.augment_spread), per_channel)

    @property
    def exists(self) -> bool:
        """Whether the stream has a model (a file or one trained on start)."""
        return self.train_on_start or self.path is not None


@dataclass(frozen=True)
class SourceSpec:
    """One source: a driver and its ring (``[[source]]``, or a one-source scene's ``[driver]``).

    Attributes
    ----------
    name : str
        ``"main"`` in a one-source scene.
    type : str
        The driver type (a registry entry).
    options : mapping
        The driver's keys, validated by its spec, defaults filled in (None: the driver's default).
    buffer : BufferSpec
    where : str
        How messages name its table (``"s.toml: [[source]] board"``).
    """

    name: str
    type: str
    options: Options
    buffer: BufferSpec
    where: str = "<scene>"

    def table(self) -> dict[str, object]:
        """Return the ``[[source]]`` table as a scene file writes it (without its ``[source.buffer]``)."""
        return {"name": self.name, "type": self.type, **self.options}


@dataclass(frozen=True)
class StreamSpec:
    """One stream: a source read through a bank, features, a model and a decision (``[[stream]]``).

    Attributes
    ----------
    name, source : str
        Its name and its source's.
    mapping : str or int
        How it reads its source's channels into its bank's (``node.runtime.streams.channel_mapper``).
    bank, features, model, decision
        Its sections.
    contact_from : str or None
        ``[decision] contact_from``: the robot's contact signal (``supramodal.drivers.contact``), or None
        (the input's RMS, ``[decision] contact_threshold``).
    where : str
        How messages name it (the scene file for a one-source scene, else ``"FILE: [[stream]] NAME"``).
    """

    name: str
    source: str
    mapping: str | int
    bank: BankSpec
    features: FeaturesSpec
    model: ModelSpec
    decision: DecisionRules = DEFAULT_DECISION
    where: str = "<scene>"
    contact_from: str | None = None


@dataclass(frozen=True)
class FusionSpec:
    """Two streams' decisions fused (``[fusion]``; each key's meaning is the schema's).

    ``weight`` is a number, or ``"learn"`` (with ``sharpness`` and ``correlation`` then learned too).
    """

    streams: tuple[str, str]
    method: str
    model: str | None
    weight: float | str
    max_wait: float
    sharpness: float
    correlation: float
    decision: DecisionRules = DEFAULT_DECISION
    contact_from: str | None = None


@dataclass(frozen=True)
class SinkSettings:
    """One ``[[sink]]``.

    Attributes
    ----------
    type : str
        The sink type (a registry entry).
    options : mapping
        Its keys, validated by its spec, defaults filled in; with ``from`` (a sink of windows) or
        ``source`` (a sink of samples).
    index : int
        Its place among the scene's sinks, from 0 (messages say ``[[sink]] #index+1``).
    """

    type: str
    options: Options
    index: int = 0

    @property
    def routes(self) -> frozenset[str] | None:
        """The streams a sink of windows listens to (None: every one)."""
        listens = self.options.get("from")
        if listens is None:
            return None
        if isinstance(listens, str):
            return frozenset((listens,))
        assert isinstance(listens, (list, tuple)), "the schema's FROM key: a name or a list of names"
        return frozenset(str(name) for name in listens)

    @property
    def source(self) -> str | None:
        """The source whose samples a sink of samples sends (None for a sink of windows)."""
        name = self.options.get("source")
        return name if isinstance(name, str) else None


#: How a scene was written: ``[driver]``, ``[bank]``, ... (one source read by one stream, both named
#: ``"main"``), or ``[[source]]`` and ``[[stream]]``. It is read the same way; only
#: :func:`~supramodal.node.scene.schema.scene_to_toml` writes it back in its own form.
FORMS = ("one-source", "graph")


@dataclass(frozen=True)
class Scene:
    """A validated scene, every default filled in: sources, streams, an optional fusion, sinks.

    A one-source scene (``[driver]``, ``[bank]``, ...) is loaded as one source and one stream, both
    named ``"main"``: :meth:`only_stream` and :meth:`only_source` read them.

    Attributes
    ----------
    sources : tuple of SourceSpec
    streams : tuple of StreamSpec
    sinks : tuple of SinkSettings
    fusion : FusionSpec or None
    source : str
        The scene file (messages name it).
    base_dir : Path
        The scene file's folder: its paths resolve against it.
    form : {"one-source", "graph"}
        How the file was written (:data:`FORMS`).
    """

    sources: tuple[SourceSpec, ...]
    streams: tuple[StreamSpec, ...]
    sinks: tuple[SinkSettings, ...] = ()
    fusion: FusionSpec | None = None
    source: str = "<scene>"
    base_dir: Path = field(default_factory=Path.cwd)
    form: str = "graph"

    @property
    def is_graph(self) -> bool:
        """Whether the scene is written in the graph form ([[source]], [[stream]])."""
        return self.form == "graph"

    @property
    def window_names(self) -> tuple[str, ...]:
        """The names the scene's windows carry, in its order: its streams, then ``"fused"`` when it fuses."""
        return tuple(st.name for st in self.streams) + (("fused",) if self.fusion is not None else ())

    def only_stream(self) -> StreamSpec:
        """Return the only stream of a one-source scene."""
        self._one_source()
        return self.streams[0]

    def only_source(self) -> SourceSpec:
        """Return the only source of a one-source scene (its ``[driver]`` and ``[buffer]``)."""
        self._one_source()
        return self.sources[0]

    def _one_source(self) -> None:
        if self.is_graph:
            raise SceneError(f"{self.source}: a scene in the graph form has no single [driver], [bank], ...: read "
                             "each stream's (scene.streams) and source's (scene.sources)")

    def source_named(self, name: str) -> SourceSpec:
        """Return the source called ``name``."""
        return next(s for s in self.sources if s.name == name)

    def stream_named(self, name: str) -> StreamSpec:
        """Return the stream called ``name``."""
        return next(s for s in self.streams if s.name == name)

    def resolve(self, path: str) -> Path:
        """Return a path from the scene, taken relative to the scene file's folder."""
        p = Path(path).expanduser()
        return p if p.is_absolute() else self.base_dir / p

    def source_table(self, name: str) -> str:
        """How the scene file names source ``name`` in messages."""
        return f"{self.source}: [driver]" if not self.is_graph else f"{self.source}: [[source]] {name}"

    def buffer_table(self, name: str) -> str:
        """How the scene file names source ``name``'s ring in messages."""
        return f"{self.source}: [buffer]" if not self.is_graph else f"{self.source}: [[source]] {name} [source.buffer]"
