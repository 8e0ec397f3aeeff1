"""``supramodal fit``: a joint search of bank, window, features and network under a user's constraints.

Every trial is one setting of all parameters at once (:class:`Setting`): the bank's family (ERB-spaced
like the cochlea, or the whisker array's layout of resonances stretched over the band), its channels,
band edges and bandwidth scale at the recordings' own rate, the window, the features, the hidden
units and the epochs. Optuna's TPE sampler, seeded, proposes them; each is scored by grouped
``k``-fold cross-validation (folds by manifest line, :func:`supramodal.training.grouped_folds`), one
fold after another, each fold's running mean reported to Optuna as an intermediate value so that its
median pruner stops a trial that is hopeless after its first folds.

What a user states is obeyed, and refused when it cannot be (:class:`FitError`): ``max_window``
(the latency budget: no window longer), ``max_channels`` (the CPU budget) and ``target``
(``window``, ``recording`` or ``contact``: the accuracy maximised). A window must hold one period
of the bank's lowest channel, so each trial's band starts no lower than ``1 / window``.

Trials run in rounds of ``batch`` (asked from Optuna together, scored fold by fold, told in
order): the result depends on the seed and the batch alone, not on how many processes or which
cluster scored the folds. The search stops early on a plateau (:func:`plateau`): when the best
trial's score has not moved by more than its own fold spread (the sd of the target over its folds)
in the last ``patience`` trials, more trials would only pick among settings that the folds cannot
tell apart, and it says so. ``jobs > 1`` starts a local Dask cluster of that many processes,
``cluster`` connects to a running Dask scheduler; the folds of a round are mapped over its
workers by Dask (:class:`Runner`). Filterbank outputs are computed once per bank and recording
(:class:`~node.fit_cache.FeatureCache`).

The report: every trial; the best; the best per window length (the accuracy-vs-window curve) with
the paper's two banks scored beside each point at the same window, features, hidden units and
epochs (so also beside the best), and whether the best beats them by more than a fold's spread
(:func:`paper_verdict`). Each fold scores the model ``supramodal train`` would make of its training
recordings (:meth:`~supramodal.model.TextureModel.train`: calibrated on folds grouped by recording, its fold
networks stopped early together and deployed), with the trial's hidden units (``train --hidden``): the
setting the fit reports is the model the ``next:`` command makes. The paper's banks are scored the same way.
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import math
import socket
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from supramodal.bankfile import bank_from_description, save_bank
from supramodal.banks import (
    ERB_TO_B,
    MAX_CHANNELS,
    WHISKER_B_MIN,
    WHISKER_Q_EAR,
    WHISKER_TABLE,
    Bank,
    cochlea_bank,
    erb,
    whisker_bank,
)
from supramodal.calibration import DEFAULT_CALIBRATION_FOLDS, pool_log_posteriors, winner
from supramodal.checks import integer, one_of, positive
from supramodal.errors import InputError
from supramodal.evaluation import pooled_accuracy
from supramodal.mlp import EARLY_STOP_PATIENCE
from supramodal.model import GainAugment, TextureModel
from supramodal.node.scene.band import channels_beyond_band
from supramodal.node.workflows.fit_cache import DEFAULT_MEMORY_BYTES, PART, FeatureCache
from supramodal.node.workflows.manifest import ManifestError, manifest_classes, read_manifest
from supramodal.node.workflows.reports import pyplot_or_none
from supramodal.node.workflows.training import recording_group
from supramodal.pipeline import window_length
from supramodal.replay.session import session_paths
from supramodal.replay.wavio import wav_info
from supramodal.training import grouped_folds

__all__ = ["DEFAULT_PATIENCE", "FitError", "Runner", "Setting", "Space", "fit_search", "format_search",
           "install_hint", "paper_verdict", "plateau", "search_space", "write_search"]

#: The values each parameter may take, (full, quick). Fractions of the Nyquist frequency for the
#: band edges; seconds for the window.
CHANNELS = ((10, 20, 30, 50), (10, 20, 30))
F_HIGH = ((0.5, 0.7, 0.9), (0.5, 0.9))
F_LOW = ((0.001, 0.005, 0.02, 0.05, 0.1), (0.005, 0.02, 0.1))
B_SCALE = ((0.5, 1.0, 2.0), (0.5, 1.0, 2.0))
WINDOWS = ((0.025, 0.05, 0.1, 0.2, 0.4), (0.05, 0.1, 0.2, 0.4))
FEATURE_SETS = (("Af", "A+f+Af", "A", "f"), ("Af", "A+f+Af"))
HIDDEN = ((8, 16, 32, 64), (8, 16, 32))
EPOCHS = ((50, 100, 200, 300), (30, 60, 120))
FAMILIES = ("erb", "whisker")
TARGETS = ("window", "recording", "contact")
#: Trials when none are asked for (full, quick).
DEFAULT_TRIALS = (60, 16)
#: Most windows a fold's model trains on (full, quick): evenly spaced over the training recordings'
#: windows, every recording in proportion (None: all). Test windows are always all scored.
TRAIN_WINDOWS = (None, 4000)
#: Trials asked from Optuna at once (the result depends on it, not on the number of processes).
DEFAULT_BATCH = 4
#: Trials in which the best must move by more than its fold spread, or the search stops (0: never stops
#: early, the default). Off by default, as measured (docs/own-sensor.md): the searches tried improved by
#: steps each within a fold's spread that added up (20 recordings: the stop at 8 trials kept 0.478 where
#: every trial reached 0.540; 700: 0.367 against 0.377), so the stop is the user's trade of time for that.
DEFAULT_PATIENCE = 0
#: A contact, for ``target = "contact"``: seconds of consecutive windows pooled.
DEFAULT_CONTACT = 0.5


class FitError(InputError):
    """A constraint or an option of the fit that cannot be met; the message says why and the fix."""


def install_hint() -> str:
    """Return the line that says how to install what the search needs."""
    return "supramodal fit needs the fit extra (optuna, dask[distributed]): pip install 'supramodal[fit]'"


def _features(text: str) -> tuple[str, ...]:
    return tuple(text.split("+"))


@dataclass(frozen=True)
class Setting:
    """One trial: a bank of ``family`` at ``fs`` Hz, a window and a network.

    Attributes
    ----------
    fs : float
        The bank's rate, Hz (the recordings' own).
    family : {"erb", "whisker"}
        ERB-spaced centre frequencies with the cochlea's bandwidth rule, or the whisker table's 20
        resonances (their spread on a log scale, interpolated to ``channels``) stretched over the
        band, with the whiskers' bandwidth rule.
    channels : int
    f_low, f_high : float
        The band's edges, Hz (``f_low`` already at least ``1 / window``).
    b_scale : float
        Every bandwidth times this.
    window : float
        Seconds.
    features : str
        Feature names joined by ``+``.
    hidden, epochs : int
        Hidden units and iRPROP- epochs of the network.
    """

    fs: float
    family: str
    channels: int
    f_low: float
    f_high: float
    b_scale: float
    window: float
    features: str
    hidden: int
    epochs: int

    def bank(self) -> Bank:
        """Return the setting's bank (kind ``custom``)."""
        if self.family == "erb":
            base = bank_from_description({"kind": "cochlea", "channels": self.channels, "f_low": self.f_low,
                                          "f_high": self.f_high, "fs": self.fs}, "fit")
            return Bank("custom", self.fs, base.cf, base.b * self.b_scale, base.names)
        table = np.log(np.sort([cf for row in WHISKER_TABLE.values() for cf in row]))
        at = np.interp(np.linspace(0, 1, self.channels), np.linspace(0, 1, table.size), table)
        span = (at - table[0]) / (table[-1] - table[0]) if table[-1] > table[0] else np.zeros_like(at)
        cf = np.exp(np.log(self.f_low) + span * (np.log(self.f_high) - np.log(self.f_low)))
        stretch = self.f_high / math.exp(table[-1])
        b = ERB_TO_B * erb(cf, WHISKER_Q_EAR, WHISKER_B_MIN * stretch) * self.b_scale
        return Bank("custom", self.fs, cf, b, tuple(f"w{i + 1:02d}" for i in range(self.channels)))


