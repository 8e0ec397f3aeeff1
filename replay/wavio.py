"""WAV files to and from float64 arrays scaled to +-1 full scale.

Reading goes through :func:`scipy.io.wavfile.read`, but only after this module
has parsed the RIFF header itself: scipy returns 24-bit PCM as left-justified
int32 (read here, scaled exactly), 12-bit PCM as int8, and a file truncated on
a frame boundary as a shorter array with only a warning. The last two would be
*silently wrong* here, so the header is checked first and every file that is
not one of the supported layouts is refused with a :class:`WavFormatError`
that names the file, the problem and the fix.

Supported layouts
-----------------
=========  ==========  ==================  ==========================
format     bits        numpy dtype         scaling to float64
=========  ==========  ==================  ==========================
PCM        8           uint8               ``(x - 128) / 128``
PCM        16          int16               ``x / 32768``
PCM        24          int32 (left-        ``x / 2**31`` (= the 24-bit
                       justified by scipy) value ``/ 2**23``, exactly)
PCM        32          int32               ``x / 2**31``
IEEE float 32          float32             none
IEEE float 64          float64             none
=========  ==========  ==================  ==========================

``WAVE_FORMAT_EXTENSIBLE`` files are accepted when their sub-format is one of
the above. RIFX (big-endian) and RF64 (> 4 GiB) containers are refused.

Float samples
-------------
Float WAVs may hold values beyond +-1 (headroom), and those are read as they
are. A float file is refused if any sample is NaN or infinite, or if any
``|x|`` exceeds :data:`MAX_FLOAT_MAGNITUDE` (1e6 full scale, 120 dB above it):
no recording holds such values, and they mean a file written in other units
(or damaged); the message gives the peak found and the fix (rescale to +-1).

Threading: the functions keep no state and may be called from any thread.
"""

from __future__ import annotations

import os
import struct
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from scipy.io import wavfile

from supramodal.errors import InputError
from supramodal.replay.errors import ClippingWarning, ReplayError, WavFormatError

__all__ = ["WavInfo", "wav_info", "read_wav", "write_wav", "as_frames", "WRITE_DTYPES", "MAX_FLOAT_MAGNITUDE",
           "MAX_WAV_CHANNELS", "MAX_WAV_RATE"]

_PCM = 0x0001
_IEEE_FLOAT = 0x0003
_EXTENSIBLE = 0xFFFE

# (format tag, bits per sample) -> numpy dtype scipy returns for it.
_SUPPORTED: dict[tuple[int, int], np.dtype] = {
    (_PCM, 8): np.dtype(np.uint8),
    (_PCM, 16): np.dtype("<i2"),
    (_PCM, 24): np.dtype("<i4"),      # field recorders' usual format; scipy shifts it left by 8 bits
    (_PCM, 32): np.dtype("<i4"),
    (_IEEE_FLOAT, 32): np.dtype("<f4"),
    (_IEEE_FLOAT, 64): np.dtype("<f8"),
}

# Names of common non-PCM format tags, only so that refusals can say what the file is.
_TAG_NAMES = {
    0x0002: "Microsoft ADPCM",
    0x0006: "A-law",
    0x0007: "mu-law",
    0x0011: "IMA ADPCM",
    0x0031: "GSM 6.10",
    0x0050: "MPEG",
    0x0055: "MPEG layer 3 (MP3)",
    0x00FF: "AAC",
    0x1610: "HE-AAC",
    0xF1AC: "FLAC",
}

_CONVERT_HINT = ("convert it to 16-, 24- or 32-bit integer PCM or 32-bit float "
                 "(e.g. `sox IN -b 32 -e float OUT.wav`)")

#: Largest ``|sample|`` a float WAV may hold, in full scale (1.0): 1e6 is 120 dB above full
#: scale, beyond any recording, yet far below what the filterbank's state can hold.
MAX_FLOAT_MAGNITUDE = 1e6
#: Highest sample rate a WAV may declare here, Hz (the drivers' highest, ``MAX_RATE``): a header beyond it is
#: damaged or no sensor's, and a rate past 4.29e9 bytes a second cannot even be written back.
MAX_WAV_RATE = 1_000_000
#: Most channels a WAV holds (its header's field is 16 bits).
MAX_WAV_CHANNELS = 65535

#: dtypes :func:`write_wav` can write, by name.
WRITE_DTYPES = ("float32", "float64", "int16", "int32", "uint8")


