"""The MLP and iRPROP-: gradients against the objective they descend, one step by hand, learning."""

import math

import numpy as np
import pytest

from supramodal.errors import InputError
from supramodal.mlp import (
    ERROR_CLIP,
    MLP,
    STOP_CHECK_EPOCHS,
    IRpropMinus,
    NetworkTask,
    logistic_in_place,
    one_hot,
    sigmoid,
    sigmoid_derivative,
    tanh_error,
    train_mlp,
    train_task,
)


def fann_objective(net, x, targets):
    """The objective whose gradient FANN's tanh error function follows.

    FANN's output delta is ln((1+e)/(1-e)) * y' with e = t - y. Since d/de [(1+e) ln(1+e) + (1-e) ln(1-e)]
    = ln(1+e) + 1 - ln(1-e) - 1 = ln((1+e)/(1-e)) and de/dy = -1, that delta is -dE/dy * y' for
    E = sum over samples and outputs of (1+e) ln(1+e) + (1-e) ln(1-e): not the MSE. (Valid while
    |e| < 0.9999999 and the units stay in [0.01, 0.99], where FANN clips nothing.)
    """
    _, y = net.forward(x)
    e = targets - y
    return float(np.sum((1 + e) * np.log1p(e) + (1 - e) * np.log1p(-e)))


def fixed_net(inputs, hidden, outputs, seed, scale=1.0):
    rng = np.random.default_rng(seed)
    u = lambda *shape: rng.uniform(-scale, scale, size=shape)
    return MLP(u(inputs, hidden), u(hidden), u(hidden, outputs), u(outputs))


# -- units and error function ------------------------------------------------------------------

def test_sigmoid_is_fanns_logistic_with_steepness_half():
    x = np.array([-30.0, -2.0, 0.0, 0.7, 40.0, 800.0])
    # 0.5 (1 + tanh(x/2)): accurate to 1e-16 absolute (not relative deep in the negative tail,
    # 2e-4 relative at x = -30, which no classifier output can notice)
    np.testing.assert_allclose(sigmoid(x), 1 / (1 + np.exp(-x)), rtol=1e-15, atol=1e-16)
    assert np.isfinite(sigmoid(np.array([-1e6, 1e6]))).all()           # no overflow
    y = np.array([0.001, 0.3, 0.5, 0.995])
    np.testing.assert_allclose(sigmoid_derivative(y), [0.01 * 0.99, 0.3 * 0.7, 0.25, 0.99 * 0.01], rtol=1e-15)


def test_training_units_are_the_logistic_function_to_the_last_bits():
    """logistic_in_place against mpmath at 50 digits, across the range, the tails included."""
    mpmath = pytest.importorskip("mpmath")
    mpmath.mp.dps = 50
    x = np.concatenate([np.linspace(-40, 40, 801), [-745.0, -700.0, -300.0, 300.0, 710.0, 1e6, -1e6]])
    want = np.array([float(1 / (1 + mpmath.exp(-mpmath.mpf(float(v))))) for v in x])
    with np.errstate(all="raise", under="ignore"):          # no overflow is reported (an underflow is 0)
        got = logistic_in_place(x.copy())
    np.testing.assert_allclose(got, want, rtol=4e-16, atol=1e-300)        # exp(-745): 0 for a subnormal
    assert got[-1] == 0.0 and got[-2] == 1.0
    steep = logistic_in_place(x[:801].copy(), steepness=2.0)            # 1 / (1 + exp(-4 x))
    np.testing.assert_allclose(steep, [float(1 / (1 + mpmath.exp(-4 * mpmath.mpf(float(v))))) for v in x[:801]],
                               rtol=4e-16, atol=0)
    np.testing.assert_allclose(got[:801], sigmoid(x[:801]), rtol=0, atol=3e-16)     # sigmoid's values


