"""Feature windows computed once per bank and recording, for every window length and feature set.

A fit scores hundreds of settings that share banks: the filterbank and the peak extractor, the
costly stages, depend on the bank and the recording alone. A window's A, f and Af are sums over
the peaks *detected* in it (:mod:`supramodal.features`; a peak's instantaneous frequency comes from
its channel's previous peak, wherever that lies), so the features of a window of ``m * B`` samples
are exactly the sums of ``m`` consecutive windows of ``B`` samples. :class:`FeatureCache` keeps,
per bank and manifest line, the three features over *base windows* of ``B`` samples, ``B`` the
greatest common divisor of the search's window lengths at the bank's rate (:func:`base_samples`),
and sums them into any
window and selects any features on demand: one filterbank run per bank and recording for the
whole search (every fold, window and feature set).

The cache is bounded in memory (least recently used banks leave first); with a folder, every bank
is also kept on disk in parts of :data:`PART` recordings, two ``.npy`` files each (written and read
by numpy without pickle, atomically), and read back when asked for again. Processes of one machine
share the folder: a part one worker computed is read by the others instead of computed again, and
the parts of one bank can be computed by several workers at once (:meth:`FeatureCache.fill`).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import warnings
from collections import OrderedDict
from pathlib import Path

import numpy as np

from supramodal.banks import Bank
from supramodal.errors import InputError
from supramodal.features import FEATURES, check_features
from supramodal.node.scene.band import BandWarning
from supramodal.node.workflows.manifest import Recording
from supramodal.node.workflows.training import recording_windows
from supramodal.pipeline import FeaturePipeline, window_length

__all__ = ["DEFAULT_MEMORY_BYTES", "PART", "FeatureCache", "base_samples"]

#: In-memory bound of one process's cache, bytes (a 50-channel bank over 600 recordings of 5 s in
#: 50 ms base windows takes 36 MB).
DEFAULT_MEMORY_BYTES = 512 * 2**20
#: Recordings per part of a bank on disk (the unit a worker filters at once).
PART = 40


def base_samples(windows, fs: float) -> tuple[int, ...]:
    """Return the base windows, samples, for ``windows`` (seconds) at ``fs`` Hz.

    Their greatest common divisor where it is at least an eighth of the shortest (and 2 samples); else
    (lengths rounded to whole samples that share no useful divisor, 1102 and 2205 samples at 44.1 kHz) each
    window takes the first base that divides it, or becomes a base itself.

    Parameters
    ----------
    windows : sequence of float
        Window lengths, seconds.
    fs : float
        The bank's rate, Hz.

    Returns
    -------
    tuple of int
        The bases, shortest first; every window is a whole number of one of them.
    """
    lengths = sorted({window_length(w, fs) for w in windows})
    common = math.gcd(*lengths)
    if common >= max(2, lengths[0] // 8):
        return (common,)
    bases: list[int] = []
    for n in lengths:
        if not any(n % b == 0 for b in bases):
            bases.append(n)
    return tuple(bases)


class FeatureCache:
    """Feature windows of a manifest's recordings per bank, computed once (module docstring).

    Parameters
    ----------
    recs : list of Recording
        The manifest's lines, in order.
    windows : sequence of float
        Every window length the search may ask for, seconds (they fix the base window).
    mapping : str or int
        Recording channels to filters (:func:`node.runtime.streams.channel_mapper`).
    memory_bytes : int
        Most bytes of feature windows held in memory.
    folder : path-like or None
        Where banks that leave memory are kept (created when first needed); None: forgotten.

    Attributes
    ----------
    filterbank_runs : int
        Recordings run through a filterbank by this object (what the cache saves is what this
        does not count).
    disk_reads : int
        Banks read back from ``folder``.
    """

    def __init__(self, recs: list[Recording], windows, mapping="auto", memory_bytes: int = DEFAULT_MEMORY_BYTES,
                 folder=None) -> None:
        if not recs:
            raise InputError("a feature cache needs at least one recording")
        self.recs = list(recs)
        self.windows = tuple(float(w) for w in windows)
        self.mapping = mapping
        self.memory_bytes = int(memory_bytes)
        self.folder = None if folder is None else Path(folder)
        self._held: OrderedDict[str, tuple[list[np.ndarray], int]] = OrderedDict()
        self._bytes = 0
        self.filterbank_runs = 0
        self.disk_reads = 0

    def features(self, bank: Bank, window: float, features) -> list[np.ndarray]:
        """Each recording's feature windows for ``bank``, ``window`` and ``features``.

        Parameters
        ----------
        bank : Bank
        window : float
            Seconds; rounded to whole samples at ``bank.fs`` as :class:`FeaturePipeline` rounds it.
        features : sequence of str

        Returns
        -------
        list of ndarray, each (windows, len(features), channels)
            What :func:`node.workflows.training.recording_windows` returns for a
            ``FeaturePipeline(bank, features, window)`` (equal up to the order of float sums).
        """
        features = check_features(features)
        W = window_length(window, bank.fs)
        # The longest base dividing the window (fewest sums); a window the search did not announce: its own.
        B = next((b for b in reversed(self._base_samples(bank)) if W % b == 0), W)
        base = self._base(bank, B)
        m = W // B
        pick = [FEATURES.index(f) for f in features]
        out = []
        for v in base:
            n = len(v) // m
            out.append(v[: n * m].reshape(n, m, len(FEATURES), bank.channels).sum(axis=1)[:, pick, :])
        return out

    @property
    def parts(self) -> int:
        """How many parts of :data:`PART` recordings a bank is kept in."""
        return -(-len(self.recs) // PART)

    def fill(self, bank: Bank, part: int) -> None:
        """Compute part ``part`` of ``bank`` into the folder (nothing if it is there already).

        So that the processes sharing the folder find it: what a worker does while others fill other parts.
        """
        for base in self._base_samples(bank):
            self._part(bank, base, part)

    def _base_samples(self, bank: Bank) -> tuple[int, ...]:
        return base_samples(self.windows, bank.fs)

    def _key(self, bank: Bank, base: int, part: int) -> str:
        recs = self.recs[part * PART: (part + 1) * PART]
        what = {"bank": bank.to_dict(), "base": base, "mapping": self.mapping,
                "recordings": [[str(r.path), r.start, r.end] for r in recs]}
        return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:32]

    def _base(self, bank: Bank, base: int) -> list[np.ndarray]:
        key = self._key(bank, base, -1)
        if key in self._held:
            self._held.move_to_end(key)
            return self._held[key][0]
        values = [v for part in range(self.parts) for v in self._part(bank, base, part)]
        self._hold(key, values)
        return values

    def _part(self, bank: Bank, base: int, part: int) -> list[np.ndarray]:
        key = self._key(bank, base, part)
        recs = self.recs[part * PART: (part + 1) * PART]
        values = self._read(key, bank.channels, len(recs))
        if values is None:
            values = []
            with warnings.catch_warnings():
                # The paper's banks may reach above the recordings' band: the fit's report says so once.
                warnings.simplefilter("ignore", BandWarning)
                for rec in recs:
                    values.append(recording_windows(rec, FeaturePipeline(bank, FEATURES, base / bank.fs),
                                                    self.mapping))
                    self.filterbank_runs += 1
            self._write(key, values)
        return values

    def _hold(self, key: str, values: list[np.ndarray]) -> None:
        size = sum(v.nbytes for v in values)
        self._held[key] = (values, size)
        self._bytes += size
        while self._bytes > self.memory_bytes and len(self._held) > 1:
            _, (_, gone) = self._held.popitem(last=False)
            self._bytes -= gone

    def _paths(self, key: str) -> tuple[Path, Path]:
        assert self.folder is not None
        return self.folder / f"{key}-values.npy", self.folder / f"{key}-ends.npy"

    def _write(self, key: str, values: list[np.ndarray]) -> None:
        """Keep a part on disk (atomically: a reader never sees half a file)."""
        if self.folder is None:
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        ends = np.cumsum([len(v) for v in values]).astype(np.int64)
        for path, array in zip(self._paths(key), (np.concatenate(values), ends)):
            tmp = path.with_name(f"{path.stem}.{os.getpid()}.{id(values)}.tmp.npy")
            np.save(tmp, array, allow_pickle=False)
            os.replace(tmp, path)

    def _read(self, key: str, channels: int, count: int) -> list[np.ndarray] | None:
        """Return a part kept on disk, or None (absent, or not what this cache wrote: then recomputed)."""
        if self.folder is None:
            return None
        values_path, ends_path = self._paths(key)
        try:
            ends = np.load(ends_path, allow_pickle=False)
            values = np.load(values_path, allow_pickle=False)
        except (OSError, ValueError):
            return None
        if (values.ndim != 3 or values.shape[1:] != (len(FEATURES), channels) or ends.shape != (count,)
                or ends.dtype.kind != "i" or (len(ends) and ends[-1] != len(values)) or np.any(np.diff(ends) < 0)):
            return None
        self.disk_reads += 1
        return np.split(values, ends[:-1])