@dataclass(frozen=True)
class Space:
    """What the search may try, after the constraints (:func:`search_space`)."""

    fs: float
    channels: tuple[int, ...]
    f_high: tuple[float, ...]
    f_low: tuple[float, ...]
    b_scale: tuple[float, ...]
    windows: tuple[float, ...]
    features: tuple[str, ...]
    hidden: tuple[int, ...]
    epochs: tuple[int, ...]
    target: str
    contact: float
    max_window: float | None
    max_channels: int | None
    train_windows: int | None = None

    def setting(self, trial) -> Setting | None:
        """Return the setting an Optuna trial proposes; None when its band is empty.

        Empty: the window's ``1 / window`` lower edge at or above half its top edge.
        """
        family = trial.suggest_categorical("family", FAMILIES)
        channels = trial.suggest_categorical("channels", self.channels)
        f_high = trial.suggest_categorical("f_high", self.f_high)
        f_low = trial.suggest_categorical("f_low", self.f_low)
        b_scale = trial.suggest_categorical("b_scale", self.b_scale)
        window = trial.suggest_categorical("window", self.windows)
        features = trial.suggest_categorical("features", self.features)
        hidden = trial.suggest_categorical("hidden", self.hidden)
        epochs = trial.suggest_categorical("epochs", self.epochs)
        nyquist = self.fs / 2
        lo, hi = max(f_low * nyquist, 1 / window), f_high * nyquist
        if lo * 2 > hi:
            return None
        return Setting(self.fs, family, channels, lo, hi, b_scale, window, features, hidden, epochs)

    def start(self) -> list[dict]:
        """Return the first trials, one per window (so that the curve has every window).

        Each is the paper's cochlea made at the recordings' rate, as far as the space allows (an ERB bank of
        the most channels over the widest band), all three features.
        """
        mid = lambda values: values[len(values) // 2]         # noqa: E731
        first = {"family": "erb", "channels": max(self.channels),
                 "f_high": max(self.f_high), "f_low": min(self.f_low),
                 "b_scale": 1.0 if 1.0 in self.b_scale else mid(self.b_scale), "features": "A+f+Af",
                 "hidden": mid(self.hidden), "epochs": mid(self.epochs)}
        return [{**first, "window": w} for w in self.windows]


def _rate(path: Path) -> int:
    wav = path if path.suffix.lower() == ".wav" else session_paths(path)[0]
    return wav_info(wav).rate


def _duration(rec) -> float:
    wav = rec.path if rec.path.suffix.lower() == ".wav" else session_paths(rec.path)[0]
    info = wav_info(wav)
    end = info.frames / info.rate if rec.end is None else min(rec.end, info.frames / info.rate)
    return end - rec.start


def search_space(recs, quick: bool = False, max_window: float | None = None, max_channels: int | None = None,
                 target: str = "window", contact: float = DEFAULT_CONTACT, max_epochs: int | None = None) -> Space:
    """Return the values the search may try on these recordings under the constraints.

    Parameters
    ----------
    recs : list of Recording
    quick : bool
        The shorter lists of values.
    max_window : float or None
        Latency budget, seconds: no window longer. A window of this length is tried too.
    max_channels : int or None
        CPU budget: no bank with more channels. A bank of this many channels is tried too.
    target : {"window", "recording", "contact"}
    contact : float
        Seconds of a contact (``target = "contact"``): that many seconds of windows pooled.
    max_epochs : int or None
        Most iRPROP- epochs; this many are tried too.

    Raises
    ------
    FitError
        Every constraint that cannot be met, with the reason and the fix: a window budget of fewer
        than two samples, or too short to hold one period of a channel an octave below the top of
        any band; windows longer than the shortest trial; a channel budget beyond
        :data:`~supramodal.banks.MAX_CHANNELS`; an unknown target; a contact shorter than a window
        or longer than a trial.
    """
    pick = 1 if quick else 0
    rates = sorted({_rate(r.path) for r in recs})
    fs = float(rates[-1])
    nyquist = fs / 2
    shortest = min(recs, key=_duration)
    short = _duration(shortest)
    if not one_of(*TARGETS)(target):
        raise FitError(f"--target {target!r}: choose one of {', '.join(TARGETS)}")
    windows = list(WINDOWS[pick])
    if max_window is not None:
        if not positive()(max_window):
            raise FitError(f"--max-window must be a positive number of seconds, got {max_window!r}")
        if round(max_window * fs) < 2:
            raise FitError(f"--max-window {max_window:g} s is {round(max_window * fs)} sample(s) at the recordings' "
                           f"{fs:g} Hz; a window needs at least 2: allow at least {2 / fs:.3g} s")
        top = max(F_HIGH[pick]) * nyquist
        if 2 / max_window > top:
            raise FitError(f"--max-window {max_window:g} s is shorter than one period of the lowest band any bank "
                           f"could have: a window must hold one period of its bank's lowest channel, and the band an "
                           f"octave below its top ({top:g} Hz at most at {fs:g} Hz), so a window of at least "
                           f"{2 / top:.3g} s; raise --max-window")
        windows = [w for w in windows if w <= max_window]
        if max_window not in windows:
            windows.append(float(max_window))
    windows = [w for w in windows if 2 / w <= max(F_HIGH[pick]) * nyquist and round(w * fs) >= 2]
    fitting = [w for w in windows if w <= short]
    if not fitting:
        raise FitError(f"{shortest.where}: {shortest.path.name} holds {short:g} s, shorter than every window the fit "
                       f"may try ({', '.join(f'{w:g}' for w in windows)} s); use longer trials or a shorter "
                       "--max-window")
    channels = list(CHANNELS[pick])
    if max_channels is not None:
        if not integer(1, MAX_CHANNELS)(max_channels):
            raise FitError(f"--max-channels must be a whole number from 1 to {MAX_CHANNELS} (MAX_CHANNELS), "
                           f"got {max_channels!r}")
        channels = [c for c in channels if c <= max_channels]
        if max_channels not in channels:
            channels.append(max_channels)
    epochs = list(EPOCHS[pick])
    if max_epochs is not None:
        epochs = [e for e in epochs if e <= max_epochs]
        if max_epochs not in epochs:
            epochs.append(int(max_epochs))
    if target == "contact":
        if not (positive()(contact) and contact >= min(fitting)):
            raise FitError(f"--contact {contact:g} s is shorter than the shortest window ({min(fitting):g} s): "
                           "a contact pools whole windows")
        if contact > short:
            raise FitError(f"--contact {contact:g} s is longer than {shortest.where} ({short:g} s): no trial would "
                           "hold a whole contact; choose a shorter contact")
    return Space(fs, tuple(sorted(channels)), F_HIGH[pick], F_LOW[pick], B_SCALE[pick], tuple(sorted(fitting)),
                 FEATURE_SETS[pick], HIDDEN[pick], tuple(sorted(epochs)), target, float(contact), max_window,
                 max_channels, TRAIN_WINDOWS[pick])


# -- one fold, anywhere --------------------------------------------------------------------------

#: This process's caches, by manifest, options and thread (a worker keeps its own between tasks; the
#: threads of a worker share the folder, not the object).
_CACHES: dict[tuple, tuple[list, FeatureCache]] = {}


def _cache(job: dict) -> tuple[list, FeatureCache]:
    key = (job["manifest"], str(job["mapping"]), job["windows"], job["cache_dir"], job["cache_memory"],
           threading.get_ident())
    if key not in _CACHES:
        recs = read_manifest(job["manifest"])
        _CACHES[key] = recs, FeatureCache(recs, job["windows"], job["mapping"], job["cache_memory"],
                                          job["cache_dir"])
    return _CACHES[key]


def forget_caches() -> None:
    """Drop this process's feature caches (the end of a fit)."""
    _CACHES.clear()


def warm_bank(job: dict) -> dict:
    """Filter part ``job["part"]`` of the recordings through ``job["bank"]`` into the cache folder.

    There the other workers of the machine read it. A task of its own, so that the parts of a new bank are
    filtered by several workers at once instead of each fold filtering them again.

    Returns
    -------
    dict
        ``filterbank_runs``: the recordings filtered (0 when the part was on disk);
        ``features_cpu_seconds``: CPU seconds of the thread that ran it.
    """
    cpu0 = time.thread_time()
    recs, cache = _cache(job)
    before = cache.filterbank_runs
    cache.fill(Bank.from_dict(job["bank"]), job["part"])
    return {"filterbank_runs": cache.filterbank_runs - before, "features_cpu_seconds": time.thread_time() - cpu0}


def score_fold(job: dict) -> dict:
    """Train on every fold but ``job["fold"]`` and score that one (a task: plain data in and out).

    Parameters
    ----------
    job : dict
        ``manifest`` (path), ``mapping``, ``windows`` (every window of the search, seconds),
        ``cache_dir``, ``cache_memory`` (bytes), ``bank`` (:meth:`Bank.to_dict`), ``window``
        (seconds), ``features`` (names joined by ``+``), ``hidden``, ``epochs``, ``fold``, ``k``,
        ``seed``, ``contact`` (seconds), ``train_windows`` (most training windows, evenly spaced; None:
        all), ``augment`` (:meth:`GainAugment.to_dict`, the network's gain augmentation; None: none).

    Returns
    -------
    dict
        ``window``, ``recording`` and ``contact`` accuracy of the fold, ``filterbank_runs`` (the
        recordings this task ran through a filterbank: 0 when the bank was cached), ``cpu_seconds``
        (of the thread that ran it: BLAS is held to that thread) and ``features_cpu_seconds``, the part
        of them spent before the network (the features: filtered, or read from the cache and summed
        into windows).
    """
    cpu0 = time.thread_time()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:                                 # without it BLAS keeps its own threads
        from contextlib import nullcontext as threadpool_limits
    recs, cache = _cache(job)
    before = cache.filterbank_runs
    bank = Bank.from_dict(job["bank"])
    features = _features(job["features"])
    with threadpool_limits(1):                          # one core per task: processes scale, threads fight
        values = cache.features(bank, job["window"], features)
        features_cpu = time.thread_time() - cpu0
        classes = sorted({r.label for r in recs})
        fold = grouped_folds([r.where for r in recs], [r.label for r in recs], job["k"], job["seed"])
        train = [i for i in range(len(recs)) if fold[i] != job["fold"]]
        test = [i for i in range(len(recs)) if fold[i] == job["fold"]]
        x = np.concatenate([values[i] for i in train])
        y = np.concatenate([np.full(len(values[i]), classes.index(recs[i].label)) for i in train])
        groups = np.repeat(np.array([recording_group(recs[i]) for i in train]), [len(values[i]) for i in train])
        if job["train_windows"] is not None and len(x) > job["train_windows"]:
            keep = np.round(np.linspace(0, len(x) - 1, job["train_windows"])).astype(int)
            x, y, groups = x[keep], y[keep], groups[keep]
        augment = job.get("augment")
        # the model `train` makes of these recordings (calibrated by recording, early-stopped fold networks)
        model = TextureModel.train(x, y, classes, bank, features, window_length(job["window"], bank.fs),
                                   epochs=job["epochs"], seed=job["seed"], hidden=job["hidden"], groups=groups,
                                   calibration_folds=DEFAULT_CALIBRATION_FOLDS, patience=EARLY_STOP_PATIENCE,
                                   augment=None if augment is None else GainAugment.from_dict(augment, FitError))
        lps = [model.log_posteriors(values[i]) for i in test if len(values[i])]
        truths = [classes.index(recs[i].label) for i in test if len(values[i])]
    window_right = np.concatenate([winner(lp) == t for lp, t in zip(lps, truths)])
    recording = float(np.mean([winner(pool_log_posteriors(lp, 0.0)) == t for lp, t in zip(lps, truths)]))
    n = max(1, int(round(job["contact"] / job["window"])))
    contact = pooled_accuracy(lps, truths, n)[0]
    return {"window": float(window_right.mean()), "recording": recording,
            "contact": recording if contact is None else float(contact),
            "filterbank_runs": cache.filterbank_runs - before, "cpu_seconds": time.thread_time() - cpu0,
            "features_cpu_seconds": features_cpu}


# -- where the folds run -------------------------------------------------------------------------

#: Run in each local worker process as it starts (Dask's preload of a script's text): Ctrl-C reaches the
#: whole process group, and it is the fit's to handle, closing the cluster; a worker that took it
#: printed a KeyboardInterrupt traceback each. A task cancelled as the cluster closes is no news either,
#: nor a heartbeat that finds the scheduler already gone (a dry run printed its traceback after a Ctrl-C).
WORKER_IGNORES_SIGINT = ("import logging, signal\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\n"
                         "logging.getLogger('distributed.worker.state_machine').setLevel(logging.ERROR)\n"
                         "logging.getLogger('distributed.worker').addFilter(lambda record: not record.getMessage()"
                         ".startswith('Failed to communicate with scheduler during heartbeat'))\n")
#: Seconds a Dask scheduler has to accept the connection, and then to greet.
SCHEDULER_TIMEOUT = 20.0
#: Seconds each local worker process has to end on its own when a fit that ran to its end closes its
#: cluster (Dask's nanny waits 0.8 of it). Dask's own close waits 4 s and then kills the worker, saying
#: "Worker process still alive after 4.0 seconds, killing" once a worker: on a busy machine a worker's
#: exit took longer (issue 36), with the fit's result in hand. An interrupted fit keeps Dask's 4 s: a
#: worker then may be in the middle of a fold, which it would finish first.
WORKER_CLOSE_SECONDS = 20.0
#: Seconds an interrupted fit's client and local cluster each have to close (Dask's own: twice
#: :data:`SCHEDULER_TIMEOUT` for the client). Ctrl-C asks to be out now: a scheduler slow to answer on a busy
#: machine held an interrupted fit for 53 s in a test run, with nothing left to save.
INTERRUPTED_CLOSE_SECONDS = 5.0


def _check_scheduler_answers(address: str, seconds: float) -> None:
    """Raise :class:`FitError` unless a TCP scheduler at ``address`` greets within ``seconds`` of the connection.

    A Dask scheduler speaks first. Dask's own timeout covers only the connection: an address that accepts and
    stays silent (another service, a stopped process) held the fit forever. Addresses of other schemes
    (tls://, ucx://) are left to Dask.
    """
    from distributed.comm import parse_address
    from distributed.comm.addressing import parse_host_port

    try:
        scheme, location = parse_address(address)
        host, port = parse_host_port(location)
    except ValueError:
        return                                          # Dask's own refusal says what is wrong
    if scheme != "tcp":
        return
    try:
        with socket.create_connection((host, port), timeout=seconds) as probe:
            probe.settimeout(seconds)
            if probe.recv(1):
                return
            said = "closed the connection without a word"
    except TimeoutError:
        said = f"accepts connections but said nothing in {seconds:g} s"
    except OSError as exc:
        said = f"cannot be reached ({exc.strerror or exc})"
    raise FitError(f"--cluster {address}: {said}: no Dask scheduler there; start one (dask scheduler; dask worker "
                   "ADDRESS) and give its address, or leave --cluster out")


class Runner:
    """Maps fold tasks over this process, a local Dask cluster or a running one; results in order.

    Parameters
    ----------
    jobs : int
        1: in this process; more: a local Dask cluster of that many single-threaded processes.
    cluster : str or None
        A Dask scheduler's address (``tcp://HOST:PORT``); its workers must have supramodal
        installed and see the manifest's files at the same paths.
    """

    def __init__(self, jobs: int = 1, cluster: str | None = None) -> None:
        self.client = self._local = None
        if cluster is not None or jobs > 1:
            try:
                import distributed  # noqa: F401
            except ImportError:
                raise FitError(install_hint()) from None
        if cluster is not None:
            from distributed import Client

            _check_scheduler_answers(cluster, SCHEDULER_TIMEOUT)
            try:
                self.client = Client(cluster, timeout=f"{SCHEDULER_TIMEOUT:g}s")
            except OSError as exc:
                raise FitError(f"--cluster {cluster}: no Dask scheduler answers there ({exc}); start one "
                               "(dask scheduler; dask worker ADDRESS) or leave --cluster out") from None
        elif jobs > 1:
            from distributed import Client, LocalCluster

            # The scheduler serves HTTP whatever the dashboard: on a port of its own, on this machine only
            # (at 8787, Dask's default, a second fit printed a 4-line "Port 8787 is already in use" warning).
            self._local = LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True, host="127.0.0.1",
                                       dashboard_address="127.0.0.1:0", preload=[WORKER_IGNORES_SIGINT])
            self.client = Client(self._local)

    @property
    def where(self) -> str:
        """Where the work runs, in words: this process, or the Dask scheduler's address and its workers."""
        if self.client is None:
            return "this process"
        workers = len(self.client.scheduler_info().get("workers", {}))
        return f"Dask scheduler {self.client.scheduler.address} ({workers} workers)"

    def map(self, jobs: list[dict], task=None) -> list[dict]:
        """``task`` (default :func:`score_fold`) of every job, in the jobs' order."""
        task = score_fold if task is None else task
        if self.client is None:
            return [task(j) for j in jobs]
        return self.client.gather(self.client.map(task, jobs, pure=False))

    def start(self, jobs: list[dict], task) -> list:
        """Begin ``task`` on every job on the cluster's workers and return at once (handles for :meth:`wait`).

        The tasks queue behind every task :meth:`map` gives the workers; nothing is begun in this process.
        """
        if self.client is None:
            return []
        return self.client.map(task, jobs, pure=False, priority=-1)

    def wait(self, started: list) -> list[dict]:
        """Return the results of what :meth:`start` began."""
        return [] if self.client is None else self.client.gather(started)

    def close(self, done: bool = True) -> None:
        """Close the client and a local cluster.

        ``done``: the work is over (no task is running), so each local worker is given
        :data:`WORKER_CLOSE_SECONDS` to end; else (an interrupt, a failure) Dask's own close of the workers,
        the client and the cluster each bounded by :data:`INTERRUPTED_CLOSE_SECONDS`.
        """
        if self.client is not None:
            if self._local is None:                     # a cluster's workers outlive the fit: free their caches
                self.client.run(forget_caches)
            if done:
                self.client.close()
            else:
                with contextlib.suppress(Exception):    # gone or slow: the fit ends either way
                    self.client.close(timeout=INTERRUPTED_CLOSE_SECONDS)
        if self._local is not None:
            if done:                                    # the workers first; the cluster's close finds them closed
                self._local.sync(_close_nannies, list(self._local.workers.values()), WORKER_CLOSE_SECONDS)
                self._local.close()
            else:
                with contextlib.suppress(Exception):    # its workers end with this process in any case
                    self._local.close(timeout=INTERRUPTED_CLOSE_SECONDS)

    def __enter__(self) -> Runner:
        return self

    def __exit__(self, kind, *exc) -> None:
        self.close(done=kind is None)