def test_tanh_error_and_its_clip():
    e = np.array([-0.5, 0.0, 0.25, 0.99999989, 0.99999991, -0.9999999001, 1.0, -1.0])
    out = tanh_error(e)
    assert out[0] == pytest.approx(math.log(0.5 / 1.5))
    assert out[1] == 0.0
    assert out[2] == pytest.approx(math.log(1.25 / 0.75))
    assert out[3] == pytest.approx(math.log(1.99999989 / 0.00000011), rel=1e-6)
    assert out[4:].tolist() == [17.0, -17.0, 17.0, -17.0]


# -- gradients ---------------------------------------------------------------------------------

def test_gradients_by_hand_on_a_1_1_1_net():
    net = MLP(np.array([[0.5]]), np.array([-0.2]), np.array([[0.8]]), np.array([0.1]))
    x, t = np.array([[1.5]]), np.array([[1.0]])
    s1 = 0.5 * 1.5 - 0.2
    h = 1 / (1 + math.exp(-s1))
    s2 = 0.8 * h + 0.1
    y = 1 / (1 + math.exp(-s2))
    e = 1.0 - y
    d2 = math.log((1 + e) / (1 - e)) * y * (1 - y)          # FANN's output delta
    d1 = d2 * 0.8 * h * (1 - h)                             # back through w2 and the hidden unit
    grads, mse = net.gradients(x, t)
    assert mse == pytest.approx(e * e, rel=1e-14)
    expected = [-d1 * 1.5, -d1, -d2 * h, -d2]                # gradient = minus FANN's slopes
    for g, want in zip(grads, expected):
        assert g.item() == pytest.approx(want, rel=1e-13)


def test_gradients_are_the_gradient_of_fanns_tanh_objective():
    net = fixed_net(3, 4, 2, seed=1)
    rng = np.random.default_rng(2)
    x = rng.standard_normal((7, 3))
    targets = one_hot(rng.integers(0, 2, 7), 2)
    grads, _ = net.gradients(x, targets)
    h = 1e-6
    for p, g in zip(net.params(), grads):
        numeric = np.zeros_like(p)
        for idx in np.ndindex(p.shape):
            old = p[idx]
            p[idx] = old + h
            up = fann_objective(net, x, targets)
            p[idx] = old - h
            down = fann_objective(net, x, targets)
            p[idx] = old
            numeric[idx] = (up - down) / (2 * h)
        np.testing.assert_allclose(g, numeric, rtol=1e-6, atol=1e-8)


def test_gradients_are_not_those_of_the_mse():
    """The point of the tanh error: far from the target it pushes harder than the MSE does."""
    net = fixed_net(2, 2, 1, seed=3)
    x = np.array([[0.3, -0.4]])
    t = np.array([[1.0]])
    grads, _ = net.gradients(x, t)
    _, y = net.forward(x)
    h = net.forward(x)[0]
    mse_grad_w2 = -(t - y) * y * (1 - y) * h.T          # d/dw2 of (t - y)^2 / 2
    assert not np.allclose(grads[2], mse_grad_w2, rtol=1e-3)
    e = (t - y).item()
    ratio = grads[2] / mse_grad_w2
    np.testing.assert_allclose(ratio, math.log((1 + e) / (1 - e)) / e, rtol=1e-12)


# -- iRPROP- -----------------------------------------------------------------------------------

def test_one_irprop_step_on_a_tiny_net_by_hand():
    net = MLP(np.array([[0.5]]), np.array([-0.2]), np.array([[0.8]]), np.array([0.1]))
    before = [p.copy() for p in net.params()]
    opt = IRpropMinus(net.params())
    x, t = np.array([[1.5]]), np.array([[1.0]])
    g1, _ = net.gradients(x, t)
    opt.step(g1)
    # First step: no previous gradient (product 0): the step stays at delta_zero = 0.1, the weight
    # moves against the gradient's sign. Output below target: every gradient here is negative.
    assert all(g.item() < 0 for g in g1)
    for p, b in zip(net.params(), before):                 # updated in place, the net's own arrays
        assert p.item() == pytest.approx(b.item() + 0.1, abs=1e-15)
    assert [s.item() for s in opt.steps] == [0.1] * 4
    g2, _ = net.gradients(x, t)
    opt.step(g2)                                            # same sign again: the step grows to 0.12
    for p, b in zip(net.params(), before):
        assert p.item() == pytest.approx(b.item() + 0.1 + 0.12, abs=1e-15)
    assert [s.item() for s in opt.steps] == pytest.approx([0.12] * 4, abs=1e-15)


