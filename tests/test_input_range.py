"""The input range of the filterbanks (``max_input``) and what happens to samples beyond it.

A finite sample large enough to overflow the filter state (1e245 in 4410-sample blocks) used to
turn the state into NaN for good, uncounted. Now every filterbank has ``max_input``, derived from
the state's headroom (``supramodal.gammatone.max_input``); samples beyond it are treated as NaN
and Inf are: refused with an InputError, or replaced by 0 and counted (``out_of_range_count``).

Every stream here is fed in random block sizes, with floating-point warnings turned into errors,
and judged against the analytic reference: the cleaned signal convolved (FFT, float64) with the
sampled gammatone of ``reference_impulse_response`` (itself checked against mpmath in
tests/test_gain.py). Underflow is not trapped: decaying states legitimately underflow.
"""

import warnings

import mpmath as mp
import numpy as np
import pytest
from scipy.signal import fftconvolve

from supramodal.backends import make_filterbank
from supramodal.banks import Bank, cochlea_bank, whisker_bank
from supramodal.errors import InputError
from supramodal.gammatone import max_input, reference_impulse_response, state_gain

BANKS = {"cochlea": cochlea_bank(), "whiskers": whisker_bank()}
#: (backend, dtype, error bound relative to each channel's peak): docs/stability.md's bounds, rounded up.
REALISATIONS = [("fast", np.float64, 1e-12), ("fast", np.float32, 2e-6), ("reference", np.float64, 1e-12)]
CASES = [(bank, *r) for bank in BANKS for r in REALISATIONS]
IDS = [f"{bank}-{backend}-{np.dtype(dtype).name}" for bank, backend, dtype, _ in CASES]


def random_sizes(rng, n: int) -> list[int]:
    """Block sizes covering ``n`` samples: single samples, short, node-sized and long blocks."""
    sizes, total = [], 0
    while total < n:
        s = int(rng.choice([1, rng.integers(2, 40), 441, 4410, rng.integers(40, 5000)]))
        sizes.append(min(s, n - total))
        total += sizes[-1]
    return sizes


def strict():
    """Floating-point warnings as errors, and numpy's overflow, invalid and divide traps on."""
    stack = warnings.catch_warnings()
    stack.__enter__()
    warnings.simplefilter("error")
    return stack, np.errstate(over="raise", invalid="raise", divide="raise")


def reference_response(bank: Bank, x: np.ndarray) -> np.ndarray:
    """The causal convolution of ``x`` (mono or per channel) with the analytic normalised gammatone."""
    n = x.shape[-1]
    h = reference_impulse_response(bank, n)
    xs = np.broadcast_to(x, (bank.channels, n))
    return fftconvolve(xs, h, axes=-1)[:, :n]


