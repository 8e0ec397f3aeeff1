"""Exact impulse-invariant 4th-order gammatone filterbank, streaming, all channels at once.

The analytic gammatone ``g(t) = t**3 exp(-2 pi b t) cos(2 pi fc t)`` sampled at
``t = n/fs`` is, up to the constant ``fs**-3``, ``Re(n**3 p**n)`` with the pole
``p = exp((-2 pi b + 2j pi fc) / fs)``. This module realises exactly that
sequence, normalised to unit gain at ``fc``. (:mod:`supramodal.backends` holds
the plain per-channel reference realisation and the backend interface.)

How it streams
--------------
For a block starting at stream index ``n0`` the past inputs enter only through
four complex "moments" per channel, ``S_j = sum_{m>=1} m**j p**m x[n0-m]``
(``j = 0..3``), because ``(d+m)**3`` expands binomially. Output and state update
over a sub-block of ``l`` samples are then closed-form:

* ``y[n0+d] = Re(p**d (d**3 S0 + 3 d**2 S1 + 3 d S2 + S3) + sum_i h[d-i] x[n0+i])``
* ``S'_j = p**l sum_r C(j, r) l**(j-r) S_r + sum_i (l-i)**j p**(l-i) x[n0+i]``

A block is cut into sub-blocks of ``m`` samples (24 to 64, chosen per block
length). One batched matrix product gives every channel's state inputs and
within-sub-block responses (``X @ [W | T]``, a mono block broadcast against the
channels' matrices); the start states of all sub-blocks come from one more
product on those inputs (for up to 12 sub-blocks; longer blocks go in groups,
and only the groups' start states are recursed on, one Python step per group);
a last batched product adds the states' part of the output. Large temporaries
are kept between calls: fresh multi-megabyte arrays cost page faults every block.

Precision
---------
* Every matrix entry and every pole power is computed once, from the closed form,
  with the phase ``2 pi fc d / fs`` reduced modulo ``2 pi`` in extended precision
  (``numpy.longdouble``) and rounded once: nothing is ever recursed on but the
  state, so nothing drifts, and the phase error after ``n`` samples is about
  ``(n / m) * 1e-16`` rad instead of ``n * fc/fs * 1e-16``.
* The state recursion is always float64 (complex128). With ``dtype=float32`` the
  three large products (Toeplitz, input-to-state, state-to-output) run in float32
  and the output is float32; its error is a few 1e-7 of the output's scale and
  does not grow with stream length (docs/stability.md).
* States below about 1e-287 are flushed to zero after each block: subnormal
  numbers make matrix products many times slower and carry nothing here.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from math import comb

import numpy as np

from supramodal.banks import Bank

_LD = np.longdouble
_TWO_PI_LD = 2 * np.arccos(_LD(-1))      # 2 pi to long-double precision

#: ``S + c - c`` rounds every |S| below ``c * 2**-53`` (about 1e-287) to exactly 0.
_FLUSH_OFFSET = 2.0**-900
#: Matrix entries below this are set to 0 (no subnormal operands in float32 products).
_FLUSH_MATRIX = {np.dtype(np.float64): 1e-290, np.dtype(np.float32): 1e-35}

#: Smallest bandwidth parameter accepted, as a fraction of the sample rate: the impulse
#: response then lasts ~1e8 samples and float64 holds its phase to ~1e-9 (docs/stability.md).
MIN_B_OVER_FS = 1e-7

#: Matrix sets kept per filterbank (one per sub-block length in use).
_MATRIX_CACHE = 6
#: Up to this many sub-blocks, their states come from one matrix product (no recursion);
#: beyond, groups of about _GROUP sub-blocks.
_SINGLE_GROUP = 12
_GROUP = 6


def _pole(bank: Bank) -> np.ndarray:
    """Complex pole per channel, shape (channels,)."""
    return pole_powers(bank, np.ones(1))[:, 0]


def pole_powers(bank: Bank, d) -> np.ndarray:
    """``p**d`` per channel for real exponents ``d``, correctly rounded to complex128.

    The phase ``2 pi fc d / fs`` is reduced modulo ``2 pi`` in extended precision
    first, so large ``d`` lose nothing to the float64 rounding of ``2 pi fc / fs``.

    Returns
    -------
    ndarray, shape (channels,) + numpy.shape(d), complex128
    """
    d = np.asarray(d, dtype=_LD)
    cf = bank.cf.astype(_LD).reshape((-1,) + (1,) * d.ndim)
    b = bank.b.astype(_LD).reshape(cf.shape)
    fs = _LD(bank.fs)
    turns = np.fmod(cf * d / fs, _LD(1))
    phase = _TWO_PI_LD * turns
    mag = np.exp(-_TWO_PI_LD * b * d / fs)
    out = np.empty(np.broadcast_shapes(cf.shape, d.shape), dtype=np.complex128)
    out.real = (mag * np.cos(phase)).astype(np.float64)
    out.imag = (mag * np.sin(phase)).astype(np.float64)
    return out


def _moment_sum(q):
    """``sum_{m>=0} m**3 q**m = q (1 + 4q + q**2) / (1 - q)**4`` for ``|q| < 1``."""
    return q * (1 + 4 * q + q * q) / (1 - q) ** 4


def _moment_sum_log(z):
    """:func:`_moment_sum` of ``q = exp(z)``, ``Re z < 0``, with ``1 - q`` taken as ``-expm1(z)``:
    exact to rounding even when ``|q|`` is within 1e-6 of 1 (narrow filters at high sample
    rates), where ``1 - q`` would lose digits."""
    q = np.exp(z)
    return q * (1 + 4 * q + q * q) / np.expm1(z) ** 4


def gain_at_cf(bank: Bank) -> np.ndarray:
    """Magnitude at ``fc`` of the un-normalised sampled response ``Re(n**3 p**n)``, per channel.

    The real sequence's transform is ``(H(w) + conj(H(-w))) / 2`` with
    ``H(w) = sum n**3 (p e**(-jw))**n`` in closed form; the second term matters
    for low ``fc`` and wide ``b``. At ``w = 2 pi fc / fs`` the first term's ratio
    ``p e**(-jw)`` is the real ``exp(-2 pi b / fs)`` exactly.
    """
    beta = 2 * np.pi * bank.b / bank.fs
    theta2 = 4 * np.pi * bank.cf / bank.fs
    h_pos = _moment_sum_log(-beta + 0j)
    h_neg = _moment_sum_log(-beta + 1j * theta2)
    return np.abs(h_pos + np.conj(h_neg)) / 2


def reference_impulse_response(bank: Bank, n: int) -> np.ndarray:
    """The sampled analytic gammatone, normalised to unit gain at ``fc``: the reference.

    Computed directly from ``t**3 exp(-2 pi b t) cos(2 pi fc t)`` (not from the
    pole form the filter uses), so comparing against it is an independent check.
    The argument ``2 pi fc k / fs`` is evaluated in ``numpy.longdouble`` (64-bit
    mantissa on x86-64) and reduced modulo one turn before the cosine: in float64
    its rounding grows like ``k * 1e-16`` rad, which over tens of thousands of
    samples (narrow ``b``) would make the reference less accurate than the filter
    it judges. Where ``longdouble`` is only float64 (some ARM platforms) it is
    float64 again.

    Returns
    -------
    ndarray, shape (channels, n), float64
    """
    k = np.arange(n, dtype=_LD)
    b = bank.b.astype(_LD)[:, None]
    cf = bank.cf.astype(_LD)[:, None]
    fs = _LD(bank.fs)
    h = k**3 * np.exp(-_TWO_PI_LD * b * k / fs) * np.cos(_TWO_PI_LD * np.fmod(cf * k / fs, _LD(1)))
    return (h / gain_at_cf(bank).astype(_LD)[:, None]).astype(np.float64)


def check_bandwidths(bank: Bank) -> None:
    """Refuse bandwidths too narrow for float64 to hold the filter (``b < MIN_B_OVER_FS * fs``)."""
    bad = np.flatnonzero(bank.b < MIN_B_OVER_FS * bank.fs)
    if bad.size:
        k = int(bad[0])
        raise ValueError(
            f"bandwidth parameter b of channel {bank.names[k]} is {bank.b[k]:g} Hz, below {MIN_B_OVER_FS:g} * fs = "
            f"{MIN_B_OVER_FS * bank.fs:g} Hz: its impulse response would last over 1e8 samples, beyond what "
            "float64 holds to the documented error (docs/stability.md); widen it or lower the sample rate")


class FilterbankBase:
    """What every filterbank backend shares: parameters, input checks, the non-finite policy.

    Subclasses implement :meth:`reset` and ``_filter(x)`` (``x`` already checked,
    of the filterbank's dtype, shape (L,) or (channels, L), L >= 1).

    Parameters
    ----------
    bank : Bank
    dtype : {numpy.float64, numpy.float32}
    nonfinite : {"raise", "zero"}
        What to do with NaN or Inf input samples: raise ValueError (default), or
        replace them by 0 and count them in :attr:`nonfinite_count`, so that a
        bad sample never poisons the filter state.
    """

    backend = "base"

    def __init__(self, bank: Bank, dtype=np.float64, nonfinite: str = "raise") -> None:
        dtype = np.dtype(dtype)
        if dtype not in (np.dtype(np.float64), np.dtype(np.float32)):
            raise ValueError(f"dtype must be float64 or float32, got {dtype}")
        if nonfinite not in ("raise", "zero"):
            raise ValueError(f"nonfinite must be 'raise' or 'zero', got {nonfinite!r}")
        check_bandwidths(bank)
        self.bank = bank
        self.channels = bank.channels
        self.dtype = dtype
        self.nonfinite = nonfinite
        self.nonfinite_count = 0
        self.samples_processed = 0

    def reset(self) -> None:
        """Return to rest: zero state, as if no sample had been seen. Counters are kept."""
        raise NotImplementedError

    def prepare(self, x) -> np.ndarray:
        """Check a block and convert it to the filterbank's dtype; apply the non-finite policy.

        Returns the block as it will be filtered: shape (L,) or (channels, L), NaN
        and Inf replaced by 0 (and counted) under ``nonfinite="zero"``.
        """
        x = np.asarray(x)
        if x.dtype.kind not in "fiu":
            raise ValueError(
                f"input samples must be real numbers (float or int), got dtype {x.dtype}; "
                "convert complex or text data before filtering"
            )
        if not (x.ndim == 1 or (x.ndim == 2 and x.shape[0] == self.channels)):
            raise ValueError(
                f"input block must have shape (L,) (mono, fed to all {self.channels} channels) or "
                f"({self.channels}, L) (one signal per channel); got shape {x.shape}"
            )
        if x.dtype != self.dtype:
            x = x.astype(self.dtype)
        # One BLAS dot product decides the common case (and raises no floating-point warning):
        # a finite sum of squares means every sample is finite.
        if x.size and not math.isfinite(np.vdot(x, x)):
            bad = ~np.isfinite(x)
            n_bad = int(bad.sum())
            if n_bad:
                if self.nonfinite == "raise":
                    raise ValueError(
                        f"input block contains {n_bad} NaN or Inf sample(s) (first at index "
                        f"{np.argwhere(bad)[0].tolist()}); clean the signal, or create the filterbank with "
                        "nonfinite='zero' to replace and count them"
                    )
                self.nonfinite_count += n_bad
                x = np.where(bad, 0.0, x).astype(self.dtype, copy=False)
        return x

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
            raise ValueError(f"out must be a {self.dtype} array of shape {(self.channels, L)}, "
                             f"got {out.dtype} {out.shape}")
        if L == 0:
            return np.empty((self.channels, 0), dtype=self.dtype) if out is None else out
        y = self._filter(x, out)
        self.samples_processed += L
        return y

    def _filter(self, x: np.ndarray, out: np.ndarray | None) -> np.ndarray:
        raise NotImplementedError

    def _fresh(self) -> "FilterbankBase":
        raise NotImplementedError

    def impulse_response(self, n: int) -> np.ndarray:
        """Response of a fresh filterbank of the same design to a unit impulse, shape (channels, n)."""
        x = np.zeros(n)
        if n:
            x[0] = 1.0
        return self._fresh().process(x)


def _transition(bank: Bank, l: int):
    """State transition over ``l`` samples, ``S' = (S @ B) * pl``: B (4, 4) complex, pl (C, 1)."""
    B = np.array([[comb(j, r) * float(l) ** (j - r) if r <= j else 0.0 for j in range(4)] for r in range(4)])
    pl = pole_powers(bank, np.array([float(l)]))
    if l > 0 and np.any(np.abs(pl) >= 1.0):
        raise ValueError("a pole power rounds to magnitude >= 1: the bandwidth is too narrow for float64")
    return B.astype(np.complex128), pl


class _SubblockMatrices:
    """Everything the fast form needs for one sub-block length ``m``, built once."""

    def __init__(self, bank: Bank, m: int, dtype: np.dtype) -> None:
        C = bank.channels
        self.m = m
        g = 1.0 / gain_at_cf(bank)[:, None]                        # (C, 1)
        d = np.arange(m + 1, dtype=np.float64)                      # lags 0..m
        pd = pole_powers(bank, d)                                   # (C, m+1), no recursion
        h = g * (d**3 * pd).real                                    # normalised impulse response

        # Per channel, one matrix for a sub-block's input x (row vector of m samples):
        # x @ TW[c] = [state input (4 complex moments as Re, Im pairs) | Toeplitz part (m outputs)].
        # The state is kept as g * S (the moments times the channel's normalising gain): of the
        # output's order whatever the bandwidth, so that its float32 copy cannot overflow.
        TW = np.zeros((C, m, 8 + m))
        back = m - np.arange(m)                                     # input i is m - i samples from the end
        for j in range(4):
            w = g * back**j * pd[:, back]                           # g (m - i)**j p**(m - i)
            TW[:, :, 2 * j], TW[:, :, 2 * j + 1] = w.real, w.imag
        lag = np.arange(m)[None, :] - np.arange(m)[:, None]         # output e - input i
        TW[:, :, 8:] = np.where(lag >= 0, h[:, np.clip(lag, 0, m)], 0.0)
        # State-to-output: y[e] = Re(p**e sum_j coef_j(e) (g S_j)), coef = (e**3, 3e**2, 3e, 1).
        e = d[:m]
        coef = np.stack([e**3, 3 * e**2, 3 * e, np.ones_like(e)])  # (4, m)
        Oc = pd[:, None, :m] * coef[None]                           # (C, 4, m)
        O = np.empty((C, 8, m))
        O[:, 0::2], O[:, 1::2] = Oc.real, -Oc.imag
        tiny = _FLUSH_MATRIX[dtype]
        for arr in (TW, O):
            arr[np.abs(arr) < tiny] = 0.0
        self.TW = np.ascontiguousarray(TW, dtype=dtype)
        self.O = np.ascontiguousarray(O, dtype=dtype)
        self._bank = bank
        self._rest: dict[int, tuple] = {}
        self._groups: dict[int, tuple] = {}

    def rest(self, r: int):
        """Transition over a last, partial sub-block of ``r`` samples."""
        if r not in self._rest:
            self._rest[r] = _transition(self._bank, r)
        return self._rest[r]

    def powers(self, n: int) -> list:
        """``Phi**k`` per channel for k = 0..n, each (C, 4, 4), from the closed form."""
        out = []
        for k in range(n + 1):
            B, pl = _transition(self._bank, k * self.m)
            out.append(pl[:, :, None] * B[None])
        return out

    def single(self, K: int) -> np.ndarray:
        """``H[c]`` (4(K+1), 4(K+1)): ``[S_0 | U_0 .. U_(K-1)] @ H[c]`` = the start states of
        sub-blocks 0..K (block (0, j) = Phi**j; block (i+1, j) = Phi**(j-1-i) for j > i)."""
        key = ("single", K)
        if key not in self._groups:
            C = self._bank.channels
            phi = self.powers(K)
            H = np.zeros((C, 4 * (K + 1), 4 * (K + 1)), dtype=np.complex128)
            for j in range(K + 1):
                H[:, 0:4, 4 * j : 4 * j + 4] = phi[j]
                for i in range(j):
                    H[:, 4 * (i + 1) : 4 * (i + 2), 4 * j : 4 * j + 4] = phi[j - 1 - i]
            H[np.abs(H) < _FLUSH_MATRIX[np.dtype(np.float64)]] = 0.0
            self._groups[key] = H
        return self._groups[key]

    def group(self, J: int):
        """For groups of ``J`` sub-blocks: (G, P, (B, pl) over J sub-blocks).

        ``G[c]`` (4J, 4J) maps the state inputs of a group's sub-blocks to the states after
        each of them from a zero start (block (i, j) = Phi**(j - i), i <= j); ``P[c]`` (4, 4J)
        maps a group's start state to the start states of its sub-blocks (block j = Phi**j);
        ``Phi**n = p**(n m) B(n m)`` comes from the closed form for every n.
        """
        if J not in self._groups:
            C = self._bank.channels
            blocks = self.powers(J)                                  # (C, 4, 4): Phi**n per channel
            G = np.zeros((C, 4 * J, 4 * J), dtype=np.complex128)
            P = np.empty((C, 4, 4 * J), dtype=np.complex128)
            for j in range(J):
                P[:, :, 4 * j : 4 * j + 4] = blocks[j]
                for i in range(j + 1):
                    G[:, 4 * i : 4 * i + 4, 4 * j : 4 * j + 4] = blocks[j - i]
            tiny = _FLUSH_MATRIX[np.dtype(np.float64)]
            G[np.abs(G) < tiny] = 0.0
            P[np.abs(P) < tiny] = 0.0
            self._groups[J] = (G, P, _transition(self._bank, J * self.m))
        return self._groups[J]


#: The automatic sub-block length aims at about this many samples (measured on x86-64: the
#: Toeplitz product grows with it, the number of state steps shrinks); 32 for short blocks.
_TARGET_SUBBLOCK = 48
_TARGET_SHORT = 32
#: After this many different sub-block lengths, automatic mode stops adapting to the block length
#: (a stream of ever-changing block lengths would otherwise rebuild matrices all the time).
_ADAPTIVE_BUILDS = 12
_FIXED_SUBBLOCK = 32


def auto_subblock(length: int) -> int:
    """Sub-block length the fast form uses for a block of ``length`` samples.

    Blocks up to 40 samples are one sub-block. Longer blocks are cut into ``K``
    sub-blocks of 24 to 64 samples, preferring an exact division (no padded
    samples) with a length near 48 (32 for blocks up to 128 samples); otherwise the
    sub-block nearest that length.
    """
    if length <= 40:
        return max(int(length), 1)
    target = _TARGET_SHORT if length <= 128 else _TARGET_SUBBLOCK
    best = None
    for K in range(-(-length // 64), -(-length // 24) + 1):
        m = -(-length // K)
        exact = m * K == length
        score = (not exact, abs(math.log(m / target)))
        if best is None or score < best[0]:
            best = (score, m)
    return best[1]


class GammatoneFilterbank(FilterbankBase):
    """Stateful streaming filterbank, the fast exact form: every channel of a block in one pass.

    Parameters
    ----------
    bank : Bank
        Centre frequencies, bandwidths and sample rate.
    dtype : {numpy.float64, numpy.float32}
        Arithmetic of the large products and type of the output (default float64).
        The state recursion is float64 either way; float32 is faster for long
        blocks, with an error of a few 1e-7 (docs/stability.md).
    subblock : int or None
        Sub-block length ``m`` of the block state-space form, 1..4096; None (default)
        picks it per block length (:func:`auto_subblock`). Results do not depend on
        it beyond rounding.
    nonfinite : {"raise", "zero"}
        See :class:`FilterbankBase`.

    Notes
    -----
    Input of :meth:`process` is either a mono block, shape (L,), fed to every
    channel (a microphone into the cochlea; one texture signal into every
    whisker), or one signal per channel, shape (channels, L). The output is
    always (channels, L). Any partition of a signal into blocks gives the same
    output as one call on the whole signal, to rounding (about 1e-15 relative in
    float64).

    Not thread-safe: one instance belongs to one stream.
    """

    backend = "fast"

    def __init__(self, bank: Bank, dtype=np.float64, subblock: int | None = None,
                 nonfinite: str = "raise") -> None:
        super().__init__(bank, dtype, nonfinite)
        if subblock is not None and not (isinstance(subblock, (int, np.integer)) and 1 <= subblock <= 4096):
            raise ValueError(f"subblock must be None (automatic) or an integer in 1..4096, got {subblock!r}")
        self.subblock = None if subblock is None else int(subblock)
        self._matrices: OrderedDict[int, _SubblockMatrices] = OrderedDict()
        self._cdtype = np.complex64 if self.dtype == np.float32 else np.complex128
        self._builds = 0
        self._auto_memo: dict[int, int] = {}
        self._scratch: dict[str, np.ndarray] = {}
        self.reset()

    def reset(self) -> None:
        self._state = np.zeros((self.channels, 4), dtype=np.complex128)

    def _fresh(self) -> "GammatoneFilterbank":
        return GammatoneFilterbank(self.bank, self.dtype, self.subblock)

    def _auto(self, L: int) -> int:
        m = self._auto_memo.get(L)
        if m is None:
            if self._builds >= _ADAPTIVE_BUILDS:
                m = min(_FIXED_SUBBLOCK, L)
            else:
                m = auto_subblock(L)
            if len(self._auto_memo) > 256:
                self._auto_memo.clear()
            self._auto_memo[L] = m
        return m

    def _get(self, m: int) -> _SubblockMatrices:
        mats = self._matrices.get(m)
        if mats is None:
            mats = self._matrices[m] = _SubblockMatrices(self.bank, m, self.dtype)
            self._builds += 1
            if len(self._matrices) > _MATRIX_CACHE:
                self._matrices.popitem(last=False)
        else:
            self._matrices.move_to_end(m)
        return mats

    def _work(self, name: str, shape: tuple, dtype) -> np.ndarray:
        """A scratch array kept between calls: fresh multi-megabyte temporaries cost page faults
        on every block (the allocator hands large freed blocks back to the system)."""
        key = (name, shape, dtype)
        a = self._scratch.get(key)
        if a is None:
            if len(self._scratch) > 64:
                self._scratch.clear()
            a = self._scratch[key] = np.empty(shape, dtype=dtype)
        return a

    def _filter(self, x: np.ndarray, out: np.ndarray | None) -> np.ndarray:
        C = self.channels
        L = x.shape[-1]
        m = self.subblock or self._auto(L)
        mats = self._get(m)
        K, r = divmod(L, m)
        Kout = K + (r > 0)
        if r:
            X = self._work("X", x.shape[:-1] + (Kout * m,), self.dtype)
            X[..., :L] = x
            X[..., L:] = 0.0
        else:
            X = x
        X = X.reshape(x.shape[:-1] + (Kout, m))
        # Every channel's state inputs and within-sub-block responses: (C, Kout, 8 + m). A mono
        # block (Kout, m) is broadcast against the channels' matrices.
        Z = np.matmul(X, mats.TW, out=self._work("Z", (C, Kout, 8 + m), self.dtype))
        st = self._states(mats, Z[:, :K, :8].view(self._cdtype), K)       # (C, K + 1, 4), complex128
        if r:
            # The last, partial sub-block: its state input from the last r rows of its matrix.
            B, pr = mats.rest(r)
            ur = np.matmul(x[..., None, K * m :], mats.TW[:, m - r :, :8])[:, 0]
            end = (st[:, K] @ B) * pr + ur.view(self._cdtype)
        else:
            end = st[:, K].copy()
        states = st[:, :Kout]
        if self.dtype != np.float64:
            states = states.astype(self._cdtype)
        y = np.matmul(states.view(self.dtype), mats.O,
                      out=None if out is None else self._work("Y", (C, Kout, m), self.dtype))
        flat = end.view(np.float64)
        flat += _FLUSH_OFFSET
        flat -= _FLUSH_OFFSET
        self._state = end
        if out is not None and not r:
            blocks = out.reshape(C, K, m)                                 # a view when out's rows are
            if np.may_share_memory(blocks, out):                          # contiguous, as the pipeline's are
                np.add(y, Z[:, :, 8:], out=blocks)
                return out
        y += Z[:, :, 8:]
        y = y.reshape(C, Kout * m)[:, :L]
        if out is not None:
            out[...] = y
            return out
        return y

    def _states(self, mats: _SubblockMatrices, U: np.ndarray, K: int) -> np.ndarray:
        """Start states of sub-blocks 0..K from the state now and the inputs ``U`` (C, K, 4).

        Sub-blocks go in groups of J: the states inside a group come from one matrix
        product on the group's inputs; only the group start states are recursed on,
        in a Python loop of ceil(K / J) steps of float64 arithmetic.
        """
        C = self.channels
        if K <= _SINGLE_GROUP:
            # One product: [S_0 | U_0 .. U_(K-1)] @ H gives every start state at once.
            inputs = self._work("in", (C, K + 1, 4), np.complex128)
            inputs[:, 0] = self._state
            inputs[:, 1:] = U
            st = np.matmul(inputs.reshape(C, 1, 4 * (K + 1)), mats.single(K),
                           out=self._work("st", (C, 1, 4 * (K + 1)), np.complex128))
            return st.reshape(C, K + 1, 4)
        st = self._work("st", (C, K + 1, 4), np.complex128)
        matmul, multiply, add = np.matmul, np.multiply, np.add
        J = _group_size(K, C)
        nc = -(-K // J)
        G, P, (BJ, pJ) = mats.group(J)
        Upad = self._work("U", (C, nc * J, 4), np.complex128)
        Upad[:, :K] = U
        Upad[:, K:] = 0.0
        local = np.matmul(Upad.reshape(C, nc, 4 * J), G, out=self._work("local", (C, nc, 4 * J), np.complex128))
        local = local.reshape(C, nc, J, 4)                                      # zero-start states
        starts = np.empty((nc + 1, C, 4), dtype=np.complex128)                 # group start states
        starts[0] = self._state
        tmp = np.empty((C, 4), dtype=np.complex128)
        ends = local[:, :, J - 1]
        for q in range(nc):
            matmul(starts[q], BJ, out=tmp)
            multiply(tmp, pJ, out=tmp)
            add(tmp, ends[:, q], out=starts[q + 1])
        full = np.matmul(starts[:nc].transpose(1, 0, 2), P, out=self._work("full", (C, nc, 4 * J), np.complex128))
        full = full.reshape(C, nc, J, 4)
        full[:, :, 1:] += local[:, :, : J - 1]
        full = full.reshape(C, nc * J, 4)
        if nc * J > K:
            return full[:, : K + 1]
        st[:, :K] = full
        st[:, K] = starts[nc]
        return st


def _group_size(K: int, channels: int) -> int:
    """Sub-blocks per group of the two-level state computation (see ``_states``)."""
    if K <= _SINGLE_GROUP:
        return K
    nc = -(-K // _GROUP)
    return -(-K // nc)


def relative_error(y, y_ref) -> float:
    """``max |y - y_ref| / max |y_ref|`` over everything compared: the project's error figure."""
    y = np.asarray(y, dtype=np.float64)
    y_ref = np.asarray(y_ref, dtype=np.float64)
    scale = np.max(np.abs(y_ref))
    if scale == 0:
        return float(np.max(np.abs(y))) if y.size else 0.0
    return float(np.max(np.abs(y - y_ref)) / scale)