def test_irprop_grow_keep_shrink_forget():
    p = np.zeros(4)
    opt = IRpropMinus([p])
    opt.step([np.array([1.0, -1.0, 0.0, 1.0])])
    np.testing.assert_allclose(p, [-0.1, 0.1, 0.0, -0.1])
    np.testing.assert_allclose(opt.steps[0], [0.1, 0.1, 0.1, 0.1])
    opt.step([np.array([2.0, -3.0, 5.0, -1.0])])
    # 0, 1: same sign -> x1.2 and move; 2: previous 0 -> keep 0.1 and move; 3: sign change -> x0.5,
    # weight NOT moved, gradient forgotten
    np.testing.assert_allclose(opt.steps[0], [0.12, 0.12, 0.1, 0.05])
    np.testing.assert_allclose(p, [-0.22, 0.22, -0.1, -0.1])
    np.testing.assert_array_equal(opt.previous[0], [2.0, -3.0, 5.0, 0.0])
    opt.step([np.array([1.0, -1.0, 1.0, -1.0])])
    # 3: the forgotten gradient makes the product 0: keep 0.05 and move by it
    np.testing.assert_allclose(opt.steps[0], [0.144, 0.144, 0.12, 0.05])
    np.testing.assert_allclose(p, [-0.364, 0.364, -0.22, -0.05])


def test_irprop_step_is_clipped_at_50_and_floored_at_1e4():
    p = np.zeros(3)
    opt = IRpropMinus([p])
    opt.steps[0][:] = [45.0, 1e-6, 1e-6]
    opt.previous[0][:] = [1.0, 1.0, 1.0]
    opt.step([np.array([1.0, 1.0, -1.0])])
    # 45 * 1.2 = 54 -> 50; 1e-6 floored to 1e-4 first, then * 1.2; the third shrinks from the floor
    np.testing.assert_allclose(opt.steps[0], [50.0, 1.2e-4, 0.5e-4], rtol=1e-15)
    np.testing.assert_allclose(p, [-50.0, -1.2e-4, 0.0], rtol=1e-15)
    opt.step([np.array([1.0, 1.0, -1.0])])
    np.testing.assert_allclose(opt.steps[0], [50.0, 1.44e-4, 1e-4], rtol=1e-15)   # kept, floored again
    np.testing.assert_allclose(p, [-100.0, -2.64e-4, 1e-4], rtol=1e-15)


def test_weights_are_clipped_to_1500():
    p = np.array([1499.0, -1499.0])
    opt = IRpropMinus([p])
    opt.steps[0][:] = 50.0
    opt.step([np.array([-1.0, 1.0])])
    np.testing.assert_array_equal(p, [1500.0, -1500.0])


# -- learning ----------------------------------------------------------------------------------

def blobs(seed, n_per_class=60):
    rng = np.random.default_rng(seed)
    centres = np.array([[3.0, 0.0, 0.0, 1.0], [0.0, 3.0, -1.0, 0.0], [-2.0, -2.0, 2.0, -1.0]])
    x = np.concatenate([c + 0.5 * rng.standard_normal((n_per_class, 4)) for c in centres])
    y = np.repeat(np.arange(3), n_per_class)
    return x, y


def test_learns_separable_gaussian_blobs():
    x, y = blobs(0)
    xt, yt = blobs(1)
    net, history = train_mlp(x, y, 3, epochs=300, seed=0)
    assert net.shape == (4, 4, 3)                       # hidden = inputs, as in the paper
    assert len(history) == 300
    assert history[-1] < 0.02 and history[-1] < history[0] / 5
    assert np.mean(net.predict(x) == y) == 1.0
    assert np.mean(net.predict(xt) == yt) >= 0.98


