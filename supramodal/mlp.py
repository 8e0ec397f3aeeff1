"""Multilayer perceptron trained with batch iRPROP-, after FANN 2.x's defaults (paper Sect. 4.1).

What follows FANN (read from its source, see docs/model.md):

* logistic units in the hidden and output layers, ``1 / (1 + exp(-2 s x))`` with
  steepness ``s = 0.5``; weights and biases uniform in [-0.1, 0.1];
* targets 1 for the true class, 0 otherwise;
* FANN's "tanh" error function: the output error ``e = t - y`` is replaced by
  ``ln((1 + e) / (1 - e))``, or +-17 when ``|e| > 0.9999999``;
* unit derivatives ``2 s y (1 - y)`` with ``y`` clipped to [0.01, 0.99];
* iRPROP- constants: increase 1.2, decrease 0.5, step min 0, max 50, initial 0.1,
  the previous step floored at 1e-4 before each update, weights clipped to +-1500.

Where this differs from FANN, by choice:

* the exact logistic function instead of FANN_SIGMOID_STEPWISE, its
  piecewise-linear approximation (which existed only to save time on 2003 CPUs);
* textbook iRPROP- (Igel & Huesken 2000) on a sign change: the step shrinks, the
  gradient is forgotten and the weight is *not* moved that epoch (FANN moves it
  by the new step in the positive direction, an artefact of its ``slope = 0``
  branch); with an unchanged sign or a zero product the step grows or is kept
  as the textbook says.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from supramodal.errors import InputError

#: iRPROP- epochs when none are asked for (the one home of this default; the paper trains 500).
DEFAULT_EPOCHS = 500
#: Epochs without a better held-out error after which a network with held-out rows stops
#: (:func:`train_mlp`'s ``stop_on``): the default of a calibrated model's fold networks. Counted in
#: looks at the error, :data:`STOP_CHECK_EPOCHS` apart (a patience of 15 waits 20 epochs).
EARLY_STOP_PATIENCE = 100
#: Epochs between two looks at the held-out error of a network that may stop early.
STOP_CHECK_EPOCHS = 10
STEEPNESS = 0.5
INIT_RANGE = 0.1
RPROP_INCREASE = 1.2
RPROP_DECREASE = 0.5
RPROP_DELTA_MIN = 0.0
RPROP_DELTA_MAX = 50.0
RPROP_DELTA_ZERO = 0.1
RPROP_STEP_FLOOR = 1e-4
WEIGHT_LIMIT = 1500.0
ERROR_CLIP = 17.0


def sigmoid(x, steepness: float = STEEPNESS):
    """FANN_SIGMOID: ``1 / (1 + exp(-2 s x))``, computed without overflow."""
    z = 2 * steepness * np.asarray(x, dtype=np.float64)
    return 0.5 * (1 + np.tanh(0.5 * z))


def sigmoid_derivative(y, steepness: float = STEEPNESS):
    """FANN's derivative from the unit's output, ``2 s y (1 - y)`` with y clipped to [0.01, 0.99]."""
    y = np.clip(y, 0.01, 0.99)
    return 2 * steepness * y * (1 - y)


def tanh_error(e):
    """FANN_ERRORFUNC_TANH: ``ln((1 + e) / (1 - e))``, +-17 beyond +-0.9999999."""
    e = np.asarray(e, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):   # e = +-1: the clip below answers
        out = np.log((1 + e) / (1 - e), out=np.empty_like(e))
    out[e > 0.9999999] = ERROR_CLIP
    out[e < -0.9999999] = -ERROR_CLIP
    return out


def logistic_in_place(a: np.ndarray, steepness: float = STEEPNESS) -> np.ndarray:
    """:func:`sigmoid` of the float64 array ``a``, written over ``a`` (returned), as ``1 / (1 + exp(-z))``.

    What training computes its units with: the exponential and four in-place passes cost a third
    of ``tanh`` and its temporaries, and the values are :func:`sigmoid`'s to about 1e-16 (more
    accurate deep in the negative tail, where ``0.5 (1 + tanh)`` cancels). iRPROP- moves each
    weight by the sign of its gradient alone, so a network trained with either is the same
    (tests/test_mlp.py trains the plain loop beside it).
    """
    if steepness != 0.5:
        a *= 2 * steepness
    np.negative(a, out=a)
    with np.errstate(over="ignore"):                        # z < -709: exp(-z) = inf, the unit exactly 0
        np.exp(a, out=a)
    a += 1.0
    return np.reciprocal(a, out=a)


@dataclass
class MLP:
    """A three-layer perceptron: inputs -> logistic hidden layer -> logistic outputs.

    Attributes
    ----------
    w1 : ndarray, shape (inputs, hidden)
    b1 : ndarray, shape (hidden,)
    w2 : ndarray, shape (hidden, outputs)
    b2 : ndarray, shape (outputs,)
    """

    w1: np.ndarray
    b1: np.ndarray
    w2: np.ndarray
    b2: np.ndarray

    @classmethod
    def create(cls, inputs: int, hidden: int, outputs: int, seed=None) -> MLP:
        """FANN-style random start: every weight and bias uniform in [-0.1, 0.1]."""
        for name, v in (("inputs", inputs), ("hidden", hidden), ("outputs", outputs)):
            if v < 1:
                raise InputError(f"{name} must be >= 1, got {v}")
        rng = np.random.default_rng(seed)

        def u(*shape: int) -> np.ndarray:
            return rng.uniform(-INIT_RANGE, INIT_RANGE, size=shape)

        return cls(u(inputs, hidden), u(hidden), u(hidden, outputs), u(outputs))

    @property
    def shape(self) -> tuple[int, int, int]:
        """The network's layers: ``(inputs, hidden, outputs)``."""
        return (self.w1.shape[0], self.w1.shape[1], self.w2.shape[1])

    def forward(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hidden and output activations for inputs ``x`` of shape (n, inputs)."""
        h = sigmoid(x @ self.w1 + self.b1)
        return h, sigmoid(h @ self.w2 + self.b2)

    def outputs(self, x: np.ndarray) -> np.ndarray:
        """Output activations in [0, 1], shape (n, outputs)."""
        return self.forward(np.asarray(x, dtype=np.float64))[1]

    def logits(self, x: np.ndarray) -> np.ndarray:
        """Return the output units' logits ``z``, ``outputs = 1 / (1 + exp(-z))``, shape (n, outputs).

        Finite where the outputs round to exactly 0.0 or 1.0: what calibrated posteriors are
        computed from (:mod:`supramodal.calibration`). Their argmax is the outputs' wherever the
        outputs' is unique (outputs that all round to 1.0 tie; their logits still differ).
        """
        h = sigmoid(np.asarray(x, dtype=np.float64) @ self.w1 + self.b1)
        return 2 * STEEPNESS * (h @ self.w2 + self.b2)

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Winner-take-all class index, shape (n,)."""
        return np.argmax(self.outputs(x), axis=1)

    def params(self) -> list[np.ndarray]:
        """Return the weights and biases, ``[w1, b1, w2, b2]`` (the arrays themselves, not copies)."""
        return [self.w1, self.b1, self.w2, self.b2]

    def gradients(self, x: np.ndarray, targets: np.ndarray) -> tuple[list[np.ndarray], float]:
        """Batch gradient of FANN's (tanh-error) objective, summed over samples, and the plain MSE.

        The sign convention is that of a gradient: a weight moves against it.
        """
        h = logistic_in_place(x @ self.w1 + self.b1)
        y = logistic_in_place(h @ self.w2 + self.b2)
        diff = targets - y
        mse = float(np.mean(diff**2))
        delta2 = tanh_error(diff)
        delta2 *= sigmoid_derivative(y)                             # (n, outputs)
        delta1 = delta2 @ self.w2.T
        delta1 *= sigmoid_derivative(h)                             # (n, hidden)
        # FANN accumulates "slopes" = delta * input (a descent direction); the gradient is minus that.
        return [-(x.T @ delta1), -delta1.sum(0), -(h.T @ delta2), -delta2.sum(0)], mse


@dataclass(frozen=True)
class Ensemble:
    """Networks of one shape on the same inputs, deciding together by the mean of their logits.

    What a calibrated model deploys (:meth:`supramodal.model.TextureModel.train`): its calibration's
    fold networks, each trained on all but one fold of the windows, so that the map fitted on their
    held-out logits is the deployed networks' own. The mean of logits, not of outputs: a member sure
    of a class (logit +40) and one unsure of it (logit -1) give a mean that is still sure, where the
    mean of outputs would halve it; the calibration map then says how sure the mean is.

    Attributes
    ----------
    members : tuple of MLP
        At least one, all of the same :attr:`MLP.shape`.
    """

    members: tuple[MLP, ...]

    def __post_init__(self) -> None:
        if not self.members:
            raise InputError("an ensemble needs at least one network")
        shapes = {m.shape for m in self.members}
        if len(shapes) > 1:
            raise InputError(f"an ensemble's networks must have one shape, got {sorted(shapes)}")

    @property
    def shape(self) -> tuple[int, int, int]:
        """The members' layers: ``(inputs, hidden, outputs)``."""
        return self.members[0].shape

    def logits(self, x: np.ndarray) -> np.ndarray:
        """Return the mean of the members' logits (:meth:`MLP.logits`), shape (n, outputs)."""
        x = np.asarray(x, dtype=np.float64)
        z = self.members[0].logits(x)
        for m in self.members[1:]:
            z += m.logits(x)
        z /= len(self.members)
        return z

    def outputs(self, x: np.ndarray) -> np.ndarray:
        """Return the output units' activations of the mean logits (:func:`sigmoid`), in [0, 1], shape (n, outputs)."""
        return sigmoid(self.logits(x) / (2 * STEEPNESS))

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Winner-take-all class index, shape (n,) (the largest mean logit)."""
        return np.argmax(self.logits(x), axis=1)

    def params(self) -> list[np.ndarray]:
        """Return every member's :meth:`MLP.params`, member after member (the arrays themselves)."""
        return [p for m in self.members for p in m.params()]

    def stacked(self) -> list[np.ndarray]:
        """Return ``[w1, b1, w2, b2]``, each the members' arrays stacked on a first axis (a model file's)."""
        return [np.stack(ps) for ps in zip(*(m.params() for m in self.members))]


def rescaled(net: MLP, mean, scale, to_mean, to_scale) -> MLP:
    """Return ``net``, trained on inputs ``(x - mean) / scale``, as the same function of ``(x - to_mean) / to_scale``.

    Exact but for rounding: with ``u = (x - mean) / scale = v (to_scale / scale) + (to_mean - mean) / scale``
    for ``v = (x - to_mean) / to_scale``, the first layer's weights are scaled by row and its biases moved.
    What lets an :class:`Ensemble`'s members, each standardised by its own fold's windows, share one
    input scaling.
    """
    mean, scale, to_mean, to_scale = (np.asarray(a, dtype=np.float64) for a in (mean, scale, to_mean, to_scale))
    return MLP(net.w1 * (to_scale / scale)[:, None], net.b1 + ((to_mean - mean) / scale) @ net.w1,
               net.w2.copy(), net.b2.copy())


@dataclass
class IRpropMinus:
    """Batch iRPROP- state for a list of parameter arrays (updated in place)."""

    params: list[np.ndarray]
    increase: float = RPROP_INCREASE
    decrease: float = RPROP_DECREASE
    delta_min: float = RPROP_DELTA_MIN
    delta_max: float = RPROP_DELTA_MAX
    delta_zero: float = RPROP_DELTA_ZERO
    steps: list[np.ndarray] = field(init=False)
    previous: list[np.ndarray] = field(init=False)

    def __post_init__(self) -> None:
        self.steps = [np.full_like(p, self.delta_zero) for p in self.params]
        self.previous = [np.zeros_like(p) for p in self.params]

    def step(self, grads: list[np.ndarray]) -> None:
        """One update from the batch gradients ``grads`` (same shapes as the parameters)."""
        for p, g, step, prev in zip(self.params, grads, self.steps, self.previous):
            g = g.copy()
            np.maximum(step, RPROP_STEP_FLOOR, out=step)             # FANN: a zero step would stop learning
            same = g * prev
            grow, shrink = same > 0, same < 0
            step[grow] = np.minimum(step[grow] * self.increase, self.delta_max)
            step[shrink] = np.maximum(step[shrink] * self.decrease, self.delta_min)
            g[shrink] = 0.0                                           # iRPROP-: forget, do not move
            p -= np.sign(g) * step
            np.clip(p, -WEIGHT_LIMIT, WEIGHT_LIMIT, out=p)
            prev[...] = g


def one_hot(labels: np.ndarray, n_classes: int) -> np.ndarray:
    """Targets: 1 for the true class, 0 otherwise, shape (n, n_classes)."""
    labels = np.asarray(labels)
    t = np.zeros((labels.size, n_classes))
    t[np.arange(labels.size), labels] = 1.0
    return t


def held_out_mse(net: MLP, x: np.ndarray, targets: np.ndarray) -> float:
    """Return the mean squared error of ``net``'s outputs on rows ``x`` (m, inputs) against ``targets`` (m, outputs)."""
    return float(np.mean((targets - net.outputs(x)) ** 2))


def train_mlp(x: np.ndarray, labels: np.ndarray, n_classes: int, hidden: int | None = None,
              epochs: int = DEFAULT_EPOCHS, seed=None, desired_mse: float = 0.0,
              progress=None, stop_on=None, patience: int = EARLY_STOP_PATIENCE,
              on_check=None) -> tuple[MLP, list[float]]:
    """Train an MLP by batch iRPROP- on (already scaled) inputs.

    With held-out rows (``stop_on``), training stops early: every :data:`STOP_CHECK_EPOCHS` epochs
    the network's mean squared error on those rows is measured, and once it has not improved for
    ``patience`` epochs the network of the best measure is returned. Without, every epoch is
    trained (the paper's 500), unless ``desired_mse`` is reached.

    Parameters
    ----------
    x : ndarray, shape (n, inputs)
    labels : ndarray of int, shape (n,)
        Class indices in ``0 .. n_classes - 1``.
    hidden : int, optional
        Hidden units (default: as many as inputs, as in the paper).
    epochs : int
        Maximum number of batch epochs (default :data:`DEFAULT_EPOCHS`).
    seed : int or None
        Seed of the initial weights; the result is deterministic given it.
    desired_mse : float
        Stop early once the training MSE falls below it (FANN's desired error; 0 = never).
    progress : callable(epoch, mse), optional
    stop_on : (ndarray, ndarray of int), optional
        Held-out rows, shape (m, inputs), scaled as ``x``, and their labels, shape (m,): what the
        network's error is watched on to stop (a calibration fold's held-out windows). Default: none.
    patience : int
        Epochs without a lower held-out error before stopping (default :data:`EARLY_STOP_PATIENCE`);
        only with ``stop_on``.
    on_check : callable(epochs, error), optional
        With ``stop_on``: told each look at the held-out error, once per number of epochs looked at.

    Returns
    -------
    (MLP, list of float)
        The network and the training MSE before each of its epochs' updates: with ``stop_on``,
        the network of the lowest held-out error and the epochs that made it (the epochs trained
        past it, to see that it stayed the lowest, are not returned).
    """
    x, labels = _checked_rows(x, labels, n_classes, "training inputs", "labels", "n", "inputs")
    if epochs < 1:
        raise InputError(f"epochs must be >= 1, got {epochs}")
    net = MLP.create(x.shape[1], hidden or x.shape[1], n_classes, seed=seed)
    opt = IRpropMinus(net.params())
    targets = one_hot(labels, n_classes)
    history: list[float] = []
    watch = None if stop_on is None else _StopWatch(net, stop_on[0], stop_on[1], n_classes, x.shape[1], patience,
                                                    on_check)
    updates = 0
    for epoch in range(epochs):
        grads, mse = net.gradients(x, targets)
        history.append(mse)
        if progress is not None:
            progress(epoch, mse)
        if mse < desired_mse:
            break
        opt.step(grads)
        updates += 1
        if watch is not None and watch.stop(updates):
            break
    if watch is None:
        return net, history
    watch.stop(updates, final=True)
    return watch.best, history[:max(watch.best_epochs, 1)]     # the start's own MSE if it stayed the best


def _checked_rows(x, labels, n_classes: int, rows: str, labelled: str, n: str, inputs) -> tuple[np.ndarray, np.ndarray]:
    """Return rows ``x`` (n >= 1, ``inputs``) as float64 and their integer ``labels`` (n,), or refuse them by name.

    ``rows`` and ``labelled`` name them in the messages, ``n`` their count; ``inputs``: the columns
    required (an int), or a name for any number of them.
    """
    x = np.asarray(x, dtype=np.float64)
    labels = np.asarray(labels)
    if x.ndim != 2 or len(x) == 0 or (isinstance(inputs, int) and x.shape[1] != inputs):
        raise InputError(f"{rows} must have shape ({n} >= 1, {inputs}), got {x.shape}")
    if labels.shape != (len(x),) or labels.dtype.kind not in "iu":
        raise InputError(f"{labelled} must be integers of shape ({len(x)},), got {labels.dtype} {labels.shape}")
    if labels.min() < 0 or labels.max() >= n_classes:
        raise InputError(f"{labelled} must lie in 0..{n_classes - 1}")
    if not np.isfinite(x).all():
        raise InputError(f"{rows} contain NaN or Inf")
    return x, labels


class _StopWatch:
    """The held-out error of a network in training, every :data:`STOP_CHECK_EPOCHS` epochs, and the best so far."""

    def __init__(self, net: MLP, x_held, labels_held, n_classes: int, inputs: int, patience: int,
                 on_check=None) -> None:
        x_held, labels_held = _checked_rows(x_held, labels_held, n_classes, "held-out rows to stop on",
                                            "held-out labels", "m", inputs)
        if isinstance(patience, bool) or not isinstance(patience, int | np.integer) or patience < 1:
            raise InputError(f"patience must be a whole number of epochs >= 1, got {patience!r}")
        self.net, self.x, self.targets, self.patience = net, x_held, one_hot(labels_held, n_classes), int(patience)
        self.best, self.best_epochs, self.best_error = MLP(*[p.copy() for p in net.params()]), 0, np.inf
        self.on_check, self.looked = on_check, -1

    def stop(self, epochs: int, final: bool = False) -> bool:
        """Look at the network after ``epochs`` epochs if it is time (or ``final``); return whether to stop."""
        if epochs % STOP_CHECK_EPOCHS and not final:
            return False
        if epochs == self.looked:                     # the last look, at epochs already looked at
            return epochs - self.best_epochs >= self.patience
        error = held_out_mse(self.net, self.x, self.targets)
        self.looked = epochs
        if self.on_check is not None:
            self.on_check(epochs, error)
        if error < self.best_error:
            self.best_error, self.best_epochs = error, epochs
            for kept, p in zip(self.best.params(), self.net.params()):
                kept[...] = p
        return epochs - self.best_epochs >= self.patience


@dataclass(frozen=True)
class NetworkTask:
    """One network to train, as data: what :func:`train_mlp` is given, and the rows to score with it.

    A task can be sent to a worker process (:func:`supramodal.parallel.map_in_processes`), and
    :func:`train_task` gives the same network wherever it runs.

    Attributes
    ----------
    x : ndarray, shape (n, inputs)
        Scaled training inputs.
    labels : ndarray of int, shape (n,)
    n_classes, hidden, epochs, seed
        As :func:`train_mlp`'s.
    score : ndarray, shape (m, inputs), optional
        Scaled rows whose logits the trained network gives back (a calibration fold's held-out
        windows).
    score_labels : ndarray of int, shape (m,), optional
        The labels of ``score``'s rows: with them, training stops early on those rows
        (:func:`train_mlp`'s ``stop_on``, with ``patience``).
    patience : int
        As :func:`train_mlp`'s (default :data:`EARLY_STOP_PATIENCE`).
    """

    x: np.ndarray
    labels: np.ndarray
    n_classes: int
    hidden: int | None = None
    epochs: int = DEFAULT_EPOCHS
    seed: int | None = None
    score: np.ndarray | None = None
    score_labels: np.ndarray | None = None
    patience: int = EARLY_STOP_PATIENCE

    @property
    def stops_early(self) -> bool:
        """Whether the network stops on its held-out rows (it has rows to score and their labels)."""
        return self.score is not None and self.score_labels is not None

    @property
    def work(self) -> float:
        """Multiply-adds of the training, about: what it costs against starting a process.

        A network that stops early is counted at :func:`expected_epochs`.
        """
        inputs = self.x.shape[1]
        hidden = self.hidden or inputs
        epochs = expected_epochs(self.epochs, self.patience if self.stops_early else None)
        return float(len(self.x)) * hidden * (inputs + self.n_classes) * epochs


def expected_epochs(epochs: int, patience: int | None) -> int:
    """Return the epochs a network is expected to train: ``epochs``, or about twice ``patience`` if it stops early."""
    return epochs if patience is None else min(epochs, 2 * patience)


class Trained(NamedTuple):
    """What :func:`train_task` gives back: the network, its training and its held-out rows' logits."""

    #: The network (where it stopped early, the one of its lowest held-out error; trained again to other
    #: epochs by :func:`~supramodal.calibration.train_fold_networks`, that one).
    network: MLP
    #: :func:`train_mlp`'s training MSE per epoch of ``network``.
    history: list[float]
    #: Logits of the task's ``score`` rows, shape (m, outputs); None without rows to score.
    logits: np.ndarray | None
    #: Where it stopped early: ``(epochs, held-out MSE)`` of every look of its (first) training, in order;
    #: else empty.
    held_out_errors: tuple[tuple[int, float], ...] = ()


def train_task(task: NetworkTask, progress=None) -> Trained:
    """Train ``task``'s network; return it, its training MSE per epoch and the logits of ``task.score``.

    The MSE is :func:`train_mlp`'s; the logits are None without rows to score. With the scored
    rows' labels, the network stops early on them (:attr:`NetworkTask.stops_early`) and the
    held-out errors it looked at come back too.
    """
    stop_on = (task.score, task.score_labels) if task.stops_early else None
    looks: list[tuple[int, float]] = []
    net, history = train_mlp(task.x, task.labels, task.n_classes, hidden=task.hidden, epochs=task.epochs,
                             seed=task.seed, progress=progress, stop_on=stop_on, patience=task.patience,
                             on_check=lambda epochs, error: looks.append((epochs, error)))
    return Trained(net, history, None if task.score is None else net.logits(task.score), tuple(looks))


#: Multiply-adds (:attr:`NetworkTask.work`) of a set of networks worth worker processes: about 2 s
#: of one core here, against about 0.3 s to start a spawned worker that imports numpy.
PARALLEL_MIN_WORK = 1e9


def train_networks(tasks, jobs: int = 1, watch=None, done=None, work: float | None = None) -> list:
    """Train every task (:func:`train_task`), over ``jobs`` worker processes where the work is worth them.

    The work is worth them from :data:`PARALLEL_MIN_WORK`; the networks are the same for any
    ``jobs``.

    Workers take the tasks in their order: put last a task whose result is needed last, so that
    what the caller does in ``done`` with the others runs while it trains.

    Parameters
    ----------
    tasks : iterable of NetworkTask
        Taken one by one as they are trained (a generator keeps only a few in memory), unless
        ``work`` is not given: then all at once, to sum their work.
    jobs : int
        Worker processes at most (:func:`supramodal.parallel.map_in_processes`); 1: in this process.
    watch : (int, callable(epoch, mse)), optional
        A task's index and its :func:`train_mlp` progress: every epoch in this process; from a
        worker, when the network is back, the last epoch of the network kept alone (of a network
        that stopped early, the epoch of its lowest held-out error, not the last one trained).
    done : callable(int, result), optional
        Told each task's index and result as it is back: in the order of ``tasks`` in this
        process, in the order they finish from workers.
    work : float, optional
        The tasks' :attr:`NetworkTask.work` summed, and more than one task (default: from the tasks).

    Returns
    -------
    list of Trained
        :func:`train_task`'s results, in the order of ``tasks``.
    """
    from supramodal.parallel import map_in_processes

    if work is None:
        tasks = list(tasks)
        work = sum(t.work for t in tasks) if len(tasks) > 1 else 0.0
    watched, progress = watch if watch is not None else (-1, None)
    if jobs == 1 or work < PARALLEL_MIN_WORK:
        results = []
        for i, task in enumerate(tasks):
            results.append(train_task(task, progress if i == watched else None))
            if done is not None:
                done(i, results[-1])
        return results

    def back(i, result) -> None:
        if i == watched and progress is not None:
            progress(len(result[1]) - 1, result[1][-1])
        if done is not None:
            done(i, result)

    return map_in_processes(train_task, tasks, jobs, done=back)