def channel_errors(y: np.ndarray, ref: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Per channel ``max |y - ref|`` over the larger of ``max |ref|`` and the input's amplitude.

    docs/stability.md: where a channel's output is far below its input (a 20 Hz channel fed a
    signal near fs/2), any realisation's rounding is relative to the input.
    """
    scale = np.maximum(np.max(np.abs(ref), axis=-1), np.max(np.abs(x)))
    return np.max(np.abs(y.astype(np.float64) - ref), axis=-1) / scale


def noise(bank: Bank, n: int, rng, per_channel: bool) -> np.ndarray:
    return rng.standard_normal((bank.channels, n) if per_channel else n)


def bad_values(limit: float, dtype) -> list[float]:
    """Finite samples beyond the range (float64), the float32 overflow among them."""
    values = [1e245, -5e252, np.finfo(np.float64).max, -limit * 1.0001]
    if np.dtype(dtype) == np.float32:
        values += [1e38, -3.5e38, 1e300]          # in float32's range but not the filter's; beyond it
    return values


@pytest.mark.parametrize("bank_name,backend,dtype,bound", CASES, ids=IDS)
def test_out_of_range_samples_are_replaced_counted_and_the_stream_continues_exactly(bank_name, backend, dtype, bound):
    bank = BANKS[bank_name]
    rng = np.random.default_rng(abs(hash(bank_name + backend + np.dtype(dtype).name)) % 2**32)
    n = 12000
    per_channel = bank_name == "whiskers"                # one signal per whisker; the microphone is mono
    x = noise(bank, n, rng, per_channel)
    fb = make_filterbank(bank, backend, dtype=dtype, nonfinite="zero")
    big = bad_values(fb.max_input, dtype)
    where = np.sort(rng.choice(np.arange(2000, 3000), len(big) + 2, replace=False))
    flat = x.reshape(-1, n)
    for i, v in zip(where, big + [np.nan, np.inf]):
        flat[rng.integers(flat.shape[0]), i] = v
    cleaned = np.where(np.isfinite(x) & (np.abs(x) <= fb.max_input), x, 0.0)
    ref = reference_response(bank, cleaned)

    stack, traps = strict()
    with traps:
        try:
            out, a = [], 0
            for s in random_sizes(rng, n):
                out.append(fb.process(x[..., a:a + s]))
                a += s
        finally:
            stack.__exit__(None, None, None)
    y = np.concatenate(out, axis=1)

    assert np.isfinite(y).all(), "a sample beyond the range poisoned the filter state"
    err = channel_errors(y, ref, cleaned)
    assert err.max() <= bound, f"channel {bank.names[err.argmax()]} off by {err.max():.3g} (bound {bound:g})"
    after = channel_errors(y[:, 3000:], ref[:, 3000:], cleaned)
    assert after.max() <= bound, f"after the bad block: {after.max():.3g}"
    assert fb.nonfinite_count == 2
    assert fb.out_of_range_count == len(big)


@pytest.mark.parametrize("bank_name,backend,dtype,bound", CASES, ids=IDS)
def test_out_of_range_samples_are_refused_by_default_and_leave_the_state_as_it_was(bank_name, backend, dtype, bound):
    bank = BANKS[bank_name]
    rng = np.random.default_rng(7)
    per_channel = bank_name == "whiskers"
    fb = make_filterbank(bank, backend, dtype=dtype)
    limit = fb.max_input
    sizes = random_sizes(rng, 9000)
    blocks = [noise(bank, s, rng, per_channel) for s in sizes]
    k = next(i for i in range(len(blocks) // 2, len(blocks)) if sizes[i] >= 2)
    refused = blocks[k].copy()
    refused.reshape(-1)[-1] = 3 * limit
    refused.reshape(-1)[0] = -1e300
    accepted, out = [], []
    stack, traps = strict()
    with traps:
        try:
            for i, block in enumerate(blocks):
                if i == k:
                    with pytest.raises(InputError) as info:
                        fb.process(refused)
                    message = str(info.value)
                out.append(fb.process(block if i != k else block[..., :0]))
                accepted.append(block if i != k else block[..., :0])
        finally:
            stack.__exit__(None, None, None)
    first = [0, 0] if per_channel else [0]
    assert f"2 sample(s) beyond the filterbank's input range +-{limit:.3g}" in message
    assert f"first at index {first}" in message and "nonfinite='zero'" in message and "Scale" in message
    y = np.concatenate(out, axis=1)
    clean = np.concatenate(accepted, axis=-1)
    err = channel_errors(y, reference_response(bank, clean), clean)
    assert err.max() <= bound, f"the refused block changed the state: {err.max():.3g}"
    assert fb.out_of_range_count == 0


@pytest.mark.parametrize("bank_name,backend,dtype,bound", CASES, ids=IDS)
def test_inputs_just_below_the_limit_are_filtered_exactly_with_no_warning(bank_name, backend, dtype, bound):
    # The filter is linear: at amplitude a just below max_input, y / a must be the unit signal's
    # response. Three shapes: random signs, a constant (DC, the largest moments of narrow
    # channels), and signs matched to the widest channel (its largest output).
    bank = BANKS[bank_name]
    rng = np.random.default_rng(11)
    n = 9000
    wide = int(np.argmax(bank.b))
    phase = 2 * np.pi * bank.cf[wide] / bank.fs * np.arange(n)[::-1]
    shapes = {"signs": rng.choice([-1.0, 1.0], n), "constant": np.ones(n),
              "matched": np.where(np.cos(phase) >= 0, 1.0, -1.0)}
    for name, unit in shapes.items():
        fb = make_filterbank(bank, backend, dtype=dtype)
        a = fb.max_input * (1 - 1e-7)
        x = unit * a
        stack, traps = strict()
        with traps:
            try:
                out, i = [], 0
                for s in random_sizes(rng, n):
                    out.append(fb.process(x[i:i + s]))
                    i += s
            finally:
                stack.__exit__(None, None, None)
        y = np.concatenate(out, axis=1)
        assert np.isfinite(y).all(), f"{name}: non-finite output at {a:.3g}"
        assert fb.out_of_range_count == 0 and fb.nonfinite_count == 0
        err = channel_errors(y.astype(np.float64) / a, reference_response(bank, unit), unit)
        assert err.max() <= bound, f"{name} at {a:.3g}: channel {bank.names[err.argmax()]} off by {err.max():.3g}"


EXTREME_BANKS = {
    # b = 10 fs at fs/4: the real response is ~exp(-63) of its complex envelope, the state ~3e26 x input.
    "wide-quarter": Bank("custom", 1000.0, [250.0, 250.00046, 100.0], [10000.0, 2000.0, 1.0], ("q", "q2", "n")),
    # b = 1e-7 fs at 192 kHz: 1e8-sample response, long passes; plus a wide channel setting the pass.
    "narrow": Bank("custom", 192000.0, [1000.0, 90000.0], [0.0192, 1.0e5], ("n", "w")),
}


@pytest.mark.parametrize("bank_name", sorted(EXTREME_BANKS))
@pytest.mark.parametrize("backend,dtype", [("fast", np.float64), ("fast", np.float32), ("reference", np.float64)])
def test_the_limit_holds_at_the_corners_of_the_domain(bank_name, backend, dtype):
    bank = EXTREME_BANKS[bank_name]
    rng = np.random.default_rng(3)
    n = 6000
    for subblock in ([None, 1, 4096] if backend == "fast" else [None]):
        options = {"subblock": subblock} if backend == "fast" else {}
        fb = make_filterbank(bank, backend, dtype=dtype, nonfinite="zero", **options)
        a = fb.max_input * (1 - 1e-7)
        wide = int(np.argmax(bank.b))
        phase = 2 * np.pi * bank.cf[wide] / bank.fs * np.arange(n)[::-1]
        for unit in (rng.choice([-1.0, 1.0], n), np.where(np.cos(phase) >= 0, 1.0, -1.0), np.ones(n)):
            stack, traps = strict()
            with traps:
                try:
                    i = 0
                    for s in random_sizes(rng, n):
                        y = fb.process(unit[i:i + s] * a)
                        assert np.isfinite(y).all(), f"subblock {subblock}: non-finite output at {a:.3g}"
                        i += s
                finally:
                    stack.__exit__(None, None, None)
        assert fb.out_of_range_count == 0


def test_float64_samples_beyond_float32_are_refused_or_counted_without_a_warning():
    bank = BANKS["cochlea"]
    x = np.zeros(441)
    x[[3, 100, 200]] = [1e39, -1e300, 2.0]
    stack, traps = strict()
    with traps:
        try:
            fb = make_filterbank(bank, "fast", dtype=np.float32, nonfinite="zero")
            y = fb.process(x)
            with pytest.raises(InputError, match=r"2 sample\(s\) beyond .* \[3\]: 1e\+39"):
                make_filterbank(bank, "fast", dtype=np.float32).process(x)
        finally:
            stack.__exit__(None, None, None)
    assert fb.out_of_range_count == 2
    assert y.dtype == np.float32 and np.isfinite(y).all()
    ref = reference_response(bank, np.where(np.abs(x) < 1e30, x, 0.0))
    assert channel_errors(y, ref, np.where(np.abs(x) < 1e30, x, 0.0)).max() <= 2e-6


def test_integer_input_is_held_to_the_range_too():
    # A wide channel at fs/4 in float32 takes only ~1e11: int64 samples can exceed that.
    bank = EXTREME_BANKS["wide-quarter"]
    fb = make_filterbank(bank, "fast", dtype=np.float32, nonfinite="zero")
    assert fb.max_input < 2**40
    x = np.zeros(64, dtype=np.int64)
    x[5], x[9] = 2**62, 3
    y = fb.process(x)
    assert fb.out_of_range_count == 1 and np.isfinite(y).all()


def test_max_input_follows_from_the_state_gain_computed_in_mpmath():
    # The state's headroom: G = max_c sum n^3 |p_c|^n / gain_c, the largest a state moment or output
    # gets per unit of input. Independently: mpmath sums (closed forms at 50 digits).
    bank = Bank("custom", 1000.0, [250.0, 100.0, 450.0], [10000.0, 1.0, 3.0], ("q", "n", "h"))
    g_code = state_gain(bank)
    with mp.workdps(50):
        for c in range(bank.channels):
            cf, b, fs = mp.mpf(float(bank.cf[c])), mp.mpf(float(bank.b[c])), mp.mpf(bank.fs)
            r = mp.exp(-2 * mp.pi * b / fs)
            q = r * mp.exp(-4j * mp.pi * cf / fs)

            def moments(z):
                return z * (1 + 4 * z + z * z) / (1 - z) ** 4

            want = moments(r) / (abs(moments(r) + moments(q)) / 2)
            assert abs(g_code[c] - want) / want < 1e-14
    G = float(np.max(g_code))
    assert max_input(bank) == pytest.approx(np.finfo(np.float64).max / (16 * G * np.exp(200.0)), rel=1e-14)
    assert max_input(bank, np.float32) == pytest.approx(float(np.finfo(np.float32).max) / (16 * G), rel=1e-14)
    # Every backend of one bank and dtype accepts the same range.
    assert make_filterbank(bank, "reference").max_input == make_filterbank(bank, "fast").max_input