def test_training_is_deterministic_given_a_seed():
    x, y = blobs(2)
    a, ha = train_mlp(x, y, 3, epochs=50, seed=7)
    b, hb = train_mlp(x, y, 3, epochs=50, seed=7)
    c, hc = train_mlp(x, y, 3, epochs=50, seed=8)
    for pa, pb in zip(a.params(), b.params()):
        np.testing.assert_array_equal(pa, pb)
    assert ha == hb
    assert not np.array_equal(a.w1, c.w1)


def test_initial_weights_follow_fann():
    net = MLP.create(20, 20, 8, seed=0)
    for p in net.params():
        assert np.all(np.abs(p) <= 0.1)
    assert net.w1.std() > 0.05                          # uniform on [-0.1, 0.1]: sd 0.058


def test_desired_mse_stops_early():
    x, y = blobs(3)
    net, history = train_mlp(x, y, 3, epochs=500, seed=0, desired_mse=0.05)
    assert history[-1] < 0.05 and all(h >= 0.05 for h in history[:-1]) and len(history) < 500


@pytest.mark.parametrize("args, match", [
    ((np.zeros((0, 2)), np.zeros(0, int), 2), "training inputs"),
    ((np.zeros(5), np.zeros(5, int), 2), "training inputs"),
    ((np.zeros((5, 2)), np.zeros(4, int), 2), "labels"),
    ((np.zeros((5, 2)), np.zeros(5), 2), "labels"),
    ((np.zeros((5, 2)), np.full(5, 2), 2), r"labels must lie in 0\.\.1"),
    ((np.full((5, 2), np.nan), np.zeros(5, int), 2), "NaN or Inf"),
])
def test_train_refuses_bad_data(args, match):
    with pytest.raises(ValueError, match=match):
        train_mlp(*args, epochs=1)


def test_train_refuses_bad_sizes():
    with pytest.raises(ValueError, match="epochs"):
        train_mlp(np.zeros((5, 2)), np.zeros(5, int), 2, epochs=0)
    with pytest.raises(ValueError, match="hidden"):
        MLP.create(2, 0, 2)


# -- the training loop against its plain form ----------------------------------------------------

def plain_train(x, labels, n_classes, epochs, seed):
    """iRPROP- as the paper's FANN trains, written plainly: sigmoid() units, the error function's clip
    by masks, every temporary allocated. train_mlp computes the same with in-place units
    (logistic_in_place) and a vectorised error function."""
    net = MLP.create(x.shape[1], x.shape[1], n_classes, seed=seed)
    opt = IRpropMinus(net.params())
    targets = one_hot(labels, n_classes)
    for _ in range(epochs):
        h = sigmoid(x @ net.w1 + net.b1)
        y = sigmoid(h @ net.w2 + net.b2)
        e = targets - y
        err = np.empty_like(e)
        hi, lo = e > 0.9999999, e < -0.9999999
        mid = ~(hi | lo)
        err[hi], err[lo] = ERROR_CLIP, -ERROR_CLIP
        err[mid] = np.log((1 + e[mid]) / (1 - e[mid]))
        delta2 = err * sigmoid_derivative(y)
        delta1 = (delta2 @ net.w2.T) * sigmoid_derivative(h)
        opt.step([-(x.T @ delta1), -delta1.sum(0), -(h.T @ delta2), -delta2.sum(0)])
    return net


def plain_gradients(net, x, targets):
    """train_mlp's gradients, written plainly (as plain_train computes them)."""
    h = sigmoid(x @ net.w1 + net.b1)
    y = sigmoid(h @ net.w2 + net.b2)
    delta2 = tanh_error(targets - y) * sigmoid_derivative(y)
    delta1 = (delta2 @ net.w2.T) * sigmoid_derivative(h)
    return [-(x.T @ delta1), -delta1.sum(0), -(h.T @ delta2), -delta2.sum(0)]


