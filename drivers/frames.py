"""Binary frame format of the whisker array's serial link, version 1.

A frame carries ``samples_per_frame`` consecutive samples of every channel.
All multi-byte fields are little-endian::

    offset size  field
    0      2     sync word, bytes A5 5A
    2      1     version (1)
    3      1     flags (bit 0: device overrun before this frame; others 0)
    4      2     sequence counter, u16, +1 per frame, wraps 65535 -> 0
    6      2     samples per frame n, u16, 1..4096
    8      1     channel count c, u8, 1..64
    9      1     header check: 0xFF XOR bytes 2..8
    10     2*n*c payload: int16 samples, frame-major
                 (sample 0 of channels 0..c-1, then sample 1, ...)
    10+2nc 4     CRC-32 (zlib.crc32, IEEE 802.3) of bytes 0 .. 10+2nc-1

Overhead is 14 bytes per frame. Full scale is 32768: a sample ``s`` means
``s / 32768`` of full scale. See ``docs/serial-frames.md`` for the rationale,
a worked example and the C side.

Why A5 5A: near-zero int16 samples are 00 xx / FF xx / xx 00 / xx FF bytes, and
both A5 and 5A as the high byte of a sample mean |x| ~ 0.7 of full scale, so
the sync word is rare inside the payload wherever it is aligned. Why a header
check byte: a false sync in garbage with a plausible length would otherwise
make the decoder wait for up to 512 kB before the CRC can reject it.

Threading: :func:`encode_frame` is pure. A :class:`FrameDecoder` holds a
buffer and counters and must be used from one thread at a time.

``python -m supramodal.benchmarks.frame_decoding`` measures the decoder's throughput.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import numpy as np

from supramodal.errors import InputError

SYNC = b"\xa5\x5a"
VERSION = 1
HEADER_SIZE = 10
CRC_SIZE = 4
OVERHEAD = HEADER_SIZE + CRC_SIZE
MAX_CHANNELS = 64
MAX_SAMPLES_PER_FRAME = 4096
FULL_SCALE = 32768
SEQ_MODULUS = 1 << 16

#: Flag bit 0: the device lost samples before this frame (ADC/DMA overrun).
#: The sequence counter does not show such losses; only the device knows.
FLAG_OVERRUN = 0x01

# sync(2s) version(B) flags(B) seq(H) n(H) channels(B) check(B)
_HEADER = struct.Struct("<2sBBHHBB")
_CRC = struct.Struct("<I")
_SYNC0 = SYNC[0]


def _header_check(version: int, flags: int, seq: int, n: int, channels: int) -> int:
    """XOR of header bytes 2..8, inverted (so an all-zero header fails)."""
    return (0xFF ^ version ^ flags ^ (seq & 0xFF) ^ (seq >> 8) ^ (n & 0xFF) ^ (n >> 8)
            ^ channels) & 0xFF


def frame_size(samples_per_frame: int, channels: int) -> int:
    """Bytes on the wire of one frame: ``14 + 2 * samples_per_frame * channels``."""
    return OVERHEAD + 2 * samples_per_frame * channels


@dataclass(frozen=True, eq=False)  # eq would compare arrays ambiguously
class Frame:
    """One decoded, CRC-checked frame.

    Attributes
    ----------
    seq : int
        Sequence counter, 0..65535.
    flags : int
        Flag byte; see :data:`FLAG_OVERRUN`.
    samples : ndarray of int16, shape (samples_per_frame, channels)
        The payload, read-only, native int16 values (full scale 32768).
    """

    seq: int
    flags: int
    samples: np.ndarray

    @property
    def channels(self) -> int:
        """Channels per sample (columns of ``samples``)."""
        return int(self.samples.shape[1])

    @property
    def samples_per_frame(self) -> int:
        """Samples in the frame (rows of ``samples``)."""
        return int(self.samples.shape[0])


def encode_frame(seq: int, samples: np.ndarray, flags: int = 0) -> bytes:
    """Encode one frame.

    Parameters
    ----------
    seq : int
        Sequence counter; taken modulo 65536, so a running count may be passed.
    samples : ndarray of int16, shape (n, channels)
        ``1 <= n <= 4096``, ``1 <= channels <= 64``. Quantise floats first
        (``round(x * 32768)`` clipped to int16).
    flags : int, default 0
        Flag byte, 0..255.

    Returns
    -------
    bytes
        ``14 + 2 * n * channels`` bytes.

    Raises
    ------
    TypeError
        If ``samples`` is not int16.
    ValueError
        If its shape is out of bounds or ``flags`` is not a byte.
    """
    samples = np.asarray(samples)
    if samples.dtype != np.int16:
        raise InputError(f"samples must be int16, got {samples.dtype}: quantise first")
    if samples.ndim != 2:
        raise InputError(f"samples must have shape (n, channels), got {samples.shape}")
    n, channels = samples.shape
    if not 1 <= n <= MAX_SAMPLES_PER_FRAME:
        raise InputError(f"samples per frame must be 1..{MAX_SAMPLES_PER_FRAME}, got {n}")
    if not 1 <= channels <= MAX_CHANNELS:
        raise InputError(f"channel count must be 1..{MAX_CHANNELS}, got {channels}")
    if not 0 <= flags <= 0xFF:
        raise InputError(f"flags must be 0..255, got {flags}")
    seq &= 0xFFFF
    head = _HEADER.pack(SYNC, VERSION, flags, seq, n, channels,
                        _header_check(VERSION, flags, seq, n, channels))
    body = head + samples.astype("<i2", copy=False).tobytes(order="C")
    return body + _CRC.pack(zlib.crc32(body))


class FrameDecoder:
    """Streaming decoder: bytes in, CRC-checked :class:`Frame` objects out.

    :meth:`feed` never raises on any input and never returns a frame whose CRC
    does not match. Resynchronisation rules:

    * Bytes before a sync word are skipped (counted in ``bytes_skipped``).
    * A sync word whose header fails (version, bounds, check byte) counts in
      ``header_errors``; the search resumes one byte after that sync.
    * A complete candidate whose CRC fails counts in ``crc_errors`` or
      ``truncated``; the search resumes one byte after its sync, so a valid
      frame that began inside the bad one (bytes were lost) is still found.
    * An incomplete candidate is kept until enough bytes arrive; a candidate
      whose CRC failed is judged once 9 more bytes have arrived (see
      ``truncated``).

    Attributes
    ----------
    frames_ok : int
        Frames returned.
    crc_errors : int
        Candidates with a good header and a bad CRC, and no frame header
        inside their span: bytes were altered (line noise, bit errors).
    truncated : int
        Candidates with a bad CRC and another valid frame header inside their
        span: bytes were lost, the next frame began early (UART or USB
        overrun). A heuristic: lost bytes replaced by as many or more
        unrelated bytes look like ``crc_errors``.
    header_errors : int
        Sync words whose header failed the checks: mostly the sync pattern
        occurring by chance in skipped bytes, or a damaged header.
    version_errors : int
        Of those, headers valid but for their version (check byte and bounds
        right): frames of another firmware version, or, rarely, chance.
    bytes_skipped : int
        Bytes not part of any returned frame (garbage, damaged frames,
        discarded by :meth:`reset`). Invariant:
        ``bytes_fed == bytes_in_frames + bytes_skipped + buffered``.
    sequence_gaps : int
        Times the sequence counter jumped forward by 2..32768 (frames lost).
    frames_lost : int
        Frames missing according to the sequence counter, summed over gaps.
    sequence_resets : int
        Jumps backwards or forward by more than half the range: taken as a
        restart of the sender, not as losses.
    bytes_fed, bytes_in_frames : int
        Totals for the invariant above.

    Notes
    -----
    Sequence accounting here is link-level and knows no time: a gap longer
    than 32768 frames cannot be told from a restart. The serial driver keeps
    its own, time-checked account for gap filling.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._last_seq: int | None = None
        self.frames_ok = 0
        self.crc_errors = 0
        self.truncated = 0
        self.header_errors = 0
        self.version_errors = 0
        self.bytes_skipped = 0
        self.sequence_gaps = 0
        self.frames_lost = 0
        self.sequence_resets = 0
        self.bytes_fed = 0
        self.bytes_in_frames = 0

    @property
    def buffered(self) -> int:
        """Bytes held waiting for the rest of a frame."""
        return len(self._buf)

    def counters(self) -> dict[str, int]:
        """All counters as a new dict."""
        return {k: getattr(self, k) for k in (
            "frames_ok", "crc_errors", "truncated", "header_errors", "version_errors", "bytes_skipped",
            "sequence_gaps", "frames_lost", "sequence_resets", "bytes_fed",
            "bytes_in_frames")}

    def reset(self, *, keep_sequence: bool = False) -> None:
        """Drop buffered bytes (counted as skipped), e.g. after a reconnect.

        Parameters
        ----------
        keep_sequence : bool, default False
            Keep the last sequence number, so the next frame's gap is counted.
        """
        self.bytes_skipped += len(self._buf)
        self._buf = bytearray()
        if not keep_sequence:
            self._last_seq = None

    @staticmethod
    def _header(buf: bytearray, i: int) -> tuple[int, int, int, int] | None:
        """Parse and check the header at ``buf[i:i+10]``; None if it is invalid."""
        fields: tuple[int, ...] = _HEADER.unpack_from(buf, i)
        _, version, flags, seq, n, ch, check = fields
        if (version != VERSION or not 1 <= ch <= MAX_CHANNELS
                or not 1 <= n <= MAX_SAMPLES_PER_FRAME
                or check != _header_check(version, flags, seq, n, ch)):
            return None
        return flags, seq, n, ch

    @staticmethod
    def _header_fits_version(buf: bytearray, i: int) -> bool:
        """Tell whether the header at ``i`` is valid but for its version (a frame of another version)."""
        fields: tuple[int, ...] = _HEADER.unpack_from(buf, i)
        _, version, flags, seq, n, ch, check = fields
        return (1 <= ch <= MAX_CHANNELS and 1 <= n <= MAX_SAMPLES_PER_FRAME
                and check == _header_check(version, flags, seq, n, ch))

    def _frame_starts_within(self, buf: bytearray, lo: int, hi: int) -> bool:
        """Tell whether a valid frame header starts at an offset in ``[lo, hi)``.

        The caller makes sure ``buf`` holds ``hi + HEADER_SIZE - 1`` bytes.
        """
        i = buf.find(SYNC, lo, hi + 1)
        while i >= 0:
            if self._header(buf, i) is not None:
                return True
            i = buf.find(SYNC, i + 1, hi + 1)
        return False

    def feed(self, data: bytes) -> list[Frame]:
        """Add bytes; return the frames completed by them, in order.

        Parameters
        ----------
        data : bytes-like
            Any bytes, any length (including empty).

        Returns
        -------
        list of Frame

        Raises
        ------
        TypeError
            If ``data`` is not bytes-like (a programming error, not bad input).
        """
        view = memoryview(data).cast("B")
        try:
            return self._feed(view)
        except Exception:  # pragma: no cover - a bug; never let it kill a stream
            # Contract: never raise. Drop the buffer (counted) so a bug in one
            # spot cannot wedge the decoder, and carry on.
            self.reset(keep_sequence=True)
            return []

    def _feed(self, data: memoryview) -> list[Frame]:
        buf = self._buf
        self.bytes_fed += len(data)
        buf += data
        out: list[Frame] = []
        pos = 0
        end = len(buf)
        crc32 = zlib.crc32
        while True:
            i = buf.find(SYNC, pos)
            if i < 0:
                # Keep a trailing first sync byte: it may be half a sync word.
                keep = 1 if end > pos and buf[end - 1] == _SYNC0 else 0
                self.bytes_skipped += end - keep - pos
                pos = end - keep
                break
            self.bytes_skipped += i - pos
            pos = i
            if end - i < HEADER_SIZE:
                break
            head = self._header(buf, i)
            if head is None:
                self.header_errors += 1
                version = buf[i + 2]
                if version != VERSION and self._header_fits_version(buf, i):
                    self.version_errors += 1
                self.bytes_skipped += 1
                pos = i + 1
                continue
            flags, seq, n, ch = head
            size = OVERHEAD + 2 * n * ch
            if end - i < size:
                break
            stop = i + size - CRC_SIZE
            (crc,) = _CRC.unpack_from(buf, stop)
            with memoryview(buf) as mv:
                good = crc32(mv[i:stop]) == crc
                # Copy the payload out (bytes: one copy, read-only array): the
                # buffer is compacted below.
                payload = bytes(mv[i + HEADER_SIZE:stop]) if good else b""
            if not good:
                if end < i + size + HEADER_SIZE - 1:
                    # To tell lost bytes from altered ones, look for a frame
                    # header starting inside this one: wait until any such
                    # header is complete. The next frame brings these bytes.
                    break
                if self._frame_starts_within(buf, i + 1, i + size):
                    self.truncated += 1
                else:
                    self.crc_errors += 1
                self.bytes_skipped += 1
                pos = i + 1
                continue
            samples = np.frombuffer(payload, dtype="<i2").reshape(n, ch)
            out.append(Frame(seq, flags, samples))
            self.frames_ok += 1
            self.bytes_in_frames += size
            self._count_sequence(seq)
            pos = i + size
        if pos:
            del buf[:pos]
        return out

    def _count_sequence(self, seq: int) -> None:
        last = self._last_seq
        self._last_seq = seq
        if last is None:
            return
        gap = (seq - last - 1) & 0xFFFF
        if gap == 0:
            return
        if gap < SEQ_MODULUS // 2:
            self.sequence_gaps += 1
            self.frames_lost += gap
        else:
            self.sequence_resets += 1