@dataclass(frozen=True)
class WavInfo:
    """What a WAV file's header declares.

    Attributes
    ----------
    path : pathlib.Path
        The file.
    rate : int
        Frames per second, Hz (WAV headers store an integer).
    channels : int
        Channels per frame.
    frames : int
        Frames in the ``data`` chunk.
    format_tag : int
        1 for integer PCM, 3 for IEEE float (after resolving ``WAVE_FORMAT_EXTENSIBLE``).
    bits : int
        Bits per sample as stored (container size).
    dtype : numpy.dtype
        The type the samples are read as: the type on disk, except 24-bit PCM, read as
        int32 shifted left by 8 bits (as :func:`scipy.io.wavfile.read` returns it).
    """

    path: Path
    rate: int
    channels: int
    frames: int
    format_tag: int
    bits: int
    dtype: np.dtype

    @property
    def duration(self) -> float:
        """Length in seconds, ``frames / rate``."""
        return self.frames / self.rate


def _fail(path: Path, problem: str) -> WavFormatError:
    return WavFormatError(f"{path}: {problem}")


def wav_info(path: str | os.PathLike[str]) -> WavInfo:
    """Parse and check a WAV file's header without reading its samples.

    Parameters
    ----------
    path : str or path-like
        The WAV file.

    Returns
    -------
    WavInfo

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    WavFormatError
        If the file is not a RIFF/WAVE file, uses an unsupported sample
        format (24-bit PCM, compressed formats, ...), or is truncated or
        corrupt (missing chunks, a ``data`` chunk longer than the file, a
        ``data`` size that is not a whole number of frames).
    """
    path = Path(path)
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        head = f.read(12)
        if len(head) < 12:
            raise _fail(path, f"too short to be a WAV file ({size} bytes; a WAV header alone is 44)")
        riff, _, wave = struct.unpack("<4sI4s", head)
        if riff in (b"RIFX", b"RF64"):
            raise _fail(path, f"{riff.decode()} container is not supported (only little-endian RIFF); "
                              "re-save it as a standard WAV file")
        if riff != b"RIFF" or wave != b"WAVE":
            raise _fail(path, f"not a WAV file (starts with {head[:4]!r}...{head[8:12]!r}, "
                              "expected b'RIFF'...b'WAVE')")
        fmt: bytes | None = None
        data_size: int | None = None
        data_offset = 0                 # set with data_size
        pos = 12
        while pos + 8 <= size:
            f.seek(pos)
            chunk_id, chunk_size = struct.unpack("<4sI", f.read(8))
            if chunk_id == b"data":
                data_offset, data_size = pos + 8, chunk_size
                # Samples run to the chunk's end; nothing after it is needed, and
                # scipy only reads as far as the first data chunk too.
                break
            if pos + 8 + chunk_size > size:
                raise _fail(path, f"truncated or corrupt: chunk {chunk_id!r} at byte {pos} declares "
                                  f"{chunk_size} bytes but the file ends at byte {size}")
            if chunk_id == b"fmt ":
                if chunk_size < 16:
                    raise _fail(path, f"corrupt: 'fmt ' chunk is {chunk_size} bytes, at least 16 needed")
                fmt = f.read(chunk_size)
            pos += 8 + chunk_size + (chunk_size & 1)  # chunks are padded to even sizes
        if fmt is None:
            raise _fail(path, "corrupt or truncated: no 'fmt ' chunk before the 'data' chunk")
        if data_size is None:
            raise _fail(path, "truncated or corrupt: no 'data' chunk")

    tag, channels, rate, _byte_rate, block_align, bits = struct.unpack("<HHIIHH", fmt[:16])
    if tag == _EXTENSIBLE:
        if len(fmt) < 40:
            raise _fail(path, f"corrupt: WAVE_FORMAT_EXTENSIBLE 'fmt ' chunk is {len(fmt)} bytes, 40 needed")
        tag = struct.unpack("<H", fmt[24:26])[0]  # first two bytes of the sub-format GUID
    if channels < 1:
        raise _fail(path, "corrupt: header declares 0 channels")
    if rate < 1:
        raise _fail(path, "corrupt: header declares a sample rate of 0 Hz")
    if rate > MAX_WAV_RATE:
        raise _fail(path, f"header declares a sample rate of {rate} Hz, beyond the {MAX_WAV_RATE} Hz of any sensor "
                          "this reads (MAX_WAV_RATE): a damaged header, or resample the recording")
    if tag not in (_PCM, _IEEE_FLOAT):
        name = _TAG_NAMES.get(tag, "unknown")
        raise _fail(path, f"compressed or unknown sample format {name} (format tag 0x{tag:04x}) "
                          f"is not supported; {_CONVERT_HINT}")
    dtype = _SUPPORTED.get((tag, bits))
    if dtype is None:
        kind = "integer PCM" if tag == _PCM else "float"
        raise _fail(path, f"{bits}-bit {kind} samples are not supported; {_CONVERT_HINT}")
    if block_align != channels * bits // 8:
        raise _fail(path, f"corrupt: block align is {block_align} bytes, but {channels} channels of "
                          f"{bits}-bit samples need {channels * bits // 8}")
    available = size - data_offset
    if data_size > available:
        raise _fail(path, f"truncated: the 'data' chunk declares {data_size} bytes "
                          f"({data_size // block_align} frames) but the file holds {available} "
                          f"({available // block_align} frames); the recording was cut short")
    if data_size % block_align:
        raise _fail(path, f"corrupt: the 'data' chunk holds {data_size} bytes, not a whole number "
                          f"of {block_align}-byte frames")
    return WavInfo(path=path, rate=int(rate), channels=int(channels), frames=data_size // block_align,
                   format_tag=tag, bits=bits, dtype=dtype)


