"""Exact impulse-invariant 4th-order gammatone filterbank, streaming, all channels at once.

The analytic gammatone ``g(t) = t**3 exp(-2 pi b t) cos(2 pi fc t)`` sampled at
``t = n/fs`` is, up to the constant ``fs**-3``, ``Re(n**3 p**n)`` with the pole
``p = exp((-2 pi b + 2j pi fc) / fs)``. This module realises exactly that
sequence, normalised to unit gain at ``fc``. (:mod:`supramodal.backends` holds
the plain per-channel reference realisation and the backend interface.)

How it streams
--------------
The moment recursion. The past inputs enter the output only through four complex
"moments" per channel, ``S_j(n) = sum_(t>=1) t**j p**t x[n-t]`` (``j = 0..3``),
because ``(d + t)**3`` expands binomially. Over the next ``l`` samples:

* ``y[n+d] = g Re(p**d sum_j C(3, j) d**(3-j) S_j(n) + sum_(i<=d) (d-i)**3 p**(d-i) x[n+i])``;
* ``S(n+l) = p**l B(l) S(n) + U``, ``B(l)[j, r] = C(j, r) l**(j-r)`` (exact integers),
  ``U_j = sum_(i<l) (l-i)**j p**(l-i) x[n+i]``

(``g`` the unit-gain factor; the state is kept as ``g S``, of the output's order).

The rescaled frame. With an anchor ``a <= n`` per channel group, ``A(n) = p**-(n-a) S(n)``
obeys ``A(n+l) = B(l) A(n) + p**-(n+l-a) U``: no pole factor is left on the state, so
the recursion is real and the same for every channel, and the state is never multiplied
by a rounded pole power, which would compound a rounding per step. The output takes
``S = p**(n-a) A`` with the factor from a table (each entry correctly rounded). When the
frame would span more than ``exp(200)`` of decay of the group's widest channel, or 2048
samples (the table), it is renormalised: ``A <- p**(n-a) A``, ``a <- n``, one rounding.

The group products. A block is cut into passes of ``K`` sub-blocks of ``m`` samples
(``m`` 16 to 32, an exact division where there is one: 441 = 21 x 21), each in three
steps of a few large products (measured on x86-64, near the core's float64 peak):

1. the state inputs ``V_k = g U_k p**-(n_k+m-a)`` of every sub-block and channel: one
   product of the mono block ``(K, m)`` with a ``(m, 8 C)`` matrix, then the rescaling;
2. the start state of every sub-block, ``A_k = B(k m) A_0 + sum_(i<k) B((k-1-i) m) V_i``:
   real, channel-independent maps applied to every channel's real and imaginary parts at
   once (one product up to 8 sub-blocks; beyond, the end states of groups of sub-blocks,
   then every group's start, then the starts within each group);
3. the output: per channel ``[S_k | x_k] @ [O ; T]``, the start state's part and the
   within-sub-block Toeplitz part in one product.

Channel groups: a channel much narrower than the bank's widest (time constant over 100
times longer, where the widest's frame is shorter than 2048 samples) gets a frame of its
own, so it is not renormalised every few samples because of a channel it does not share
anything with. Large temporaries are kept between calls: fresh multi-megabyte arrays
cost page faults every block.

Precision
---------
* Every matrix entry and every pole power is computed once, from the closed form,
  with the phase ``2 pi fc d / fs`` reduced modulo ``2 pi`` in extended precision
  (``numpy.longdouble``) and rounded once: nothing is recursed on but the state, so
  nothing drifts.
* The rescaling costs no precision: each term of a start state is the term of the
  direct sum times one common factor, so the sums round as they would without it.
  What remains is a rounding per renormalisation (every 2048 samples at most, or every
  block for blocks longer than half the frame) and one per block in ``B(l) A`` (exact
  integers, but the sum rounds): blocks of a few samples therefore carry a larger error
  (docs/stability.md states it).
* The state computation is always float64 (complex128). With ``dtype=float32`` the
  two large products (steps 1 and 3) run in float32 and the output is float32; its
  error is a few 1e-7 of the output's scale and does not grow with stream length
  (docs/stability.md).
* States below about 1e-287 are flushed to zero every 8 passes: subnormal
  numbers make matrix products many times slower and carry nothing here.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from math import comb

import numpy as np

from supramodal.banks import Bank
from supramodal.errors import InputError

_LD = np.longdouble
_TWO_PI_LD = 2 * np.arccos(_LD(-1))      # 2 pi to long-double precision

#: ``S + c - c`` rounds every |S| below ``c * 2**-53`` (about 1e-287) to exactly 0.
_FLUSH_OFFSET = 2.0**-900
#: The state is flushed every this many passes (a decay to 1e-287 takes far longer).
_FLUSH_EVERY = 8
#: Matrix entries below this are set to 0 (no subnormal operands in float32 products).
_FLUSH_MATRIX = {np.dtype(np.float64): 1e-290, np.dtype(np.float32): 1e-35}

#: Smallest bandwidth parameter accepted, as a fraction of the sample rate: the impulse
#: response then lasts ~1e8 samples and float64 holds its phase to ~1e-9 (docs/stability.md).
MIN_B_OVER_FS = 1e-7
#: Largest bandwidth parameter accepted, as a fraction of the sample rate: the response then
#: decays by exp(-2 pi * 10), about 5e-28, per sample; the fast form rescales by up to
#: exp(200) per pass, which a wider filter would overflow in a single sample.
MAX_B_OVER_FS = 10.0
#: Factor kept between the bound on every number the filter computes and the largest float
#: (:func:`max_input`): the bound is a sum of magnitudes, so this only covers rounding and the
#: few partial sums a realisation may form beyond it.
INPUT_HEADROOM = 16.0
_FLOAT64_MAX = float(np.finfo(np.float64).max)



def _cos_sin_turns(k, s):
    """``cos`` and ``sin`` of ``2 pi (k/4 + s)`` for integers ``k`` and ``|s| <= 1/8``, from ``s`` alone.

    A cosine or sine that vanishes at a quarter turn is then ``+-sin(2 pi s)``, with the full
    relative precision of ``s`` (exactly 0 at an exact quarter turn), instead of the absolute
    rounding of ``2 pi`` times a number near 1/4 (about 1e-20 in long double, 1e-17 in float64).
    """
    sigma = _TWO_PI_LD * s
    c, sn = np.cos(sigma), np.sin(sigma)
    quadrant = np.mod(k, 4).astype(np.intp)
    return np.choose(quadrant, [c, -sn, -c, sn]), np.choose(quadrant, [sn, c, -sn, -c])


def _two_product(a, b):
    """Return ``(hi, lo)`` with ``a * b = hi + lo`` exactly (Dekker's splitting; float64 arrays, no overflow)."""
    hi = a * b
    a_hi = a * 134217729.0 - (a * 134217729.0 - a)
    b_hi = b * 134217729.0 - (b * 134217729.0 - b)
    a_lo, b_lo = a - a_hi, b - b_hi
    return hi, ((a_hi * b_hi - hi) + a_hi * b_lo + a_lo * b_hi) + a_lo * b_lo


def _quarter_turns(cf, fs: float, d):
    """``cf * d / fs = k/4 + s``: integers ``k`` (as floats) and ``|s| <~ 1/8`` in long double.

    The remainder ``cf d - k fs/4`` is formed exactly from the float64 values (two exact
    products, then a subtraction that is exact where it cancels), so ``s`` keeps its full
    relative precision however close ``cf d / fs`` lies to a quarter turn, where the cosine or
    the sine vanishes; and it loses nothing for large ``d`` (integers below 2**53).
    """
    cf, d = np.broadcast_arrays(np.asarray(cf, dtype=np.float64), np.asarray(d, dtype=np.float64))
    k = np.rint(4 * (cf * d) / fs)
    p_hi, p_lo = _two_product(cf, d)
    q_hi, q_lo = _two_product(k, np.full_like(k, fs / 4))
    rest = (p_hi - q_hi).astype(_LD) + (p_lo.astype(_LD) - q_lo.astype(_LD))
    return k, rest / _LD(fs)


def pole_powers(bank: Bank, d) -> np.ndarray:
    """``p**d`` per channel for real exponents ``d``, correctly rounded to complex128.

    The phase ``2 pi fc d / fs`` is reduced exactly to the nearest quarter turn first
    (:func:`_quarter_turns`), so large ``d`` lose nothing to the rounding of
    ``2 pi fc / fs``, and a real or imaginary part that vanishes or nearly does
    (``fc`` at or near ``fs/4``, ``d = 1``) keeps its relative precision.

    Returns
    -------
    ndarray, shape (channels,) + numpy.shape(d), complex128
    """
    d = np.asarray(d, dtype=_LD)
    cf = bank.cf.astype(_LD).reshape((-1,) + (1,) * d.ndim)
    b = bank.b.astype(_LD).reshape(cf.shape)
    fs = _LD(bank.fs)
    cos_t, sin_t = _cos_sin_turns(*_quarter_turns(bank.cf.reshape(cf.shape), bank.fs, d.astype(np.float64)))
    mag = np.exp(-_TWO_PI_LD * b * d / fs)
    out = np.empty(np.broadcast_shapes(cf.shape, d.shape), dtype=np.complex128)
    out.real = (mag * cos_t).astype(np.float64)
    out.imag = (mag * sin_t).astype(np.float64)
    return out


def _moment_sum_log(z):
    """``sum_{m>=0} m**3 q**m = q (1 + 4q + q**2) / (1 - q)**4`` for ``q = exp(z)``, ``Re z < 0``.

    ``1 - q`` is taken as ``-expm1(z)``: exact to rounding even when ``|q|`` is within 1e-6 of 1
    (narrow filters at high sample rates), where ``1 - q`` would lose digits. Works in the
    precision of ``z`` (complex128 or ``numpy.clongdouble``).
    """
    q = np.exp(z)
    return q * (1 + 4 * q + q * q) / np.expm1(z) ** 4


#: Above this decay per sample ``beta = 2 pi b / fs`` (b > 0.48 fs), :func:`gain_at_cf` sums the
#: response directly: the closed form's two terms would cancel by up to ``exp(beta) / 8``.
_GAIN_DIRECT_BETA = 3.0
#: Terms of the direct sum: at ``beta >= 3`` the rest is below ``1e-30`` of the gain.
_GAIN_DIRECT_TERMS = 48


def _gain_direct(cf: float, b: float, fs: float) -> float:
    """:func:`gain_at_cf` of one wide channel by the direct sum (see there)."""
    n = np.arange(1, _GAIN_DIRECT_TERMS + 1, dtype=_LD)
    w = n**3 * np.exp(-_TWO_PI_LD * (_LD(b) / _LD(fs)) * n)
    cos_t, sin_t = _cos_sin_turns(*_quarter_turns(cf, fs, np.arange(1.0, _GAIN_DIRECT_TERMS + 1)))
    re = np.sum(w * cos_t * cos_t)
    im = np.sum(w * sin_t * cos_t)
    return float(np.hypot(re, im))


def gain_at_cf(bank: Bank) -> np.ndarray:
    """Magnitude at ``fc`` of the un-normalised sampled response ``h[n] = n**3 r**n cos(theta n)``, per channel.

    With ``r = exp(-beta)``, ``beta = 2 pi b / fs`` and ``theta = 2 pi fc / fs``, the gain is
    ``|H| = |sum_n h[n] exp(-j theta n)|``. Two forms, each used where it is well conditioned,
    give it to a few units in the last place (float64) over the whole accepted domain
    (``1e-7 fs <= b <= 10 fs``, ``0 < fc < fs/2``; tests/test_gain.py checks it against mpmath):

    * ``beta <= 3`` (b <= 0.48 fs), the closed form. Writing ``cos`` as two exponentials,
      ``H = (M(r) + M(r exp(-2j theta))) / 2`` with ``M(q) = sum n**3 q**n = q (1 + 4q + q**2) / (1 - q)**4``
      (:func:`_moment_sum_log`, ``1 - q = -expm1(z)``). The second term matters for low ``fc``
      and wide ``b``; since ``|M(r exp(-2j theta))| <= M(r)`` the cancellation between them
      costs at most ``M(r) / |H|``, about 4 at ``beta = 3``, ``fc = fs/4``, and it grows like
      ``exp(beta) / 8`` beyond (``M(r) ~ r`` while ``|H| ~ 8 r**2`` at ``fc = fs/4``: 100 % at
      b = 10 fs). The angle ``2 theta`` is reduced exactly to ``(-pi, pi]`` first
      (``2 fc - fs`` is exact for ``fc >= fs/4``), so ``1 - q`` keeps its relative precision
      for ``fc`` near ``fs/2`` and narrow ``b``; the rest runs in ``numpy.longdouble``.
    * ``beta > 3``, the direct sum, short because the response is: 48 terms leave out less
      than ``1e-30`` of ``|H|``. ``Re H = sum n**3 r**n cos(theta n)**2`` has no cancellation
      (every term >= 0); ``Im H = -sum n**3 r**n sin(theta n) cos(theta n)`` has little, as
      ``r < 0.05`` makes its first term dominate. Its ill-conditioning is in the phase: near
      ``fc = fs/4`` the leading term ``r cos(theta)**2`` hangs on ``fc/fs - 1/4``. So
      ``n fc / fs`` is reduced to the nearest quarter turn exactly (exact products of the
      float64 inputs, :func:`_quarter_turns`) and the cosine and sine taken of the
      remainder, each with full relative precision.

    Returns
    -------
    ndarray, shape (channels,), float64
    """
    cf, b, fs = bank.cf, bank.b, bank.fs
    beta = _TWO_PI_LD * b.astype(_LD) / _LD(fs)
    # 2 theta reduced to (-pi, pi] in turns: 2 fc/fs - 1 for fc >= fs/4, where 2 fc - fs is exact
    # (Sterbenz: fs/2 <= 2 fc < fs).
    turns2 = np.where(cf >= fs / 4, 2 * cf - fs, 2 * cf).astype(_LD) / _LD(fs)
    h = (_moment_sum_log((-beta).astype(np.clongdouble))
         + _moment_sum_log(-beta + 1j * (_TWO_PI_LD * turns2)))
    gain = (np.abs(h) / 2).astype(np.float64)
    for c in np.flatnonzero(beta > _GAIN_DIRECT_BETA):
        gain[c] = _gain_direct(float(cf[c]), float(b[c]), float(fs))
    return gain


def reference_impulse_response(bank: Bank, n: int) -> np.ndarray:
    """Return the sampled analytic gammatone, normalised to unit gain at ``fc``: the reference.

    Computed directly from ``t**3 exp(-2 pi b t) cos(2 pi fc t)`` (not from the
    pole form the filter uses), so comparing against it is an independent check.
    The argument ``2 pi fc k / fs`` is evaluated in ``numpy.longdouble`` (64-bit
    mantissa on x86-64) and reduced modulo one turn before the cosine: in float64
    its rounding grows like ``k * 1e-16`` rad, which over tens of thousands of
    samples (narrow ``b``) would make the reference less accurate than the filter
    it judges. Where ``longdouble`` is only float64 (some ARM platforms) it is
    float64 again. The cosine is taken of the remainder after the nearest quarter
    turn (:func:`_cos_sin_turns`): for wide ``b`` near ``fc = fs/4`` the normalised
    ``n = 1`` term is ``exp(beta) cos(theta) / 8``, and a cosine that should vanish
    must not come out as 1e-20 times 1e27.

    Returns
    -------
    ndarray, shape (channels, n), float64
    """
    k = np.arange(n, dtype=_LD)
    b = bank.b.astype(_LD)[:, None]
    fs = _LD(bank.fs)
    cos_t, _ = _cos_sin_turns(*_quarter_turns(bank.cf[:, None], bank.fs, np.arange(n, dtype=np.float64)))
    h = k**3 * np.exp(-_TWO_PI_LD * b * k / fs) * cos_t
    return (h / gain_at_cf(bank).astype(_LD)[:, None]).astype(np.float64)


def check_bandwidths(bank: Bank) -> None:
    """Refuse bandwidths float64 cannot hold: ``b < MIN_B_OVER_FS * fs`` or ``b > MAX_B_OVER_FS * fs``.

    Raises
    ------
    InputError
        Naming the first channel out of range and the fix.
    """
    bad = np.flatnonzero(bank.b < MIN_B_OVER_FS * bank.fs)
    if bad.size:
        k = int(bad[0])
        raise InputError(
            f"bandwidth parameter b of channel {bank.names[k]} is {bank.b[k]:g} Hz, below {MIN_B_OVER_FS:g} * fs = "
            f"{MIN_B_OVER_FS * bank.fs:g} Hz: its impulse response would last over 1e8 samples, beyond what "
            "float64 holds to the documented error (docs/stability.md); widen it or lower the sample rate")
    bad = np.flatnonzero(bank.b > MAX_B_OVER_FS * bank.fs)
    if bad.size:
        k = int(bad[0])
        raise InputError(
            f"bandwidth parameter b of channel {bank.names[k]} is {bank.b[k]:g} Hz, above {MAX_B_OVER_FS:g} * fs = "
            f"{MAX_B_OVER_FS * bank.fs:g} Hz: its impulse response would be over within one sample; narrow it "
            "or raise the sample rate")


def state_gain(bank: Bank) -> np.ndarray:
    """Per channel, the largest magnitude any state moment or output reaches per unit of input.

    ``g sum_{n>=1} n**3 |p|**n = g M(r)`` with ``g = 1 / gain_at_cf`` and ``r = exp(-2 pi b / fs)``:
    the l1 norm of the complex normalised response ``g n**3 p**n``. It bounds every moment
    ``g S_j = g sum_m m**j p**m x[-m]`` (``m**j <= m**3``), the output, and every stage of the
    reference backend's cascade. About 2 for narrow channels; it grows like ``exp(beta) / 8``
    for wide channels near ``fs/4`` (3e26 at b = 10 fs), where the response's real part is
    much smaller than its complex envelope.

    Returns
    -------
    ndarray, shape (channels,), float64, >= 1
    """
    beta = 2 * np.pi * bank.b / bank.fs
    return _moment_sum_log(-beta) / gain_at_cf(bank)


def max_input(bank: Bank, dtype=np.float64) -> float:
    """Return the largest input magnitude a filterbank of ``bank`` accepts, in the input's units.

    Derivation. Let ``|x| <= X``. Every number a filterbank forms is bounded by a sum of
    magnitudes of terms ``g m**j p**(m-l) x``:

    * The state moments and the output are at most ``G X``, ``G`` = :func:`state_gain`
      (largest over the channels); so is every partial sum of the products that form them,
      and, in the reference backend, every section's output.
    * The fast form computes the start states of a pass rescaled to the pass start, divided
      by ``p**l``: ``|p**-l| = exp(beta l)``, at most ``exp(_MAX_DECAY)`` (about 7e86) since a
      pass spans at most ``_MAX_DECAY`` time constants of the widest channel. Each term of the
      binomial shifts ``B(l)`` is bounded the same way (``sum_r C(j, r) l**(j-r) m**r =
      (m + l)**j``), so nothing in that step exceeds ``exp(_MAX_DECAY) G X``.
    * With ``dtype=float32`` the two large products (state inputs; state and input to the
      output) run in float32: their operands and sums are at most ``G X``, and the input
      itself must fit (``G >= 1``).

    Hence ``X <= DBL_MAX / (16 G exp(_MAX_DECAY))`` (float64; about 1e220 for the cochlea and
    the whiskers) and also ``X <= FLT_MAX / (16 G)`` for float32 (about 1e37), 16 being
    :data:`INPUT_HEADROOM`. The reference backend needs only ``DBL_MAX / (16 G)``; one limit for
    every backend keeps them interchangeable. Samples beyond it are treated as NaN and Inf
    are (:class:`FilterbankBase`, ``nonfinite``).

    Parameters
    ----------
    bank : Bank
    dtype : {numpy.float64, numpy.float32}
        The filterbank's arithmetic.

    Returns
    -------
    float
    """
    gain = float(np.max(state_gain(bank)))
    limit = _FLOAT64_MAX / (INPUT_HEADROOM * gain * math.exp(_MAX_DECAY))
    if np.dtype(dtype) == np.float32:
        limit = min(limit, float(np.finfo(np.float32).max) / (INPUT_HEADROOM * gain))
    return float(limit)


class FilterbankBase:
    """What every filterbank backend shares: parameters, input checks, the input policy.

    Subclasses implement :meth:`reset` and ``_filter(x)`` (``x`` already checked,
    of the filterbank's dtype, shape (L,) or (channels, L), L >= 1).

    Parameters
    ----------
    bank : Bank
    dtype : {numpy.float64, numpy.float32}
    nonfinite : {"raise", "zero"}
        What to do with input samples the filter cannot take: NaN, Inf, and finite samples
        beyond :attr:`max_input`. ``"raise"`` (default): refuse the block with an
        :class:`~supramodal.errors.InputError` naming the count, the first index and the fix;
        nothing of it enters the filter. ``"zero"``: replace them by 0 and count them, NaN and
        Inf in :attr:`nonfinite_count`, the others in :attr:`out_of_range_count`, so that a bad
        sample never poisons the filter state.

    Attributes
    ----------
    max_input : float
        The input range is ``[-max_input, max_input]``, in the input's units: about 1e220 in
        float64 and 1e37 in float32 for the cochlea and the whiskers (:func:`max_input`
        derives it from the state's headroom). Inside it the state and the output stay finite
        and no floating-point warning is raised, whatever the block sizes.
    nonfinite_count, out_of_range_count : int
        Samples replaced by 0 under ``nonfinite="zero"``.
    samples_processed : int
    """

    backend = "base"

    def __init__(self, bank: Bank, dtype=np.float64, nonfinite: str = "raise") -> None:
        dtype = np.dtype(dtype)
        if dtype not in (np.dtype(np.float64), np.dtype(np.float32)):
            raise InputError(f"dtype must be float64 or float32, got {dtype}")
        if nonfinite not in ("raise", "zero"):
            raise InputError(f"nonfinite must be 'raise' or 'zero', got {nonfinite!r}")
        check_bandwidths(bank)
        self.bank = bank
        self.channels = bank.channels
        self.dtype = dtype
        self.nonfinite = nonfinite
        self.max_input = max_input(bank, dtype)
        self.nonfinite_count = 0
        self.out_of_range_count = 0
        self.samples_processed = 0

    def reset(self) -> None:
        """Return to rest: zero state, as if no sample had been seen. Counters are kept."""
        raise NotImplementedError

    def prepare(self, x) -> np.ndarray:
        """Check a block and convert it to the filterbank's dtype; apply the input policy.

        Returns the block as it will be filtered: shape (L,) or (channels, L), NaN, Inf and
        samples beyond :attr:`max_input` replaced by 0 (and counted) under ``nonfinite="zero"``.

        Raises
        ------
        InputError
            Not real numbers, a wrong shape, or (``nonfinite="raise"``) a sample outside the range.
        """
        x = np.asarray(x)
        if x.dtype.kind not in "fiu":
            raise InputError(
                f"input samples must be real numbers (float or int), got dtype {x.dtype}; "
                "convert complex or text data before filtering"
            )
        if not (x.ndim == 1 or (x.ndim == 2 and x.shape[0] == self.channels)):
            raise InputError(
                f"input block must have shape (L,) (mono, fed to all {self.channels} channels) or "
                f"({self.channels}, L) (one signal per channel); got shape {x.shape}"
            )
        if x.dtype.kind != "f":
            x = x.astype(self.dtype)           # integers: even 2**64 is far inside float32's range
        # The range is checked in the block's own precision, before any narrowing cast (a float64
        # sample above 3.4e38 would overflow float32). One BLAS dot product decides the common case
        # and raises no floating-point warning: a finite sum of squares at most max_input**2 means
        # every sample is finite and in range (max_input**2 may overflow: then finite is the test).
        # Otherwise (a bad sample, or many near the limit) look.
        limit = self.max_input
        if x.size and not (float(np.vdot(x, x)) <= min(limit * limit, _FLOAT64_MAX)):
            x = self._clean(x, limit)
        return x if x.dtype == self.dtype else x.astype(self.dtype)

    def _clean(self, x: np.ndarray, limit: float) -> np.ndarray:
        """Apply the input policy to a block that may hold NaN, Inf or samples beyond ``limit``."""
        nonfinite = ~np.isfinite(x)
        outside = np.abs(x) > limit                  # Inf too: counted as non-finite below
        outside &= ~nonfinite
        n_nonfinite, n_outside = int(nonfinite.sum()), int(outside.sum())
        if not (n_nonfinite or n_outside):
            return x
        if self.nonfinite == "raise":
            if n_nonfinite:
                raise InputError(
                    f"input block contains {n_nonfinite} NaN or Inf sample(s) (first at index "
                    f"{np.argwhere(nonfinite)[0].tolist()}); clean the signal, or create the filterbank with "
                    "nonfinite='zero' to replace and count them"
                )
            first = tuple(np.argwhere(outside)[0].tolist())
            raise InputError(
                f"input block contains {n_outside} sample(s) beyond the filterbank's input range "
                f"+-{limit:.3g} (first at index {list(first)}: {float(x[first]):.3g}); such values would overflow "
                "the filter state (docs/stability.md). Scale the signal down, or create the filterbank "
                "with nonfinite='zero' to replace and count them"
            )
        self.nonfinite_count += n_nonfinite
        self.out_of_range_count += n_outside
        return np.where(nonfinite | outside, x.dtype.type(0), x)

    def process(self, x, *, prepared: bool = False, out: np.ndarray | None = None) -> np.ndarray:
        """Filter one block.

        Parameters
        ----------
        x : array_like, shape (L,) or (channels, L)
            Samples at ``bank.fs``; ``L`` may be 0.
        prepared : bool
            ``x`` is already the result of :meth:`prepare` (skip the checks).
        out : ndarray, shape (channels, L), optional
            Write the output here (of the filterbank's dtype) instead of a new array.

        Returns
        -------
        ndarray, shape (channels, L), of the filterbank's dtype (``out`` if given)
        """
        if not prepared:
            x = self.prepare(x)
        L = x.shape[-1]
        if out is not None and (out.shape != (self.channels, L) or out.dtype != self.dtype):
            raise InputError(f"out must be a {self.dtype} array of shape {(self.channels, L)}, "
                             f"got {out.dtype} {out.shape}")
        if L == 0:
            return np.empty((self.channels, 0), dtype=self.dtype) if out is None else out
        y = self._filter(x, out)
        self.samples_processed += L
        return y

    def _filter(self, x: np.ndarray, out: np.ndarray | None) -> np.ndarray:
        raise NotImplementedError

    def _fresh(self) -> FilterbankBase:
        raise NotImplementedError

    def impulse_response(self, n: int) -> np.ndarray:
        """Response of a fresh filterbank of the same design to a unit impulse, shape (channels, n)."""
        x = np.zeros(n)
        if n:
            x[0] = 1.0
        return self._fresh().process(x)


def _shift(l: float) -> np.ndarray:  # noqa: E741 (l: the lag, as the docstring and the derivation name it)
    """``B(l)``, shape (4, 4): moments ``l`` samples later, pole factor aside: ``S'_j = sum_r B[j, r] S_r``.

    ``(t + l)**j`` expanded: ``B[j, r] = C(j, r) l**(j - r)`` for ``r <= j``, else 0. Real,
    channel-independent, exact integers for ``l <= 2**17``; ``B(a) B(b) = B(a + b)``.
    """
    return np.array([[comb(j, r) * float(l) ** (j - r) if r <= j else 0.0 for r in range(4)] for j in range(4)])


def _flush_small(a: np.ndarray, dtype) -> np.ndarray:
    """Matrix entries below the dtype's flush level set to 0: no subnormal operands in products."""
    a[np.abs(a) < _FLUSH_MATRIX[np.dtype(dtype)]] = 0.0
    return a


def _as_real_rows(z: np.ndarray) -> np.ndarray:
    """Return a complex array (..., n, 4, C) seen as real (..., 4 n, 2 C), no copy.

    The recursion's maps are real and act on the (sub-block, moment) rows alone, so they apply
    to the real and imaginary parts of every channel at once: one real matrix product.
    """
    return z.view(np.float64).reshape(z.shape[:-3] + (4 * z.shape[-3], 2 * z.shape[-1]), copy=False)


class _SubblockMatrices:
    """The per-channel matrices of one sub-block length ``m``, built once (steps 1 and 3).

    The state is kept as ``g S`` (``g`` the channel's unit-gain factor): of the output's order
    whatever the bandwidth, so that its float32 copy cannot overflow.

    Attributes
    ----------
    to_state : ndarray, shape (m, 8 C)
        A mono sub-block (a row) times this gives every channel's state input
        ``g U_j = g sum_i (m - i)**j p**(m - i) x[i]``, as (moment j, channel, Re/Im) columns.
    to_state_per_channel : ndarray, shape (C, m, 8)
        The same per channel, for one signal per channel.
    to_output : ndarray, shape (C, 8 + m, m)
        Per channel, ``[state ; input] @ to_output`` is the sub-block's output: the first 8 rows
        map the start state (``Re S0, Im S0, .., Im S3``) to ``Re(p**e sum_j c_j(e) S_j)``, the
        other ``m`` are the Toeplitz matrix of the impulse response (input ``i`` to output ``e``).
    """

    def __init__(self, bank: Bank, m: int, dtype: np.dtype) -> None:
        C = bank.channels
        g = 1.0 / gain_at_cf(bank)[:, None]                        # (C, 1)
        d = np.arange(m + 1, dtype=np.float64)                      # lags 0..m
        pd = pole_powers(bank, d)                                   # (C, m+1), no recursion
        impulse = g * (d**3 * pd).real                              # normalised impulse response
        back = m - np.arange(m)                                     # input i is m - i samples from the end
        to_state = np.empty((m, 4, C, 2))
        for j in range(4):
            w = g * back**j * pd[:, back]                           # (C, m)
            to_state[:, j, :, 0], to_state[:, j, :, 1] = w.real.T, w.imag.T
        _flush_small(to_state, dtype)
        self.to_state = np.ascontiguousarray(to_state.reshape(m, 8 * C), dtype=dtype)
        self.to_state_per_channel = np.ascontiguousarray(to_state.transpose(2, 0, 1, 3).reshape(C, m, 8),
                                                         dtype=dtype)
        # y[e] = Re(p**e sum_j c_j(e) (g S_j)), c(e) = (e**3, 3e**2, 3e, 1): (e + t)**3 expanded
        e = d[:m]
        coef = np.stack([e**3, 3 * e**2, 3 * e, np.ones_like(e)])  # (4, m)
        from_state = pd[:, None, :m] * coef[None]                   # (C, 4, m) complex
        to_output = np.empty((C, 8 + m, m))
        to_output[:, 0:8:2], to_output[:, 1:8:2] = from_state.real, -from_state.imag
        lag = np.arange(m)[None, :] - np.arange(m)[:, None]         # output e - input i
        to_output[:, 8:] = np.where(lag >= 0, impulse[:, np.clip(lag, 0, m)], 0.0)
        self.to_output = np.ascontiguousarray(_flush_small(to_output, dtype), dtype=dtype)


def _grouping(K: int) -> tuple[int, int]:
    """Return ``(groups, J)`` for a pass of ``K`` sub-blocks.

    ``(0, K)`` up to _ONE_LEVEL, else ``groups`` groups of ``J`` sub-blocks, the last
    zero-padded to ``groups * J >= K``.
    """
    if K <= _ONE_LEVEL:
        return 0, K
    groups = max(1, round(math.sqrt(K / 2)))
    return groups, -(-K // groups)


def _reach(K: int) -> int:
    """Sub-blocks a pass of ``K`` reaches in the rescaled frame, padding included.

    The last group's end state is formed at ``groups * J`` sub-blocks, so that is what the frame
    must hold.
    """
    groups, J = _grouping(K)
    return groups * J if groups else K


def _one_level_map(K: int, m: int) -> np.ndarray:
    """Real (4 (K + 1), 4 (K + 1)): ``[A_0 ; V_0 .. V_(K-1)]`` to ``[A_0 .. A_K]``.

    ``A_k = B(k m) A_0 + sum_(i<k) B((k - 1 - i) m) V_i``: the recursion ``A_(k+1) = B(m) A_k + V_k`` unrolled.
    """
    H = np.zeros((K + 1, 4, K + 1, 4))
    for k in range(K + 1):
        H[k, :, 0, :] = _shift(k * m)
        for i in range(k):
            H[k, :, i + 1, :] = _shift((k - 1 - i) * m)
    return H.reshape(4 * (K + 1), 4 * (K + 1))


def _two_level_maps(groups: int, J: int, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the three real maps of the grouped recursion: ``K`` sub-blocks in ``groups`` groups of ``J``.

    Returns
    -------
    group_end : (4, 4 J)
        A group's inputs ``V_(qJ) .. V_(qJ+J-1)`` to its end state from a zero start,
        ``E_q = sum_i B((J - 1 - i) m) V_(qJ+i)``.
    coarse : (4 (2 groups + 1), same)
        ``[A_0 ; E_0 .. E_(groups-1) ; V_0, V_J, ..]`` to ``[A_0, A_J, .., A_(groups J) ; A_1, A_(J+1), ..]``:
        every group's start state, the pass's end, and the start state of every group's second
        sub-block ``A_(qJ+1) = B(m) A_(qJ) + V_(qJ)``.
    inner : (4 (J - 1), 4 (J - 1))
        Within a group, ``[A_(qJ+1) ; V_(qJ+1) .. V_(qJ+J-2)]`` to ``[A_(qJ+1) .. A_(qJ+J-1)]``.
    """
    group_end = np.zeros((4, J, 4))
    for i in range(J):
        group_end[:, i, :] = _shift((J - 1 - i) * m)
    n = 2 * groups + 1
    coarse = np.zeros((n, 4, n, 4))
    for q in range(groups + 1):                                      # A_(qJ)
        coarse[q, :, 0, :] = _shift(q * J * m)
        for i in range(q):
            coarse[q, :, 1 + i, :] = _shift((q - 1 - i) * J * m)
    for q in range(groups):                                          # A_(qJ+1)
        row = groups + 1 + q
        coarse[row, :, 0, :] = _shift((q * J + 1) * m)
        for i in range(q):
            coarse[row, :, 1 + i, :] = _shift(((q - 1 - i) * J + 1) * m)
        coarse[row, :, row, :] = _shift(0)
    inner = _one_level_map(J - 2, m)
    return group_end.reshape(4, 4 * J), coarse.reshape(4 * n, 4 * n), inner


class _PassPlan:
    """One pass shape, ``K`` sub-blocks of ``m`` samples: step 2's real maps and the scratch arrays.

    Scratch is kept between calls (fresh temporaries of this size cost page faults). Up to
    _ONE_LEVEL sub-blocks, one product gives every start state; beyond, ``groups`` groups of
    ``J`` sub-blocks (the last zero-padded): the groups' end states from a zero start, then
    every group's start state, then the start states within each group (:func:`_two_level_maps`).

    The real and complex views of the scratch that the products read and write are made here
    once (a view costs about a microsecond per call); each is listed with the array it shows.
    """

    def __init__(self, mats: _SubblockMatrices, m: int, K: int, channels: int, dtype: np.dtype) -> None:
        C = channels
        self.mats, self.m, self.K = mats, m, K
        cdtype = np.complex64 if dtype == np.float32 else np.complex128
        self.groups, self.J = _grouping(K)
        self.reach = _reach(K) * m                  # samples of the frame the pass uses, padding included
        if self.groups == 0:
            self.one_level = _one_level_map(K, m)
            state_and_inputs = np.zeros((K + 1, 4, C), dtype=np.complex128)        # [A_0 ; V_0 .. V_(K-1)]
            self.first_state = state_and_inputs[0]                  # A_0  } views of state_and_inputs
            self.inputs = state_and_inputs[1:]                      # V_k  }
            self.state_and_inputs_rows = _as_real_rows(state_and_inputs)
            self.starts = np.empty((K + 1, 4, C), dtype=np.complex128)             # A_0 .. A_K
            self.starts_rows = _as_real_rows(self.starts)
        else:
            groups, J = self.groups, self.J
            self.group_end, self.coarse, inner = _two_level_maps(groups, J, m)
            # inner is block lower-triangular: its first `half` row blocks need only the first
            # `half` input blocks (a quarter of its product saved).
            half = (J - 1) // 2
            self.inner_first = np.ascontiguousarray(inner[: 4 * half, : 4 * half])
            self.inner_rest = np.ascontiguousarray(inner[4 * half :])
            padded = np.zeros((groups * J, 4, C), dtype=np.complex128)   # V_k; the padding stays 0
            self.inputs = padded[:K]
            self.inputs_by_group = _as_real_rows(padded.reshape(groups, J, 4, C))  # (groups, 4 J, 2 C)
            self.group_firsts = padded[::J]                         # V_(qJ), later A_(qJ+1)
            coarse_in = np.empty((2 * groups + 1, 4, C), dtype=np.complex128)
            self.coarse_in_rows = _as_real_rows(coarse_in)
            self.coarse_in_state = coarse_in[0]                     # A_0        } views of coarse_in
            self.coarse_in_ends = coarse_in[1 : groups + 1].view(np.float64)   # E_q  }
            self.coarse_in_firsts = coarse_in[groups + 1 :]         # V_(qJ)     }
            self.coarse_out = np.empty((2 * groups + 1, 4, C), dtype=np.complex128)
            self.coarse_out_rows = _as_real_rows(self.coarse_out)
            self.starts = np.empty((groups * J + 1, 4, C), dtype=np.complex128)    # A_0 .. A_(groups J)
            by_group = self.starts[: groups * J].reshape(groups, J, 4, C)
            self.group_starts = by_group[:, 0]                      # A_(qJ)               } views
            later = _as_real_rows(by_group[:, 1:])                  # A_(qJ+1 .. qJ+J-1)  } views
            self.later_starts_first = later[:, : 4 * half]          # ... the first half  } of starts
            self.later_starts_rest = later[:, 4 * half :]            # ... the rest        }
            self.inner_inputs_first = self.inputs_by_group[:, : 4 * half]      # [A_(qJ+1) ; V ..] } views
            self.inner_inputs = self.inputs_by_group[:, : 4 * (J - 1)]          # } of the inputs
        self.used_starts = self.starts[:K]                          # A_0 .. A_(K-1) } views
        self.end_state = self.starts[K]                             # A_K            } of starts
        self.state_input = np.empty((K, 8 * C), dtype=dtype)                        # mono: g U_k
        self.state_input_complex = self.state_input.view(cdtype).reshape(K, 4, C)
        self.state_input_per_channel = np.empty((C, K, 8), dtype=dtype)
        self.state_input_per_channel_complex = self.state_input_per_channel.view(cdtype).transpose(1, 2, 0)
        self.start_states = np.empty((K, 4, C), dtype=np.complex128)                # S_k
        # The rescaling factors of the pass per frame offset, copied out of the group's tables and
        # repeated over the 4 moments (contiguous, they multiply about twice as fast as strided,
        # broadcast rows): a stream of equal blocks meets a few offsets again and again.
        self.rescale_at: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        # Per channel, the sub-blocks' [S_k | x_k] as columns: the output product reads its transpose
        # (measured faster than the row layout, whose filling strides badly).
        columns = np.empty((C, 8 + m, K), dtype=dtype)
        self.columns_states = columns[:, :8].reshape(C, 4, 2, K)     # } views of columns
        self.columns_input = columns[:, 8:]                         # }
        self.rows = columns.transpose(0, 2, 1)                      # } (C, K, 8 + m)
        self.start_states_by_channel = self.start_states.view(np.float64).reshape(K, 4, C, 2).transpose(2, 1, 3, 0)


def _start_states(plan: _PassPlan, state: np.ndarray) -> None:
    """Step 2: the start state of every sub-block of the pass and its end, ``A_0 .. A_K``, into ``plan.starts``.

    ``state`` (4, C) is ``A_0``; the inputs ``V_k`` are in ``plan.inputs``. Two levels: the first
    input of every group is overwritten.
    """
    if plan.groups == 0:
        plan.first_state[...] = state
        np.matmul(plan.one_level, plan.state_and_inputs_rows, out=plan.starts_rows)
        return
    plan.coarse_in_state[...] = state
    np.matmul(plan.group_end, plan.inputs_by_group, out=plan.coarse_in_ends)
    plan.coarse_in_firsts[...] = plan.group_firsts
    np.matmul(plan.coarse, plan.coarse_in_rows, out=plan.coarse_out_rows)
    groups, J = plan.groups, plan.J
    plan.group_starts[...] = plan.coarse_out[:groups]
    # A_(qJ+1) takes the place of V_(qJ), which it contains: the rest of the group's start states
    # are then one map of [A_(qJ+1) ; V_(qJ+1) .. V_(qJ+J-2)].
    plan.group_firsts[...] = plan.coarse_out[groups + 1 :]
    np.matmul(plan.inner_first, plan.inner_inputs_first, out=plan.later_starts_first)
    np.matmul(plan.inner_rest, plan.inner_inputs, out=plan.later_starts_rest)
    if plan.K == groups * J:                                # else A_K is the first padded sub-block's start
        plan.end_state[...] = plan.coarse_out[groups]


#: The automatic sub-block length: an exact division of the block between these, nearest to
#: _TARGET_SUBBLOCK (measured on x86-64: the Toeplitz product grows with the length, the state
#: products with the number of sub-blocks).
_SUBBLOCK_RANGE = (16, 32)
_TARGET_SUBBLOCK = 21
#: Up to this many sub-blocks, one product gives every start state; beyond, two levels of groups.
_ONE_LEVEL = 8
#: Sub-blocks per pass at most: longer blocks go in passes (the group products grow with it).
_MAX_SUBBLOCKS = 24
#: The rescaled frame spans at most this many of a channel group's widest channel's time
#: constants ``fs / (2 pi b)``: the rescaling multiplies by up to ``exp(_MAX_DECAY)`` (about 1e87).
_MAX_DECAY = 200.0
#: ... and at most this many samples: the length of the tables of pole powers (a pass is never longer).
_ANCHOR_SPAN = 2048
#: A channel shares its group's rescaled frame if its time constant is at most this many times the
#: group's shortest (or the group's frame reaches _ANCHOR_SPAN anyway): the frame then spans at
#: least ``_MAX_DECAY / _GROUP_RATIO = 2`` of its time constants between renormalisations.
_GROUP_RATIO = 100.0
#: Frame offsets whose rescaling factors a pass plan keeps (a stream of equal blocks meets a few).
_RESCALE_CACHE = 64
#: Plans and matrix sets kept per filterbank (least recently used dropped).
_PLAN_CACHE = 16
#: After this many different sub-block lengths, automatic mode stops adapting to the block length
#: (a stream of ever-changing block lengths would otherwise rebuild matrices all the time).
_ADAPTIVE_BUILDS = 12


def auto_subblock(length: int) -> int:
    """Sub-block length the fast form uses for a block of ``length`` samples.

    Blocks up to 32 samples are one sub-block. Longer blocks: the length between 16 and 32 that
    divides the block exactly, nearest to 21 (441 -> 21, 64 -> 16, 50 -> 25); if none divides
    it, 21, and the rest of the block goes in a pass of its own.
    """
    if length <= _SUBBLOCK_RANGE[1]:
        return max(int(length), 1)
    lo, hi = _SUBBLOCK_RANGE
    exact = [m for m in range(lo, hi + 1) if length % m == 0]
    if not exact:
        return _TARGET_SUBBLOCK
    return min(exact, key=lambda m: abs(math.log(m / _TARGET_SUBBLOCK)))


def _channel_groups(bank: Bank) -> list[np.ndarray]:
    """Channels that share one rescaled frame, widest first; usually one group of every channel.

    A group's frame is renormalised at least every ``span`` samples, ``span`` set by its widest
    channel (:data:`_MAX_DECAY`, :data:`_ANCHOR_SPAN`). A much narrower channel in the same group
    would be renormalised many times per time constant, each a rounding that compounds: it opens
    a group of its own.
    """
    spans = _MAX_DECAY / (2 * np.pi * bank.b / bank.fs)
    groups: list[list[int]] = []
    for c in np.argsort(spans, kind="stable"):
        if groups:
            widest = spans[groups[-1][0]]
            if widest >= _ANCHOR_SPAN or spans[c] <= _GROUP_RATIO * widest:
                groups[-1].append(int(c))
                continue
        groups.append([int(c)])
    return [np.array(sorted(g)) for g in groups]


class _ChannelGroup:
    """Channels sharing one rescaled frame: their bank, pole-power tables, state and anchor.

    ``state`` (4, C) holds ``A = p**-offset S``: the moments (times the unit-gain factor) at the
    current sample, rescaled to the anchor ``offset`` samples back. ``powers[t] = p**t`` and
    ``inverse_powers[t] = p**-t`` (``t = 0 .. span``), shape (1, C) each, correctly rounded.
    """

    def __init__(self, bank: Bank, channels: np.ndarray) -> None:
        self.channels = channels
        self.bank = Bank(bank.kind, bank.fs, bank.cf[channels], bank.b[channels],
                         tuple(bank.names[c] for c in channels))
        beta_max = float(np.max(2 * np.pi * self.bank.b / self.bank.fs))
        self.span = max(1, min(int(_MAX_DECAY / beta_max), _ANCHOR_SPAN))
        t = np.arange(self.span + 1.0)
        self.powers = np.ascontiguousarray(pole_powers(self.bank, t).T[:, None, :])     # (span + 1, 1, C)
        self.inverse_powers = np.ascontiguousarray(pole_powers(self.bank, -t).T[:, None, :])
        self.state = np.zeros((4, len(channels)), dtype=np.complex128)
        self.offset = 0
        self.passes = 0

    def reset(self) -> None:
        self.state[...] = 0.0
        self.offset = 0


def _filter_pass(group: _ChannelGroup, plan: _PassPlan, x: np.ndarray, dst: np.ndarray) -> None:
    """Filter one pass, ``K * m`` samples of ``x`` ((L,) or (C, L)), into ``dst`` (C, K, m); advance the state.

    With ``o = group.offset``: ``V_k = g U_k p**-(o + (k+1) m)``, ``S_k = p**(o + k m) A_k``.
    """
    m, K, mats = plan.m, plan.K, plan.mats
    # Renormalise (the anchor moves here) before any state the pass forms, the padded last group's
    # end included, would lie more than span samples from the anchor: exp(_MAX_DECAY) at most.
    if group.offset + plan.reach > group.span:
        group.state *= group.powers[group.offset]
        group.offset = 0
    o = group.offset
    rescale = plan.rescale_at.get(o)
    if rescale is None:
        rescale = (group.inverse_powers[o + m : o + (K + 1) * m : m],        # p**-(o + (k+1) m), (K, 1, C)
                   group.powers[o : o + K * m : m])                          # p**(o + k m), (K, 1, C)
        if len(plan.rescale_at) < _RESCALE_CACHE:
            rescale = (np.repeat(rescale[0], 4, axis=1), np.repeat(rescale[1], 4, axis=1))   # (K, 4, C), contiguous
            plan.rescale_at[o] = rescale
    rescale_in, rescale_out = rescale
    # 1. State inputs, rescaled to the anchor; every channel's Toeplitz input.
    X: np.ndarray
    if x.ndim == 1:
        X = x.reshape(K, m)
        np.matmul(X, mats.to_state, out=plan.state_input)
        np.multiply(plan.state_input_complex, rescale_in, out=plan.inputs)
        plan.columns_input[...] = np.ascontiguousarray(X.T)         # broadcast to every channel
    else:
        X = x.reshape(x.shape[0], K, m)
        np.matmul(X, mats.to_state_per_channel, out=plan.state_input_per_channel)
        np.multiply(plan.state_input_per_channel_complex, rescale_in, out=plan.inputs)
        plan.columns_input[...] = X.transpose(0, 2, 1)
    # 2. Start states A_0 .. A_K in the rescaled frame (real, channel-independent maps).
    _start_states(plan, group.state)
    # 3. The output: per channel [S_k | x_k] @ to_output, S_k = p**(o + k m) A_k.
    np.multiply(plan.used_starts, rescale_out, out=plan.start_states)
    plan.columns_states[...] = plan.start_states_by_channel
    np.matmul(plan.rows, mats.to_output, out=dst)
    group.state[...] = plan.end_state
    group.offset = o + K * m
    group.passes += 1
    if group.passes % _FLUSH_EVERY == 0:
        _flush_tiny(group.state)


def _flush_tiny(state: np.ndarray) -> None:
    """Set state entries below about 1e-287 to exactly 0, in place (``s + c - c``, exact for larger ones)."""
    real = state.view(np.float64)
    real += _FLUSH_OFFSET
    real -= _FLUSH_OFFSET


class GammatoneFilterbank(FilterbankBase):
    """Stateful streaming filterbank, the fast exact form: every channel of a block in one pass.

    Parameters
    ----------
    bank : Bank
        Centre frequencies, bandwidths and sample rate.
    dtype : {numpy.float64, numpy.float32}
        Arithmetic of the two large products and type of the output (default float64).
        The state computation is float64 either way; float32 is faster for long
        blocks, with an error of a few 1e-7 (docs/stability.md).
    subblock : int or None
        Sub-block length ``m`` of the block state-space form, 1..4096; None (default)
        picks it per block length (:func:`auto_subblock`). It is capped where the widest
        channel would decay by more than ``exp(200)`` over one sub-block. Results do not
        depend on it beyond rounding.
    nonfinite : {"raise", "zero"}
        See :class:`FilterbankBase`.

    Notes
    -----
    Input of :meth:`process` is either a mono block, shape (L,), fed to every
    channel (a microphone into the cochlea; one texture signal into every
    whisker), or one signal per channel, shape (channels, L). The output is
    always (channels, L). Any partition of a signal into blocks gives the same
    output as one call on the whole signal, to rounding (docs/stability.md).

    Not thread-safe: one instance belongs to one stream.
    """

    backend = "fast"

    def __init__(self, bank: Bank, dtype=np.float64, subblock: int | None = None,
                 nonfinite: str = "raise") -> None:
        super().__init__(bank, dtype, nonfinite)
        if subblock is not None and not (isinstance(subblock, (int, np.integer)) and 1 <= subblock <= 4096):
            raise InputError(f"subblock must be None (automatic) or an integer in 1..4096, got {subblock!r}")
        self.subblock = None if subblock is None else int(subblock)
        self._groups = [_ChannelGroup(bank, channels) for channels in _channel_groups(bank)]
        # Least-recently-used caches: matrices per (group, m), plans per (group, m, K).
        self._matrices: OrderedDict[tuple, _SubblockMatrices] = OrderedDict()
        self._plans: OrderedDict[tuple, _PassPlan] = OrderedDict()
        self._layouts: dict[tuple, list] = {}
        self._builds = 0

    def reset(self) -> None:
        """Return to rest: zero every channel group's state, as if no sample had been seen (counters are kept)."""
        for group in self._groups:
            group.reset()

    def _fresh(self) -> GammatoneFilterbank:
        return GammatoneFilterbank(self.bank, self.dtype, self.subblock)

    def _layout(self, L: int, group: int = 0) -> list:
        """Return the passes a block of ``L`` samples goes in: ``[(m, K), ...]``, ``K * m`` samples each."""
        passes = self._layouts.get((group, L))
        if passes is None:
            span = self._groups[group].span
            if self.subblock is not None:
                m = self.subblock
            elif self._builds >= _ADAPTIVE_BUILDS:
                m = _TARGET_SUBBLOCK
            else:
                m = auto_subblock(L)
            m = max(1, min(m, L, span))
            per_pass = max(1, min(_MAX_SUBBLOCKS, span // m))
            # The passes below hold at most per_pass sub-blocks each; none may reach past the span.
            while per_pass > 1 and max(map(_reach, range(1, per_pass + 1))) * m > span:
                per_pass -= 1
            K, r = divmod(L, m)
            n = -(-K // per_pass)
            passes = [(m, K // n + (i < K % n)) for i in range(n)]
            if r:
                passes.append((r, 1))
            if len(self._layouts) > 256:
                self._layouts.clear()
            self._layouts[(group, L)] = passes
        return passes

    def _plan(self, group: int, m: int, K: int) -> _PassPlan:
        key = (group, m, K)
        plan = self._plans.get(key)
        if plan is not None:
            self._plans.move_to_end(key)                    # least recently used is dropped first
        else:
            mats = _lru_get(self._matrices, (group, m))
            if mats is None:
                mats = _SubblockMatrices(self._groups[group].bank, m, self.dtype)
                _lru_put(self._matrices, (group, m), mats)
                self._builds += 1
            plan = _PassPlan(mats, m, K, len(self._groups[group].channels), self.dtype)
            _lru_put(self._plans, (group, m, K), plan)
        return plan

    def _filter(self, x: np.ndarray, out: np.ndarray | None) -> np.ndarray:
        C, L = self.channels, x.shape[-1]
        y = np.empty((C, L), dtype=self.dtype) if out is None else out
        if len(self._groups) == 1:
            passes = self._layout(L)
            if len(passes) == 1 and y.flags.c_contiguous:          # the common case, kept short
                m, K = passes[0]
                _filter_pass(self._groups[0], self._plan(0, m, K), x, y.reshape(C, K, m))
            else:
                self._filter_group(0, x, y)
            return y
        for g, group in enumerate(self._groups):
            rows = np.empty((len(group.channels), L), dtype=self.dtype)
            self._filter_group(g, x if x.ndim == 1 else x[group.channels], rows)
            y[group.channels] = rows
        return y

    def _filter_group(self, g: int, x: np.ndarray, y: np.ndarray) -> None:
        """Filter one channel group's block ``x`` into its rows ``y`` (C_group, L), pass by pass."""
        group, a = self._groups[g], 0
        for m, K in self._layout(x.shape[-1], g):
            b = a + m * K
            dst = y[:, a:b].reshape(y.shape[0], K, m)
            if np.may_share_memory(dst, y):
                _filter_pass(group, self._plan(g, m, K), x[..., a:b], dst)
            else:                                  # y's rows are not evenly strided: go through a copy
                _filter_pass(group, self._plan(g, m, K), x[..., a:b], dst)
                y[:, a:b] = dst.reshape(y.shape[0], -1)
            a = b


def _lru_get(cache: OrderedDict, key):
    """Return the cached value (marked most recently used), or None."""
    value = cache.get(key)
    if value is not None:
        cache.move_to_end(key)
    return value


def _lru_put(cache: OrderedDict, key, value) -> None:
    """Cache a value, dropping the least recently used beyond _PLAN_CACHE entries."""
    cache[key] = value
    if len(cache) > _PLAN_CACHE:
        cache.popitem(last=False)


def relative_error(y, y_ref, axis=None, floor: float = 0.0):
    """``max |y - y_ref| / max |y_ref|``: the project's error figure.

    Parameters
    ----------
    y, y_ref : array_like
        What is measured and its reference, same shape (compared in float64).
    axis : int, tuple of int or None, optional
        None (default): one figure over everything compared, a float. The axes compared over
        (``-1`` for filterbank output of shape (channels, samples)): one figure per channel,
        an ndarray.
    floor : float, optional
        The divisor is ``max(max |y_ref|, floor)``: with a floor, an error is measured against
        at least that scale (e.g. the input's amplitude, where a response is near 0). Where the
        divisor is 0, the figure is ``max |y - y_ref|``. Default 0.

    A NaN or Inf in ``y`` gives a NaN or Inf figure.
    """
    y = np.asarray(y, dtype=np.float64)
    y_ref = np.asarray(y_ref, dtype=np.float64)
    if y.size == 0:
        return 0.0 if axis is None else np.zeros(np.delete(y.shape, axis))
    with np.errstate(invalid="ignore", over="ignore"):
        diff = np.max(np.abs(y - y_ref), axis=axis)
    scale = np.maximum(np.max(np.abs(y_ref), axis=axis), floor)
    err = diff / np.where(scale == 0, 1.0, scale)
    return float(err) if axis is None else err