@pytest.mark.parametrize("inputs, hidden, classes, scale", [(20, 20, 8, 0.1), (50, 50, 3, 1.0), (6, 3, 2, 5.0)])
def test_gradients_are_the_plain_loops_to_rounding(inputs, hidden, classes, scale):
    rng = np.random.default_rng(inputs)
    net = fixed_net(inputs, hidden, classes, seed=classes, scale=scale)
    x = 3 * rng.normal(size=(200, inputs))
    targets = one_hot(rng.integers(0, classes, 200), classes)
    for g, want in zip(net.gradients(x, targets)[0], plain_gradients(net, x, targets)):
        np.testing.assert_allclose(g, want, rtol=0, atol=1e-13 * np.abs(want).max())


@pytest.mark.parametrize("n, inputs, classes, seed", [(1500, 20, 8, 0), (1000, 12, 3, 1), (600, 6, 2, 2)])
def test_training_gives_the_network_of_the_plain_loop(n, inputs, classes, seed):
    """Units a rounding apart (logistic_in_place against sigmoid) leave the sign of every gradient
    that is more than rounding, so iRPROP- takes the same steps: the same weights to the bit, on
    classes that overlap, so that no gradient falls to rounding's level in 200 epochs (where the
    training set is learnt to the last window, the gradients end at 1e-13 and their signs are
    rounding in either loop)."""
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, classes, n)
    x = rng.normal(size=(n, inputs)) + 0.3 * np.eye(classes)[labels] @ rng.normal(size=(classes, inputs))
    fast, history = train_mlp(x, labels, classes, epochs=200, seed=seed)
    plain = plain_train(x, labels, classes, 200, seed)
    assert np.mean(fast.predict(x) == labels) < 0.98                  # the premise: not learnt to the last window
    for p, q in zip(fast.params(), plain.params()):
        np.testing.assert_array_equal(p, q)
    assert history[-1] < history[0]


# -- stopping early on held-out rows -------------------------------------------------------------

def overlapping(n, inputs, classes, seed, held=200):
    """Classes that overlap, ``n`` training rows and ``held`` held-out rows of the same classes: a network
    of this size overfits them within a few hundred epochs."""
    rng = np.random.default_rng(seed)
    means = 0.4 * rng.normal(size=(classes, inputs))
    labels = rng.integers(0, classes, n + held)
    x = rng.normal(size=(n + held, inputs)) + means[labels]
    return x[:n], labels[:n], x[n:], labels[n:]


def plain_held_out_errors(x, labels, classes, x_held, labels_held, epochs, seed):
    """The held-out mean squared error after every STOP_CHECK_EPOCHS epochs of the plain loop, computed plainly."""
    targets = one_hot(labels_held, classes)
    errors = {}
    for e in range(STOP_CHECK_EPOCHS, epochs + 1, STOP_CHECK_EPOCHS):
        net = plain_train(x, labels, classes, e, seed)
        y = 1.0 / (1.0 + np.exp(-(sigmoid(x_held @ net.w1 + net.b1) @ net.w2 + net.b2)))
        errors[e] = float(np.mean((targets - y) ** 2))
    return errors


@pytest.mark.parametrize("patience", [20, 60])
def test_a_network_stops_at_its_lowest_held_out_error_after_patience(patience):
    """The network returned is the plain loop's of the epochs with the lowest held-out error (every 10th
    epoch looked at); it trained ``patience`` epochs past them, no more, and says the epochs that made it."""
    x, y, xh, yh = overlapping(300, 12, 3, 0)
    seen = []
    net, history = train_mlp(x, y, 3, epochs=400, seed=0, stop_on=(xh, yh), patience=patience,
                             progress=lambda epoch, mse: seen.append(epoch))
    errors = plain_held_out_errors(x, y, 3, xh, yh, len(seen), 0)
    best = min(errors, key=lambda e: (errors[e], e))
    assert best < 400 - patience                                    # the premise: it stopped before the last epoch
    assert len(history) == best and len(seen) == best + patience
    assert all(errors[e] > errors[best] for e in errors if e > best)
    for p, q in zip(net.params(), plain_train(x, y, 3, best, 0).params()):
        np.testing.assert_array_equal(p, q)