def read_wav(path: str | os.PathLike[str]) -> tuple[np.ndarray, int]:
    """Read a WAV file into float64 samples scaled to +-1 full scale.

    Parameters
    ----------
    path : str or path-like
        The WAV file: mono or multichannel, 8-bit unsigned, 16-, 24- or 32-bit
        integer PCM, or 32-bit or 64-bit float.

    Returns
    -------
    data : ndarray of float64, shape (frames, channels)
        Integer samples divided by their full scale (128, 32768, 2**23, 2**31;
        uint8 is offset by 128 first); float samples as stored. Mono files
        give shape ``(frames, 1)``.
    rate : int
        Frames per second, Hz.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    WavFormatError
        For unsupported formats, truncated or corrupt files (see
        :func:`wav_info`), and float files holding NaN, infinity or values
        beyond :data:`MAX_FLOAT_MAGNITUDE` full scale.
    """
    info = wav_info(path)
    try:
        with warnings.catch_warnings():
            # scipy only *warns* about some damage (premature EOF): make it fatal.
            warnings.simplefilter("error", wavfile.WavFileWarning)
            rate, raw = wavfile.read(info.path)
    except (ValueError, struct.error, wavfile.WavFileWarning) as e:
        raise _fail(info.path, f"unreadable: {e}") from e
    raw = raw.reshape(raw.shape[0], -1) if raw.ndim == 2 else raw.reshape(-1, 1)
    # Cross-check scipy against our own header parse: any disagreement means one
    # of us misread the file, and guessing which would be silently wrong.
    if raw.shape != (info.frames, info.channels) or raw.dtype.kind != info.dtype.kind \
            or raw.dtype.itemsize != info.dtype.itemsize or rate != info.rate:
        raise _fail(info.path, f"inconsistent: header declares {info.frames} frames x {info.channels} "
                               f"channels of {info.dtype} at {info.rate} Hz, scipy read {raw.shape} "
                               f"{raw.dtype} at {rate} Hz")
    kind = info.dtype
    if kind == np.uint8:
        data = (raw.astype(np.float64) - 128.0) / 128.0
    elif kind.kind == "i":
        data = raw.astype(np.float64) / float(2 ** (8 * kind.itemsize - 1))
    else:
        data = raw.astype(np.float64)
        bad = np.count_nonzero(~np.isfinite(data))
        if bad:
            raise _fail(info.path, f"{bad} samples are NaN or infinite; a recording never holds those")
        peak = float(np.max(np.abs(data))) if data.size else 0.0
        if peak > MAX_FLOAT_MAGNITUDE:
            over = np.count_nonzero(np.abs(data) > MAX_FLOAT_MAGNITUDE)
            raise _fail(info.path, f"{over} float samples exceed {MAX_FLOAT_MAGNITUDE:g} times full scale "
                                   f"(peak |x| = {peak:.6g}); a recording scaled to +-1 never holds those: "
                                   "rescale it to +-1 full scale (e.g. `sox IN OUT.wav gain -n`)")
    return data, info.rate


def as_frames(data: ArrayLike) -> np.ndarray:
    """Return samples as float64 frames, shape (frames, channels); a 1-D array is one channel.

    Raises
    ------
    ValueError
        For another number of dimensions, no channel, or samples that are not real numbers.
    """
    a = np.asarray(data)
    if a.ndim == 1:
        a = a.reshape(-1, 1)
    if a.ndim != 2 or a.shape[1] < 1:
        raise InputError(f"data must have shape (frames, channels), got {a.shape}")
    if a.dtype.kind not in "fiu" or a.dtype == bool:
        raise InputError(f"data must be real numbers scaled to +-1, got dtype {a.dtype}")
    return a.astype(np.float64, copy=False)


