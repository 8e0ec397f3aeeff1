"""A recording as a rosbag2 (MCAP): what ``supramodal record --bag`` writes beside the sessions.

It is for ``ros2 bag play``, Foxglove and ``rosbags``, and what ``import-recording --bag`` reads back.

Each recorded source becomes one stamped ``sensor_msgs/Image`` topic, ``/supramodal/SOURCE/samples``:
one message per block the node recorded (per 10 ms of samples for a session without its blocks),
``height`` samples by ``width`` channels, ``32FC1`` (``64FC1`` where a sample is no float32, never
rounded), ``header.stamp`` the block's last sample on the recording's time, ``header.frame_id`` the
source. A graph recording's sources are on the node's common time: each block's sample clock is the
lower envelope of its arrivals (the earliest-arriving block's offset, at the clock model's rate), so that
the stamps are the samples' times, not their delays. The labels go on ``/supramodal/labels``
(``std_msgs/String``): a message at each label's start, an empty one at its end (the form
``import-recording --label-topic`` reads). The node's decisions go on ``/supramodal/STREAM/decision``
(``std_msgs/String``, the ``ros2`` sink's form: the window's JSON line and its ``stamp``), stamped at
each window's end. The bag's time starts at :data:`BAG_EPOCH_NS` (a ROS time,
the same for every export: a bag is reproducible to the byte).

Filled frames travel as the zeros they are; their flags, and a board's restart marks, stay in the
sessions (a rosbag2 has no place for them).
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from supramodal.errors import InputError
from supramodal.replay.session import Session, load_session

__all__ = ["BAG_EPOCH_NS", "LABEL_TOPIC", "BagExportError", "check_bag_target", "decision_topic", "export_bag",
           "samples_topic"]

#: ROS time of the recording's time 0 in the bag, ns (2025-01-01T00:00:00Z).
BAG_EPOCH_NS = 1_735_689_600 * 10**9
#: The labels' topic.
LABEL_TOPIC = "/supramodal/labels"
#: Samples per message where a session does not keep its blocks: 10 ms of them.
BLOCK_SECONDS = 0.01


class BagExportError(InputError):
    """A recording that cannot be written as a bag; the message says why and what to do."""


def samples_topic(source: str) -> str:
    """Return the topic of a source's samples in an exported bag."""
    return f"/supramodal/{source}/samples"


def _clock(session: Session) -> tuple[float, float]:
    """``(offset, rate)``: sample ``i`` of ``session`` was taken at ``offset + i / rate`` on the recording's time.

    A graph recording's session keeps its blocks' arrivals on the node's common time: the line is their lower
    envelope at the clock model's rate (every block arrives at or after its last sample, the quickest closest
    to it). Without them, the session's own seconds.
    """
    if session.arrivals is None:
        return 0.0, float(session.rate)
    ends, arrived, rate = session.arrivals
    return float(np.min(np.asarray(arrived) - (np.asarray(ends) - 1) / rate)), float(rate)


def _block_ends(session: Session) -> np.ndarray:
    """Each block's end frame: the recorded blocks', else one per :data:`BLOCK_SECONDS`."""
    if session.arrivals is not None:
        return np.asarray(session.arrivals[0], dtype=np.int64)
    step = max(1, round(session.rate * BLOCK_SECONDS))
    return np.append(np.arange(step, session.frames, step), session.frames)


def decision_topic(stream: str) -> str:
    """Return the topic of a stream's decisions in an exported bag (the ``ros2`` sink's, under ``/supramodal``)."""
    return f"/supramodal/{stream}/decision"


