"""A small XDF 1.0 writer for tests, written from the specification
(https://github.com/sccn/xdf/wiki/Specifications), independent of the reader under test (pyxdf).

File: the magic ``XDF:``, then chunks. A chunk: NumLengthBytes (uint8: 1, 4 or 8), Length (that
many bytes, little-endian: the bytes of tag and content), Tag (uint16), Content. Tags: 1
FileHeader (XML), 2 StreamHeader (StreamId uint32 + XML), 3 Samples (StreamId, NumSampleBytes +
NumSamples, then per sample TimeStampBytes (0 or 8) [+ double] + the values), 4 ClockOffset
(StreamId, CollectionTime double, OffsetValue double), 5 Boundary (16 bytes), 6 StreamFooter
(StreamId + XML).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

_FORMATS = {"float32": "<f4", "double64": "<f8", "int16": "<i2", "int32": "<i4"}
_BOUNDARY = bytes.fromhex("43a5461dd4e84e93817e9d0d86a1b4e2")


def _varlen(n: int) -> bytes:
    if n < 256:
        return struct.pack("<BB", 1, n)
    if n < 2 ** 32:
        return struct.pack("<BI", 4, n)
    return struct.pack("<BQ", 8, n)


def _chunk(tag: int, content: bytes) -> bytes:
    return _varlen(len(content) + 2) + struct.pack("<H", tag) + content


@dataclass
class XdfStream:
    """One stream to write: samples (n, channels), one timestamp per sample (seconds, the sender's
    clock), and the clock offsets (collection time, offset) the recorder measured for it. With
    ``fmt = "string"`` (a marker stream) the samples are a list of rows of strings."""

    name: str
    type: str
    rate: float
    samples: np.ndarray
    stamps: np.ndarray
    fmt: str = "float32"
    source_id: str = ""
    offsets: list[tuple[float, float]] = field(default_factory=list)
    chunk: int = 100                    # samples per Samples chunk


def write_xdf(path, streams: list[XdfStream]) -> None:
    """Write ``streams`` as LabRecorder does: headers, then the streams' chunks interleaved in
    time, a boundary now and then, the clock offsets, and the footers."""
    out = [b"XDF:", _chunk(1, b'<?xml version="1.0"?><info><version>1.0</version></info>')]
    for sid, s in enumerate(streams, start=1):
        xml = (f'<?xml version="1.0"?><info><name>{s.name}</name><type>{s.type}</type>'
               f"<channel_count>{len(s.samples[0])}</channel_count><nominal_srate>{s.rate!r}</nominal_srate>"
               f"<channel_format>{s.fmt}</channel_format><source_id>{s.source_id}</source_id>"
               f"<created_at>{float(s.stamps[0]) - 1.0!r}</created_at><desc></desc></info>")
        out.append(_chunk(2, struct.pack("<I", sid) + xml.encode()))
    pieces = []                          # (time, bytes) of every samples chunk, to interleave
    for sid, s in enumerate(streams, start=1):
        if s.fmt == "string":
            # A string value: its length (as a chunk's length is written), then its UTF-8 bytes.
            values = [b"".join(_varlen(len(v.encode())) + v.encode() for v in row) for row in s.samples]
        else:
            values = [row.tobytes() for row in np.ascontiguousarray(s.samples, dtype=_FORMATS[s.fmt])]
        for a in range(0, len(values), s.chunk):
            b = min(len(values), a + s.chunk)
            body = bytearray(struct.pack("<I", sid) + _varlen(b - a))
            for i in range(a, b):
                # Every sample stamped (TimeStampBytes 8): the reader must take them as they are.
                body += struct.pack("<Bd", 8, float(s.stamps[i])) + values[i]
            pieces.append((float(s.stamps[a]), _chunk(3, bytes(body))))
        for collected, offset in s.offsets:
            pieces.append((collected, _chunk(4, struct.pack("<Idd", sid, collected, offset))))
    for k, (_, piece) in enumerate(sorted(pieces, key=lambda p: p[0])):
        if k % 50 == 0:
            out.append(_chunk(5, _BOUNDARY))
        out.append(piece)
    for sid, s in enumerate(streams, start=1):
        xml = (f'<?xml version="1.0"?><info><first_timestamp>{float(s.stamps[0])!r}</first_timestamp>'
               f"<last_timestamp>{float(s.stamps[-1])!r}</last_timestamp><sample_count>{len(s.stamps)}</sample_count>"
               "</info>")
        out.append(_chunk(6, struct.pack("<I", sid) + xml.encode()))
    with open(path, "wb") as fh:
        fh.write(b"".join(out))