def write_wav(path: str | os.PathLike[str], data: ArrayLike, rate: int, dtype: str = "float32") -> int:
    """Write samples scaled to +-1 full scale to a WAV file.

    The file is written to a temporary name in the same directory and then
    renamed, so a reader never sees a half-written file.

    Parameters
    ----------
    path : str or path-like
        Destination; replaced if it exists.
    data : array_like of float, shape (frames, channels) or (frames,)
        Samples, full scale +-1.0. A 1-D array is one channel.
    rate : int
        Frames per second, Hz; a positive integer (WAV headers store integers).
    dtype : {'float32', 'float64', 'int16', 'int32', 'uint8'}, default 'float32'
        Sample type on disk. Float types keep values beyond +-1 as they are, up to
        :data:`MAX_FLOAT_MAGNITUDE`.
        Integer types round to the nearest step (``x * 32768`` for int16,
        ``x * 2**31`` for int32, ``x * 128 + 128`` for uint8) and clip what does
        not fit, so +1.0 itself is clipped by one step.

    Returns
    -------
    int
        Number of samples (not frames) clipped; always 0 for float types.
        When it is not 0 a :class:`ClippingWarning` is also issued.

    Raises
    ------
    ValueError
        For a bad shape, dtype or rate, or samples that are NaN or infinite
        (refused rather than written as garbage); for float types, samples
        beyond :data:`MAX_FLOAT_MAGNITUDE` (a :class:`ReplayError`: :func:`read_wav`
        would refuse the file).
    """
    if dtype not in WRITE_DTYPES:
        raise InputError(f"dtype must be one of {WRITE_DTYPES}, got {dtype!r}")
    if isinstance(rate, bool) or not float(rate).is_integer() or rate < 1:
        raise InputError(f"rate must be a positive whole number of Hz (WAV stores integers), got {rate!r}")
    rate = int(rate)
    if rate > MAX_WAV_RATE:
        raise InputError(f"{path}: a rate of {rate} Hz is beyond the {MAX_WAV_RATE} Hz a WAV may have here "
                         "(MAX_WAV_RATE); check the rate")
    x = as_frames(data)
    if x.shape[1] > MAX_WAV_CHANNELS:
        raise InputError(f"{path}: {x.shape[1]} channels; a WAV holds at most {MAX_WAV_CHANNELS} (its header's "
                         "field is 16 bits): check the stream's channel count")
    bad = np.count_nonzero(~np.isfinite(x))
    if bad:
        raise InputError(f"{path}: refusing to write {bad} NaN or infinite samples")
    clipped = 0
    lo: float
    hi: float
    if dtype in ("float32", "float64"):
        peak = float(np.max(np.abs(x))) if x.size else 0.0
        if peak > MAX_FLOAT_MAGNITUDE:
            # read_wav would refuse the file: refuse to write it.
            raise ReplayError(f"{path}: refusing to write samples beyond {MAX_FLOAT_MAGNITUDE:g} times full "
                              f"scale (peak |x| = {peak:.6g}); scale the data to +-1 full scale")
        out = x.astype(dtype)
    else:
        if dtype == "uint8":
            q, lo, hi = np.rint(x * 128.0) + 128.0, 0, 255
        else:
            full = float(2 ** (8 * np.dtype(dtype).itemsize - 1))
            q, lo, hi = np.rint(x * full), -full, full - 1
        over = (q < lo) | (q > hi)
        clipped = int(np.count_nonzero(over))
        out = np.clip(q, lo, hi).astype(dtype)
    # Mono as 1-D: identical file, and it keeps scipy's channel count obvious.
    out = out[:, 0] if out.shape[1] == 1 else out
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent or ".")
    try:
        with os.fdopen(fd, "wb") as f:
            wavfile.write(f, rate, out)
        os.chmod(tmp, 0o644)  # mkstemp makes it 0600; a recording is meant to be shared
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    if clipped:
        peak = float(np.max(np.abs(x)))
        warnings.warn(f"{path}: clipped {clipped} of {x.size} samples writing {dtype} "
                      f"(peak |x| = {peak:.6g}; full scale is 1.0)", ClippingWarning, stacklevel=2)
    return clipped