def test_without_held_out_rows_every_epoch_is_trained():
    x, y, _, _ = overlapping(300, 12, 3, 0)
    net, history = train_mlp(x, y, 3, epochs=120, seed=0, patience=10)
    assert len(history) == 120
    for p, q in zip(net.params(), plain_train(x, y, 3, 120, 0).params()):
        np.testing.assert_array_equal(p, q)


def test_a_held_out_error_still_falling_at_the_last_epoch_keeps_the_last_network():
    x, y, xh, yh = overlapping(1000, 12, 3, 0)
    targets = one_hot(yh, 3)
    err = {e: float(np.mean((targets - plain_train(x, y, 3, e, 0).outputs(xh)) ** 2)) for e in (10, 15)}
    assert err[15] < err[10]                                        # the premise: still falling
    net, history = train_mlp(x, y, 3, epochs=15, seed=0, stop_on=(xh, yh))
    assert len(history) == 15                                       # looked at after the last epoch too
    for p, q in zip(net.params(), train_mlp(x, y, 3, epochs=15, seed=0)[0].params()):
        np.testing.assert_array_equal(p, q)


def test_a_task_with_its_scored_rows_labels_stops_early_on_them():
    x, y, xh, yh = overlapping(300, 12, 3, 0)
    plain = NetworkTask(x, y, 3, epochs=400, seed=0, score=xh)
    stopping = NetworkTask(x, y, 3, epochs=400, seed=0, score=xh, score_labels=yh, patience=20)
    assert not plain.stops_early and stopping.stops_early and stopping.work < plain.work
    net, history, logits, looks = train_task(stopping)
    assert len(train_task(plain).history) == 400 and train_task(plain).held_out_errors == () and len(history) < 400
    np.testing.assert_array_equal(logits, net.logits(xh))
    np.testing.assert_array_equal(net.w1, train_mlp(x, y, 3, epochs=len(history), seed=0)[0].w1)
    # every look comes back: every 10 epochs until 20 (the patience) past the best, each the plain loop's error
    assert [e for e, _ in looks] == list(range(STOP_CHECK_EPOCHS, len(history) + 20 + 1, STOP_CHECK_EPOCHS))
    want = plain_held_out_errors(x, y, 3, xh, yh, len(history) + 20, 0)
    np.testing.assert_allclose([err for _, err in looks], [want[e] for e, _ in looks], rtol=1e-12)


@pytest.mark.parametrize("stop_on, patience, match", [
    ((np.zeros((4, 3)), np.zeros(4, int)), 10, r"shape \(m >= 1, 2\)"),
    ((np.zeros((0, 2)), np.zeros(0, int)), 10, "held-out rows"),
    ((np.zeros((4, 2)), np.zeros(3, int)), 10, "held-out labels must be integers of shape"),
    ((np.zeros((4, 2)), np.zeros(4)), 10, "held-out labels must be integers"),
    ((np.zeros((4, 2)), np.full(4, 2)), 10, r"held-out labels must lie in 0\.\.1"),
    ((np.zeros((4, 2)), np.zeros(4, int)), 0, "patience"),
    ((np.zeros((4, 2)), np.zeros(4, int)), True, "patience"),
    ((np.zeros((4, 2)), np.zeros(4, int)), 2.5, "patience"),
])
def test_train_refuses_bad_held_out_rows(stop_on, patience, match):
    with pytest.raises(InputError, match=match):
        train_mlp(np.zeros((5, 2)), np.zeros(5, int), 2, epochs=5, stop_on=stop_on, patience=patience)