def _decisions(path: Path, String: Any) -> list[tuple[int, str, Any, str]]:
    """Return the decision messages of the windows of a JSON Lines file the node wrote.

    The file is the node's own output: read line by line, each a JSON object; a line that is not one is refused.
    """
    import json

    out = []
    with path.open(encoding="utf-8") as f:
        for n, line in enumerate(f, 1):
            try:
                d = json.loads(line)
            except ValueError:
                raise BagExportError(f"{path}, line {n}: not JSON; the node's windows file is damaged") from None
            if not (isinstance(d, dict) and "window" in d and "predicted" in d):
                continue                    # an event, the summary, or a window without a model
            stamp = BAG_EPOCH_NS + round(float(d["end"]) * 1e9)
            d["stamp"] = {"sec": stamp // 10**9, "nanosec": stamp % 10**9}
            out.append((stamp, decision_topic(str(d["stream"])), String(data=json.dumps(d)), "std_msgs/msg/String"))
    return out


def check_bag_target(bag: str | Path, names: Sequence[str], overwrite: bool = False,
                     made: str | Path | None = None) -> Path:
    """Refuse, before anything is recorded, a bag :func:`export_bag` could not write.

    Refused: rosbags missing, ``bag`` there (and no rosbag2 folder, or ``overwrite`` False), no parent folder
    (but ``made``, a folder the recording makes), a source's or stream's name (``names``) that is no ROS name
    token. Returns ``bag`` as a Path.
    """
    from supramodal.drivers.ros2 import check_token
    from supramodal.replay.rosbag import INSTALL_HINT

    try:
        import rosbags.rosbag2  # noqa: F401
    except ImportError:
        raise BagExportError(f"writing a rosbag2 needs rosbags, which is not installed: {INSTALL_HINT}") from None
    bag = Path(bag)
    if bag.suffix == ".bag":
        raise BagExportError(f"{bag}: a folder named *.bag is taken for a ROS 1 bag by bag readers (rosbags); name the "
                             f"rosbag2 folder without .bag, e.g. {bag.with_suffix('')}")
    if bag.exists():
        if not overwrite:
            raise BagExportError(f"{bag} exists; choose another --bag, or pass --force to replace it")
        if not (bag.is_dir() and (bag / "metadata.yaml").is_file()):
            raise BagExportError(f"{bag} exists and is no rosbag2 folder (no metadata.yaml): it is left as it is; "
                                 "choose another --bag")
    if not bag.parent.is_dir() and (made is None or bag.parent.resolve() != Path(made).resolve()):
        raise BagExportError(f"{bag.parent}: no such folder for the bag; make it first (mkdir -p {bag.parent})")
    bad = [name for name in names if not check_token(name)]
    if bad:
        raise BagExportError(f"{bad}: a bag's topics name the sources and streams, which must then be ROS name "
                             "tokens (letters, digits and _, no __); rename them in the scene")
    return bag


def export_bag(sessions: Sequence[tuple[str, str | Path]], bag: str | Path, overwrite: bool = False,
               windows: str | Path | None = None) -> dict[str, Any]:
    """Write ``sessions`` (``(source name, session WAV path)``) as a rosbag2 MCAP folder at ``bag``.

    Parameters
    ----------
    sessions : sequence of (str, path-like)
        Each source's name (a ROS name token) and its recorded session.
    bag : path-like
        The bag's folder, made here (its parent must exist).
    overwrite : bool, default False
        Replace a bag already there (only a rosbag2 folder: anything else is refused).
    windows : path-like, optional
        The JSON Lines the recording node wrote (its ``jsonl`` sink): each window with a decision becomes a
        message of ``/supramodal/STREAM/decision`` (``std_msgs/String``: the line and its ``stamp``, as the
        ``ros2`` sink publishes it), stamped at the window's end on the recording's time.

    Returns
    -------
    dict
        ``{"bag": path, "topics": {topic: messages}}``.

    Raises
    ------
    BagExportError
        ``bag`` exists (and is no bag, or ``overwrite`` is False), its parent is missing, a source
        name is no ROS name, or rosbags is not installed.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    bag = check_bag_target(bag, [name for name, _ in sessions], overwrite)
    loaded = [(name, load_session(path)) for name, path in sessions]
    ts = get_typestore(Stores.ROS2_KILTED)
    t = ts.types
    Image, Header, Time, String = (t["sensor_msgs/msg/Image"], t["std_msgs/msg/Header"],
                                   t["builtin_interfaces/msg/Time"], t["std_msgs/msg/String"])
    messages: list[tuple[int, str, Any, str]] = []    # (log time, topic, message, type)
    labels: list[tuple[float, str]] = []           # (time, label; "" ends one)
    for name, session in loaded:
        offset, rate = _clock(session)
        ends = _block_ends(session)
        data = session.data
        exact = np.array_equal(data.astype(np.float32).astype(np.float64), data)
        dtype, encoding = ("<f4", "32FC1") if exact else ("<f8", "64FC1")
        start = 0
        for end in ends.tolist():
            block = np.ascontiguousarray(data[start:end], dtype=dtype)
            stamp = BAG_EPOCH_NS + round((offset + (end - 1) / rate) * 1e9)
            msg = Image(header=Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=name),
                        height=block.shape[0], width=block.shape[1], encoding=encoding, is_bigendian=0,
                        step=block.itemsize * block.shape[1], data=np.frombuffer(block.tobytes(), np.uint8))
            messages.append((stamp, samples_topic(name), msg, "sensor_msgs/msg/Image"))
            start = end
        if session.labels and not labels:
            # The labels, of the first source that has them (a graph's sources carry the same ones, each on
            # its own samples): a session's seconds are its samples', put on the recording's time by its clock.
            per_second = session.rate / rate
            starts = {round(label.start, 9) for label in session.labels}
            for label in session.labels:
                labels.append((offset + label.start * per_second, label.label))
                if round(label.end, 9) not in starts:           # a label that runs into the next ends there
                    labels.append((offset + label.end * per_second, ""))
    for when, text in labels:
        messages.append((BAG_EPOCH_NS + round(when * 1e9), LABEL_TOPIC, String(data=text), "std_msgs/msg/String"))
    if windows is not None:
        messages += _decisions(Path(windows), String)
    messages.sort(key=lambda m: (m[0], m[1]))
    counts: dict[str, int] = {}
    with tempfile.TemporaryDirectory(dir=bag.parent, prefix=f".{bag.name}.") as tmp:
        written = Path(tmp) / "bag"
        with Writer(written, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            cons: dict[str, Any] = {}
            for logged, topic, msg, kind in messages:
                if topic not in cons:
                    cons[topic] = w.add_connection(topic, kind, typestore=ts)
                w.write(cons[topic], logged, ts.serialize_cdr(msg, kind))
                counts[topic] = counts.get(topic, 0) + 1
        if bag.exists():                    # a bag of ours (checked above), replaced only now
            shutil.rmtree(bag)
        written.rename(bag)
    return {"bag": str(bag), "topics": counts}
