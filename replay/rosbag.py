"""A rosbag2 of a robot's sensor topics, read as recorded streams.

The bag is MCAP (the default since ROS 2 Iron) or sqlite3, or a ROS 1 bag too: what
``supramodal import-recording --bag`` turns into a replayable graph recording.

Read by ``rosbags`` (pure Python, in the ``ros2`` extra; no ROS installation needed). Each sensor topic
holds the messages the ``ros2`` driver reads (:data:`supramodal.drivers.ros2.MESSAGES`: a
``*MultiArray`` of samples x channels, or the stamped ``sensor_msgs/Image``), decoded by the same
function (:func:`~supramodal.drivers.ros2.samples_of`). A message's samples are dated as the driver
dates them: the stamped form by its ``header.stamp`` (its last sample's time on the publisher's sample
clock), the others by the time the bag received them; the samples before the last one period apart.
The streams are handed to the XDF reader's rules (:func:`supramodal.replay.xdf.xdf_session`: samples in
blocks of about 10 ms at their last sample's time, gaps the stamps show filled with zeros and marked), on
one time whose zero is the earliest sample of the topics read. A ``std_msgs/String`` topic may label
them: each message starts a label that runs to the next (an empty one ends it).

A bag is data: it is decoded, never executed; a damaged one (a truncated chunk), a missing topic, a
topic of another type, a message of another layout or non-finite samples are refused with a
:class:`~supramodal.replay.errors.ReplayError` naming the file, the topic and the fix.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from supramodal.drivers.ros2 import MESSAGES, samples_of
from supramodal.interrupts import held_interrupts
from supramodal.replay.errors import ReplayError

__all__ = ["INSTALL_HINT", "LABEL_TYPE", "bag_streams", "import_rosbags"]

INSTALL_HINT = 'install the optional extra: pip install "supramodal[ros2]" (rosbags, pure Python)'
#: The type of a topic of labels.
LABEL_TYPE = "std_msgs/msg/String"


def import_rosbags() -> ModuleType:
    """Return the ``rosbags.highlevel`` module, or raise a :class:`ReplayError` saying what to install."""
    try:
        with held_interrupts():
            import rosbags.highlevel as highlevel
    except ImportError:
        raise ReplayError(f"reading a rosbag2 needs rosbags, which is not installed: {INSTALL_HINT}") from None
    return highlevel


def _channels(kind: str, msg: Any) -> int:
    """Return the channels a message says it has.

    That is an image's width, a layout's second dimension, else 1 (a flat array of one channel).
    """
    if kind == "sensor_msgs/msg/Image":
        return int(msg.width)
    dims = msg.layout.dim
    return int(dims[1].size) if len(dims) == 2 else 1


def bag_streams(path: str | os.PathLike[str], topics: Mapping[str, float],
                labels: str | None = None) -> list[dict[str, Any]]:
    """Read the topics of a bag as streams in the XDF reader's form, for :func:`supramodal.replay.xdf.xdf_session`.

    Each stream is a dict of ``info``, ``time_series`` and ``time_stamps``, named by its topic.

    Parameters
    ----------
    path : path-like
        The bag: its folder (``metadata.yaml`` and the storage files) or one ``.mcap`` / ``.db3`` file.
    topics : mapping of str to float
        Each sensor topic to read, with its samples' rate, Hz.
    labels : str, optional
        A ``std_msgs/String`` topic whose messages label the streams (a marker stream, named by it).

    Returns
    -------
    list of dict
        One stream per topic of ``topics`` (``time_series`` float64 samples x channels at full scale
        +-1, ``time_stamps`` seconds from the earliest sample of them all), then the label stream.

    Raises
    ------
    ReplayError
        No such bag, a damaged one, a topic it lacks or of another type, messages of changing
        channels, no message, no rosbags.
    """
    highlevel = import_rosbags()
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    if not path.exists():
        raise ReplayError(f"{path}: no such bag (a rosbag2 folder, or its .mcap or .db3 file)")
    if path.is_dir() and path.suffix == ".bag":
        # rosbags takes a path named *.bag for ROS 1 (by its suffix): a rosbag2 folder so named is read
        # through its one storage file
        files = sorted(p for p in path.iterdir() if p.suffix in (".mcap", ".db3"))
        if len(files) != 1:
            raise ReplayError(f"{path}: a rosbag2 folder named *.bag with {len(files)} storage files; rename the "
                              "folder without .bag (bag readers take *.bag for a ROS 1 bag)")
        path = files[0]
    wanted = {**{t: "sensor" for t in topics}, **({labels: "labels"} if labels is not None else {})}
    parts: dict[str, list[tuple[int, Any]]] = {t: [] for t in wanted}
    channels: dict[str, int] = {}
    try:
        with highlevel.AnyReader([path], default_typestore=get_typestore(Stores.ROS2_KILTED)) as reader:
            have = {c.topic: c.msgtype for c in reader.connections}
            for topic, role in wanted.items():
                if topic not in have:
                    listed = ", ".join(f"{t} ({k})" for t, k in sorted(have.items())) or "no topic"
                    raise ReplayError(f"{path}: no topic {topic}; the bag has {listed}")
                ok = [LABEL_TYPE] if role == "labels" else sorted(MESSAGES)
                if have[topic] not in ok:
                    raise ReplayError(f"{path}: topic {topic} carries {have[topic]}; "
                                      + (f"labels are read from a {LABEL_TYPE} topic" if role == "labels" else
                                         f"the node reads {ok} (samples x channels)"))
            connections = [c for c in reader.connections if c.topic in wanted]
            for con, logged, raw in reader.messages(connections=connections):
                msg = reader.deserialize(raw, con.msgtype)
                if wanted[con.topic] == "labels":
                    parts[con.topic].append((int(logged), str(msg.data)))
                    continue
                c = channels.setdefault(con.topic, _channels(con.msgtype, msg))
                data, why = samples_of(con.msgtype, msg, c)
                if data is None:
                    raise ReplayError(f"{path}: topic {con.topic}, message {len(parts[con.topic])}: {why}; every "
                                      f"message of a topic holds samples x {c} channels")
                if con.msgtype == "sensor_msgs/msg/Image":
                    last = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
                else:
                    last = int(logged)
                parts[con.topic].append((last, data))
    except ReplayError:
        raise
    except Exception as exc:    # rosbags' own errors: a damaged file, a truncated chunk, not a bag
        raise ReplayError(f"{path}: not a readable rosbag2 ({type(exc).__name__}: {exc}); a damaged or truncated "
                          "bag, or not a bag at all") from None
    empty = [t for t in topics if not parts[t]]
    if empty:
        raise ReplayError(f"{path}: topics {empty} hold no message")
    zero = min(last - round((p[0][1].shape[0] - 1) * 1e9 / topics[t]) for t, p in parts.items() if t in topics
               for last, _ in p[:1])
    streams = []
    for topic, rate in topics.items():
        blocks = parts[topic]
        data = np.concatenate([d for _, d in blocks])
        stamps = np.concatenate([(last - zero) / 1e9 - np.arange(d.shape[0] - 1, -1, -1) / rate for last, d in blocks])
        streams.append({"info": {"name": [topic], "type": ["rosbag2"], "source_id": [""], "nominal_srate": [repr(rate)],
                                 "channel_count": [str(data.shape[1])], "channel_format": ["double64"]},
                        "time_series": data, "time_stamps": stamps})
    if labels is not None:
        marks = parts[labels]
        streams.append({"info": {"name": [labels], "type": ["Markers"], "source_id": [""], "nominal_srate": ["0"],
                                 "channel_count": ["1"], "channel_format": ["string"]},
                        "time_series": [[text] for _, text in marks],
                        "time_stamps": np.array([(t - zero) / 1e9 for t, _ in marks], dtype=np.float64)})
    return streams