async def _close_nannies(nannies: list, seconds: float) -> None:
    """Close a local cluster's worker processes (Dask nannies) together, each given ``seconds``."""
    await asyncio.gather(*(nanny.close(timeout=seconds) for nanny in nannies))


# -- the search ----------------------------------------------------------------------------------

def _summary(folds: list[dict]) -> dict:
    out = {}
    for key in TARGETS:
        v = np.array([f[key] for f in folds])
        out[f"{key}_mean"] = float(v.mean())
        out[f"{key}_sd"] = float(v.std(ddof=1)) if len(v) > 1 else 0.0
    return out


def fit_search(manifest, k: int = 5, seed: int = 0, quick: bool = False, trials: int | None = None,
               timeout: float | None = None, batch: int = DEFAULT_BATCH, max_window: float | None = None,
               max_channels: int | None = None, target: str = "window", contact: float = DEFAULT_CONTACT,
               max_epochs: int | None = None, jobs: int = 1, cluster: str | None = None, mapping="auto",
               cache_dir=None, cache_memory: int = DEFAULT_MEMORY_BYTES, patience: int = DEFAULT_PATIENCE,
               augment: GainAugment | None = None, progress=None) -> dict:
    """Search settings (module docstring) on the manifest's recordings.

    Parameters
    ----------
    manifest : path-like
    k, seed : int
        Folds (grouped by manifest line) and the seed of the folds, the sampler and the networks.
    quick : bool
        The shorter lists of values, and fewer trials by default.
    trials : int or None
        Trials to run (default :data:`DEFAULT_TRIALS`).
    timeout : float or None
        Seconds: no new round of trials starts after this (the trials done so far are the result).
    batch : int
        Trials asked at once; the result depends on it (and the seed), not on ``jobs``/``cluster``.
    max_window, max_channels, target, contact, max_epochs
        See :func:`search_space`.
    jobs, cluster
        See :class:`Runner`.
    cache_dir : path-like or None
        Where feature windows that leave memory are kept (shared by local workers).
    cache_memory : int
        Bytes of feature windows each process keeps in memory.
    patience : int
        Trials: the search stops after a round at whose end the best has not moved by more than its
        fold spread in the last ``patience`` trials (:func:`plateau`); 0: it runs every trial.
    augment : GainAugment or None
        Gain augmentation of every fold's networks, the paper's banks' too (``train --augment-gains``'s;
        its gains by each trial's bank where it leaves them to the bank): the settings are then scored as
        the model will be trained. Default none.
    progress : callable(str), optional

    Returns
    -------
    dict
        ``fs``, ``k``, ``seed``, ``batch``, ``target``, ``space`` (the values tried), ``rows`` (every
        trial: state, setting, folds scored, means and sds), ``best`` (the best trial's row),
        ``curve`` (per window: ``fitted``, the best trial there, and ``whisker``, ``cochlea``, the
        paper's banks at that window with its features and network), ``paper`` (the paper's
        banks beside the best), ``filterbank_runs`` (recordings run through a filterbank, all
        processes), ``seconds``, ``where``, ``trials`` (asked), ``patience``, ``stopped`` (None, or what
        :func:`plateau` said when it ended the search before its last trial), ``features_cpu_seconds`` and
        ``networks_cpu_seconds`` (CPU seconds of every task, all processes: the features, filtered or read
        and summed, and the networks, trained and scored).

    Raises
    ------
    FitError
        A constraint that cannot be met (:func:`search_space`), or nothing completed.
    ManifestError
        A manifest that cannot be cross-validated with ``k`` folds.
    """
    try:
        import optuna
    except ImportError:
        raise FitError(install_hint()) from None
    say = progress or (lambda m: None)
    recs = read_manifest(manifest)
    manifest_classes(recs, manifest)          # one label: refused as train refuses it (it scored 1.000)
    try:
        grouped_folds([r.where for r in recs], [r.label for r in recs], k, seed)
    except InputError as exc:
        raise ManifestError(f"{manifest}: {exc}") from None
    space = search_space(recs, quick, max_window, max_channels, target, contact, max_epochs)
    trials = DEFAULT_TRIALS[1 if quick else 0] if trials is None else int(trials)
    if trials < 1 or batch < 1:
        raise FitError(f"the fit needs at least one trial and a batch of at least one, got {trials} and {batch}")
    if not integer(0, None)(patience):
        raise FitError(f"--patience must be a whole number of trials, 0 or more (0: no early stop), got {patience!r}")
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="maximize", sampler=optuna.samplers.TPESampler(seed=seed),
                                pruner=optuna.pruners.MedianPruner(n_startup_trials=max(batch, len(space.windows)),
                                                                   n_warmup_steps=0))
    for params in space.start()[:trials]:
        study.enqueue_trial(params)
    base = {"manifest": str(manifest), "mapping": mapping, "windows": space.windows,
            "cache_dir": None if cache_dir is None else str(cache_dir), "cache_memory": int(cache_memory),
            "k": k, "seed": seed, "contact": space.contact, "train_windows": space.train_windows,
            "augment": None if augment is None else augment.to_dict()}
    rows: list[dict] = []
    stopped: dict | None = None
    # What the tasks did, all processes: recordings filtered, and CPU seconds of features and of networks
    # (where a fit's time goes: benchmarks/fit_speed.py prints it).
    spent = {"filterbank_runs": 0, "features": 0.0, "networks": 0.0}

    def tally(results: list[dict]) -> list[dict]:
        for r in results:
            spent["filterbank_runs"] += r["filterbank_runs"]
            spent["features"] += r["features_cpu_seconds"]
            spent["networks"] += r.get("cpu_seconds", r["features_cpu_seconds"]) - r["features_cpu_seconds"]
        return results

    t0 = time.perf_counter()
    warmed: set[str] = set()

    def warm(banks: list[Bank], runner: Runner) -> list[dict]:
        """Return the jobs filtering the parts of the banks not yet filtered, on a cluster sharing the cache folder.

        None in this process: each fold fills what it needs.
        """
        if runner.client is None or cache_dir is None:
            return []
        todo = {}
        for bank in banks:
            key = repr(bank.to_dict())
            if key not in warmed:
                warmed.add(key)
                todo[key] = [{**base, "bank": bank.to_dict(), "part": part} for part in range(parts)]
        return [job for jobs in todo.values() for job in jobs]

    parts = -(-len(recs) // PART)
    with Runner(jobs, cluster) as runner:
        where = runner.where
        # The paper's banks filter every recording at their own rates (the cochlea's 44.1 kHz is the
        # costliest bank of the fit): on a cluster they start now, beside the trials.
        paper_warm = runner.start(warm([whisker_bank(), cochlea_bank()], runner), warm_bank)
        say(f"fit: {trials} trials of grouped {k}-fold cross-validation in rounds of {batch}, on {where}; "
            f"maximising {target} accuracy; windows {', '.join(f'{w:g}' for w in space.windows)} s")
        # A time budget stops new rounds, never the first: a fit always has a result.
        while (len(rows) < trials and stopped is None
               and (not rows or timeout is None or time.perf_counter() - t0 < timeout)):
            asked = [study.ask() for _ in range(min(batch, trials - len(rows)))]
            live: list[tuple] = []
            for trial in asked:
                setting = space.setting(trial)
                if setting is None:
                    study.tell(trial, state=optuna.trial.TrialState.PRUNED)
                    rows.append({"trial": trial.number, "state": "empty band", "folds": 0, **_params(trial.params)})
                    continue
                live.append((trial, setting, []))
            tally(runner.map(warm([s.bank() for _, s, _ in live], runner), warm_bank))
            for f in range(k):
                if not live:
                    break
                results = runner.map([{**base, "bank": s.bank().to_dict(), "window": s.window,
                                       "features": s.features, "hidden": s.hidden, "epochs": s.epochs, "fold": f}
                                      for _, s, _ in live])
                still = []
                for (trial, setting, folds), r in zip(live, tally(results)):
                    folds.append(r)
                    trial.report(float(np.mean([x[target] for x in folds])), f)
                    if f < k - 1 and trial.should_prune():
                        study.tell(trial, state=optuna.trial.TrialState.PRUNED)
                        rows.append(_row(trial.number, "pruned", setting, folds, target))
                    else:
                        still.append((trial, setting, folds))
                live = still
            for trial, setting, folds in live:
                row = _row(trial.number, "complete", setting, folds, target)
                study.tell(trial, row["score"])
                rows.append(row)
            rows.sort(key=lambda r: r["trial"])
            done = [r for r in rows if r["state"] == "complete"]
            elapsed = time.perf_counter() - t0
            left = elapsed / len(rows) * (trials - len(rows))
            if timeout is not None:
                left = min(left, max(0.0, timeout - elapsed))
            best = max(done, key=_rank) if done else None
            say(f"fit: trial {len(rows)} of {trials}; "
                + (f"best so far {best[f'{target}_mean']:.3f} of {target}s (trial {best['trial']}: {_describe(best)})"
                   if best else "none complete yet")
                + f"; {elapsed:.0f} s" + ("" if timeout is None else f" of the {timeout:g} s budget")
                + f", about {left:.0f} s left"
                + ("" if (cpu := cpu_per_trial(rows)) is None else f"; {cpu:.1f} CPU s per complete trial"))
            # Checked after whole rounds, on the trials' scores alone: the same seed and batch stop at the
            # same trial wherever the folds ran. A plateau at the last trial is no early stop.
            stopped = plateau(rows, patience, target) if len(rows) < trials else None
            if stopped is not None:
                say(f"fit: {stopped['text']}; {trials - len(rows)} trials not run")
        done = [r for r in rows if r["state"] == "complete"]
        if not done:
            raise FitError("no trial completed (every one pruned or with an empty band); run more trials")
        best = max(done, key=_rank)
        curve: list[dict] = []
        for w in space.windows:
            here = [r for r in done if r["window"] == w]
            if here:
                curve.append({"window": w, "fitted": max(here, key=_rank)})
        paper_jobs = []
        for point in curve:
            s: dict = point["fitted"]
            for bank in (whisker_bank(), cochlea_bank()):
                paper_jobs += [{**base, "bank": bank.to_dict(), "window": s["window"], "features": s["features"],
                                "hidden": s["hidden"], "epochs": s["epochs"], "fold": f}
                               for f in range(k)]
        say(f"fit: the paper's whisker and cochlea banks at {len(curve)} window(s), beside the best of each")
        tally(runner.wait(paper_warm))
        results = tally(runner.map(paper_jobs))
        for i, point in enumerate(curve):
            for j, name in enumerate(("whisker", "cochlea")):
                folds = results[(2 * i + j) * k: (2 * i + j + 1) * k]
                bank = whisker_bank() if name == "whisker" else cochlea_bank()
                point[name] = {"folds": k, **_summary(folds), "channels": bank.channels,
                               "beyond_band": int(channels_beyond_band(bank, min(_rate(r.path) for r in recs)).size)}
    forget_caches()
    if cache_dir is not None:
        for path in Path(cache_dir).glob("*.npy"):     # this fit's; the next computes its own
            path.unlink(missing_ok=True)
    paper = next(p for p in curve if p["window"] == best["window"])
    return {"fs": space.fs, "k": k, "seed": seed, "batch": batch, "target": target, "space": asdict(space),
            "rows": rows, "best": best, "curve": curve, "paper": {n: paper[n] for n in ("whisker", "cochlea")},
            "filterbank_runs": spent["filterbank_runs"], "recordings": len(recs), "seconds": time.perf_counter() - t0,
            "where": where, "trials": trials, "patience": patience, "stopped": stopped,
            "augment": None if augment is None else augment.to_dict(),
            "features_cpu_seconds": spent["features"], "networks_cpu_seconds": spent["networks"]}


def _params(p: dict) -> dict:
    return {"family": p.get("family"), "channels": p.get("channels"), "b_scale": p.get("b_scale"),
            "window": p.get("window"), "features": p.get("features"), "hidden": p.get("hidden"),
            "epochs": p.get("epochs")}


def _row(number: int, state: str, s: Setting, folds: list[dict], target: str) -> dict:
    summary = _summary(folds)
    # CPU to 0.1 ms: a pruned trial of one fold of a few epochs takes under 5 ms, which 2 decimals made 0.
    return {"trial": number, "state": state, "folds": len(folds), **asdict(s), **summary,
            "score": summary[f"{target}_mean"], "cpu_seconds": round(sum(f["cpu_seconds"] for f in folds), 4)}


def plateau(rows: list[dict], patience: int, target: str) -> dict | None:
    """Return whether the search has reached a plateau, and how.

    A plateau: the best complete trial's score is no more than its fold spread above the best of the trials
    before the last ``patience``.

    Parameters
    ----------
    rows : list of dict
        Every trial so far, in trial order (:func:`fit_search`'s rows).
    patience : int
        Trials; 0, or no more trials than ``patience``: never a plateau.
    target : {"window", "recording", "contact"}
        The score's accuracy, whose sd over the best trial's folds is the spread.

    Returns
    -------
    dict or None
        None while the best still moves (or nothing was complete ``patience`` trials ago); else
        ``trials`` (so far), ``patience``, ``spread`` and ``moved`` (accuracy, fractions) and ``text``,
        the sentence that says it.
    """
    if patience <= 0 or len(rows) <= patience:
        return None
    before = [r for r in rows[: len(rows) - patience] if r["state"] == "complete"]
    if not before:
        return None
    best = max((r for r in rows if r["state"] == "complete"), key=_rank)
    moved = best["score"] - max(before, key=_rank)["score"]
    spread = best[f"{target}_sd"]
    if moved > spread:
        return None
    return {"trials": len(rows), "patience": patience, "spread": spread, "moved": moved,
            "text": f"stopped after {len(rows)} trials: the best has not moved by more than the fold spread "
                    f"({spread:.3f}) for {patience} trials"}


def paper_verdict(result: dict) -> dict:
    """Return whether the search's best beats each of the paper's banks by more than a fold's spread.

    Each bank at its window, with its features and network; the spread is the larger of the two sds of the
    target over the folds.

    Parameters
    ----------
    result : dict
        What :func:`fit_search` returns.

    Returns
    -------
    dict
        ``beats`` (True when the best beats both banks by more than the spread); per bank (``whisker``,
        ``cochlea``) ``ahead`` (the best's mean minus the bank's, a fraction), ``spread`` and ``beats``;
        and ``text``, the sentences that say it.
    """
    t, b = result["target"], result["best"]
    banks = {}
    for name, p in result["paper"].items():
        ahead = b[f"{t}_mean"] - p[f"{t}_mean"]
        spread = max(b[f"{t}_sd"], p[f"{t}_sd"])
        banks[name] = {"ahead": ahead, "spread": spread, "beats": ahead > spread}
    beats = all(v["beats"] for v in banks.values())
    said = "; ".join(f"the {name} bank by {v['ahead']:+.3f}, {'more' if v['beats'] else 'not more'} than a fold's "
                     f"spread ({v['spread']:.3f})" for name, v in banks.items())
    text = (f"The best {'beats' if beats else 'does NOT beat'} the paper's banks by more than a fold's spread "
            f"({t} accuracy): {said}."
            + ("" if beats else " On these folds the search found nothing that a paper bank does not match "
               "within the folds' spread."))
    return {**banks, "beats": beats, "text": text}


def cpu_per_trial(rows: list[dict]) -> float | None:
    """Return the median CPU seconds of the complete trials, None before one is complete.

    A trial's CPU seconds: every fold's filterbank, features and network.
    """
    done = [r["cpu_seconds"] for r in rows if r["state"] == "complete"]
    return float(np.median(done)) if done else None


def _rank(row: dict):
    """Return a trial's sort key: best first by the target's mean (the search's objective).

    Then by window and recording accuracy, then the earlier trial.
    """
    return (row["score"], row["window_mean"], row["recording_mean"], -row["trial"])


def _describe(row: dict) -> str:
    return (f"{row['family']} {row['channels']} ch {row['f_low']:.4g}..{row['f_high']:.4g} Hz x{row['b_scale']:g}, "
            f"{row['window']:g} s, {row['features']}, {row['hidden']} hidden, {row['epochs']} epochs")


def _augment_line(augment: dict) -> str:
    """Return the report's line of the folds' gain augmentation (``augment``: :meth:`GainAugment.to_dict`)."""
    a = GainAugment.from_dict(augment, FitError)
    return (f"every fold's networks (the paper's banks' too) trained with gain augmentation: {a.copies} more copies "
            f"of each window, gains exp(N(0, {a.spread:g})) {a.gains} (as `train --augment-gains` trains the model)")


def format_search(result: dict) -> str:
    """Return the search's report: the best, the paper's banks beside it, the accuracy-vs-window curve."""
    t = result["target"]
    b, rows = result["best"], result["rows"]
    states = {s: sum(r["state"] == s for r in rows) for s in ("complete", "pruned", "empty band")}
    lines = [f"fit by grouped {result['k']}-fold cross-validation (seed {result['seed']}, rounds of "
             f"{result['batch']}), banks at {result['fs']:g} Hz, maximising {t} accuracy: {len(rows)} trials "
             f"({states['complete']} complete, {states['pruned']} pruned, {states['empty band']} with an empty "
             f"band) in {result['seconds']:.0f} s on {result['where']} ({cpu_per_trial(rows):.1f} CPU s per complete "
             f"trial, median); {result['filterbank_runs']} filterbank runs for {result['recordings']} recordings"
             + ("" if result["space"]["train_windows"] is None else
                f"; each fold's model trained on at most {result['space']['train_windows']} windows (--quick)"),
             *([] if not result.get("augment") else [_augment_line(result["augment"])]),
             *([] if not result.get("stopped") else
               [f"{result['stopped']['text']} (--patience {result['stopped']['patience']}; "
                f"{result['trials'] - len(rows)} of the {result['trials']} trials not run)"]),
             "",
             f"best (trial {b['trial']}): {_describe(b)}: windows {b['window_mean']:.3f} +- {b['window_sd']:.3f}, "
             f"recordings {b['recording_mean']:.3f} +- {b['recording_sd']:.3f}, contacts {b['contact_mean']:.3f}"]
    for name, p in result["paper"].items():
        lines.append(f"the paper's {name} bank (same window, features, network): windows {p['window_mean']:.3f} +- "
                     f"{p['window_sd']:.3f}, recordings {p['recording_mean']:.3f} +- {p['recording_sd']:.3f}, "
                     f"contacts {p['contact_mean']:.3f}"
                     + (f"; {p['beyond_band']} of its {p['channels']} channels lie above the recordings' band"
                        if p["beyond_band"] else ""))
    lines.append(paper_verdict(result)["text"])
    lines += ["", f"best {t} accuracy per window length (each window's best trial; the paper's banks with its "
                  "features and network)",
              f"{'window':>8}  {'fitted':>14}  {'whisker':>14}  {'cochlea':>14}  setting"]
    for p in result["curve"]:
        f, w, c = p["fitted"], p["whisker"], p["cochlea"]
        lines.append(f"{p['window']:>7g}s  {f[t + '_mean']:>7.3f} +-{f[t + '_sd']:.3f}  {w[t + '_mean']:>7.3f} +-"
                     f"{w[t + '_sd']:.3f}  {c[t + '_mean']:>7.3f} +-{c[t + '_sd']:.3f}  {_describe(f)}")
    return "\n".join(lines)


ROW_FIELDS = ("trial", "state", "folds", "family", "channels", "f_low", "f_high", "b_scale", "window", "features",
              "hidden", "epochs", "score", "window_mean", "window_sd", "recording_mean", "recording_sd",
              "contact_mean", "contact_sd", "cpu_seconds")


def write_search(result: dict, folder: Path) -> list[Path]:
    """Write the search's result into ``folder`` and return the files written.

    ``fit.csv`` (every trial), ``fit-curve.csv`` (best accuracy per window, beside the paper's banks),
    ``bank.json`` (the best bank, for ``train --bank``) and, where matplotlib is installed,
    ``fit-curve.png``.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "fit.csv", "w", newline="") as fh:
        rows = csv.DictWriter(fh, ROW_FIELDS, extrasaction="ignore", restval="")
        rows.writeheader()
        rows.writerows(result["rows"])
    t = result["target"]
    with open(folder / "fit-curve.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["window", "target", "fitted_mean", "fitted_sd", "whisker_mean", "whisker_sd", "cochlea_mean",
                    "cochlea_sd", "fitted_window_mean", "whisker_window_mean", "cochlea_window_mean", "trial",
                    "family", "channels", "f_low", "f_high", "b_scale", "features", "hidden", "epochs"])
        for p in result["curve"]:
            f = p["fitted"]
            w.writerow([p["window"], t, f[t + "_mean"], f[t + "_sd"], p["whisker"][t + "_mean"],
                        p["whisker"][t + "_sd"], p["cochlea"][t + "_mean"], p["cochlea"][t + "_sd"],
                        f["window_mean"], p["whisker"]["window_mean"], p["cochlea"]["window_mean"], f["trial"],
                        f["family"], f["channels"], f["f_low"], f["f_high"], f["b_scale"], f["features"],
                        f["hidden"], f["epochs"]])
    b = result["best"]
    best = Setting(**{name: b[name] for name in Setting.__dataclass_fields__})
    written = [folder / "fit.csv", folder / "fit-curve.csv", save_bank(folder / "bank.json", best.bank())]
    plt = pyplot_or_none()
    if plt is None:
        return written
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    x = [p["window"] for p in result["curve"]]
    for name, style in (("fitted", "o-"), ("cochlea", "s--"), ("whisker", "^:")):
        ax.errorbar(x, [p[name][t + "_mean"] for p in result["curve"]],
                    yerr=[p[name][t + "_sd"] for p in result["curve"]], fmt=style, capsize=3,
                    label={"fitted": "fitted (best trial)", "cochlea": "paper's cochlea",
                           "whisker": "paper's whisker"}[name])
    ax.set_xscale("log")
    ax.minorticks_off()
    ax.set_xticks(x, [f"{v:g}" for v in x])
    ax.set_xlabel("window (s): the decision's latency")
    ax.set_ylabel(f"{t} accuracy (grouped {result['k']}-fold CV)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(folder / "fit-curve.png", dpi=110)
    plt.close(fig)
    return written + [folder / "fit-curve.png"]
