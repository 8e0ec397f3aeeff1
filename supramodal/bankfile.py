"""A bank as data: one description that scenes, ``train`` and bank files share, and its file form.

A description is a JSON object (a TOML table in a scene) of one of two forms:

* **By recipe**: ``{"kind": "whisker", "rows": "ABCDE", "mean_B": 145, "fs": 5000}`` or
  ``{"kind": "cochlea", "channels": 30, "f_low": 20, "f_high": 1000, "fs": 2200}``: the paper's
  banks, or an ERB-spaced cochlea over any band at any rate (a sensor's native rate needs no
  resampling). Keys left out take the bank's own default.
* **Explicit**: ``{"kind": "custom", "fs": 2200, "cf": [...], "b": [...], "names": [...]}``: any
  channels (``names`` optional); what a fitted bank is saved as.

A bank file is ``{"format": "supramodal-bank", "version": 1, "bank": DESCRIPTION}``, read with
size and nesting bounds and validated like every other file a user may receive. Every bank is
checked by :class:`~supramodal.banks.Bank` (centre frequencies inside (0, fs/2), finite, at
least one channel, at most :data:`~supramodal.banks.MAX_CHANNELS`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from supramodal.banks import MAX_CHANNELS, MAX_RATE, Bank, cochlea_bank, whisker_bank
from supramodal.checks import Key, fill, integer, is_number, positive
from supramodal.errors import InputError
from supramodal.jsondata import read_json_file

__all__ = ["BankFileError", "BANK_FORMAT", "BANK_VERSION", "BANK_KEYS", "bank_from_description", "load_bank",
           "save_bank"]

BANK_FORMAT = "supramodal-bank"
BANK_VERSION = 1
#: Largest bank file, bytes (1024 channels of cf, b and a name take about 60 kB).
MAX_BANK_BYTES = 2**20
#: Deepest nesting of a bank file's JSON (the format nests 3 levels).
MAX_BANK_DEPTH = 8


class BankFileError(InputError):
    """A bank description or bank file does not fit; the message names the key and the fix."""


def _numbers(v):
    return isinstance(v, list) and 0 < len(v) <= MAX_CHANNELS and all(is_number(x) for x in v)


def _names(v):
    return isinstance(v, list) and all(isinstance(x, str) and x for x in v)


def _rows(v):
    return isinstance(v, str) and v != "" and set(v) <= set("ABCDE") and len(set(v)) == len(v)


#: Widest mean Slaney bandwidth of a whisker bank (its filters would ring for less than a sample).
MAX_MEAN_B = 10000.0
_FS = f"sample rate, Hz, > 0 and at most {MAX_RATE:g} (MAX_RATE)"
#: Per kind, the keys a description may hold (supramodal.checks: a default of None is the bank's own).
BANK_KEYS = {
    "whisker": {"rows": Key(_rows, 'whisker rows, e.g. "ABCDE"', None),
                "mean_B": Key(positive(MAX_MEAN_B), f"mean Slaney bandwidth 2 pi b, > 0 and at most {MAX_MEAN_B:g} "
                                                    "(Fig. 5 sweeps 10 to 500)", None),
                "fs": Key(positive(MAX_RATE), _FS, None)},
    "cochlea": {"channels": Key(integer(1, MAX_CHANNELS), f"an integer 1..{MAX_CHANNELS} (MAX_CHANNELS)", None),
                "f_low": Key(positive(), "lowest centre frequency, Hz, > 0", None),
                "f_high": Key(positive(), "top of the band, Hz, above f_low", None),
                "fs": Key(positive(MAX_RATE), _FS, None)},
    "custom": {"fs": Key(positive(MAX_RATE), _FS),
               "cf": Key(_numbers, f"centre frequencies, Hz: a list of 1..{MAX_CHANNELS} numbers (MAX_CHANNELS)"),
               "b": Key(_numbers, "bandwidth parameters b, Hz: one per centre frequency"),
               "names": Key(_names, "channel names: one non-empty string per channel", None)},
}


def bank_from_description(d, where: str = "bank") -> Bank:
    """Return the :class:`~supramodal.banks.Bank` a description names (module docstring).

    Raises
    ------
    BankFileError
        Naming ``where`` and the key, for an unknown kind or key, a value of the wrong form, a
        missing required key, or a bank that cannot run (e.g. a centre frequency at or above
        the Nyquist frequency).
    """
    if not isinstance(d, dict):
        raise BankFileError(f"{where}: a bank description is a table (JSON object), got {type(d).__name__}")
    kind = d.get("kind")
    if not isinstance(kind, str) or kind not in BANK_KEYS:      # a list or an object is no kind (and unhashable)
        raise BankFileError(f"{where}: kind must be one of {sorted(BANK_KEYS)}, got {kind!r}")
    d = {k: v for k, v in fill(f"{where} ({kind} bank)", {k: v for k, v in d.items() if k != "kind"},
                               BANK_KEYS[kind], BankFileError).items() if v is not None}
    try:
        if kind == "whisker":
            return whisker_bank(**d)
        if kind == "cochlea":
            names = {"channels": "n", "f_low": "f_low", "f_high": "f_high", "fs": "fs"}
            return cochlea_bank(**{arg: d[k] for k, arg in names.items() if k in d})
        n = len(d["cf"])
        names = d.get("names", [f"ch{k:02d}" for k in range(n)])
        return Bank("custom", d["fs"], np.asarray(d["cf"], float), np.asarray(d["b"], float), tuple(names))
    except InputError as exc:
        raise BankFileError(f"{where}: {exc}") from None


def load_bank(path) -> Bank:
    """Read and validate a bank file (never executed)."""
    path = Path(path)
    try:
        d = read_json_file(path, max_bytes=MAX_BANK_BYTES, max_depth=MAX_BANK_DEPTH, error=BankFileError,
                           limits=("MAX_BANK_BYTES", "MAX_BANK_DEPTH"))
    except FileNotFoundError:
        raise BankFileError(f"no bank file at {path}: give 'whisker', 'cochlea' or the path of a bank file") from None
    except IsADirectoryError:
        raise BankFileError(f"{path} is a folder, not a bank file") from None
    if not isinstance(d, dict) or d.get("format") != BANK_FORMAT:
        raise BankFileError(f"{path} is not a supramodal bank file (its 'format' must be {BANK_FORMAT!r})")
    if type(d.get("version")) is not int or d.get("version") != BANK_VERSION:
        raise BankFileError(f"{path}: bank file version {d.get('version')!r} is not supported (this program "
                            f"reads version {BANK_VERSION})")
    unknown = sorted(set(d) - {"format", "version", "bank"})
    if unknown:
        raise BankFileError(f"{path}: unknown key(s) {unknown}; a bank file holds format, version and bank")
    return bank_from_description(d.get("bank"), f"{path}: bank")


def save_bank(path, bank: Bank) -> Path:
    """Write ``bank`` as a bank file in the explicit form (every channel's cf and b, exactly)."""
    path = Path(path)
    description = {"kind": "custom", "fs": bank.fs, "cf": [float(v) for v in bank.cf],
                   "b": [float(v) for v in bank.b], "names": list(bank.names)}
    path.write_text(json.dumps({"format": BANK_FORMAT, "version": BANK_VERSION, "bank": description}, indent=1) + "\n")
    return path
