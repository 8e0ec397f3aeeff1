"""Bags as a robot's recorder writes them, made with rosbags alone (no ROS): a whisker array on a
stamped ``sensor_msgs/Image`` topic on its own sample clock, a microphone on a ``std_msgs/Int16MultiArray``
topic dated by the recorder's arrival times (late by a jittered delay), the textures on a ``std_msgs/String``
topic, each sense's textures in the same order and of the same lengths."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest


def require_rosbags() -> None:
    """Skip the calling module where rosbags cannot be imported."""
    pytest.importorskip("rosbags", reason="the rosbag2 tests need rosbags (the ros2 extra; CI installs it)")


def sense_signals(textures: int, seconds: float) -> dict[str, tuple[np.ndarray, int]]:
    """``{"whiskers": (samples x 20 at 5 kHz), "mic": (samples x 1 at 44.1 kHz)}``: the reference textures
    of each sense in turn, ``seconds`` each (the whisker array fanned out with a gain per whisker)."""
    from supramodal.textures import reference_texture_set

    out = {}
    for sense, kind, rate, channels in (("whiskers", "whisker", 5000, 20), ("mic", "cochlea", 44100, 1)):
        ts = reference_texture_set(kind)
        x = np.concatenate([ts.synthesize(k, duration=seconds) for k in range(textures)])
        gains = np.linspace(0.6, 1.0, channels)
        out[sense] = ((x[:, None] * gains[None, :] * 0.5).astype(np.float64), rate)
    return out


def write_bag(path: Path, textures: int = 4, seconds: float = 2.0, storage: str = "mcap", nan_at: int | None = None,
              seed: int = 0) -> dict[str, np.ndarray]:
    """A bag of two senses and their labels at ``path`` (MCAP or sqlite3); returns each sense's samples.

    The whiskers come in 10 ms Image messages stamped with their last sample's time on a clock that
    starts 1.234 s after the recorder's zero; the microphone in 441-sample messages dated by their
    arrival, 2 to 6 ms after their last sample; a label message at each texture's start. ``nan_at``:
    a whisker message holds a NaN (bad input)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from supramodal.textures import reference_texture_set

    ts = get_typestore(Stores.ROS2_KILTED)
    t = ts.types
    Image, Header, Time = t["sensor_msgs/msg/Image"], t["std_msgs/msg/Header"], t["builtin_interfaces/msg/Time"]
    I16, Layout, Dim = (t["std_msgs/msg/Int16MultiArray"], t["std_msgs/msg/MultiArrayLayout"],
                        t["std_msgs/msg/MultiArrayDimension"])
    String = t["std_msgs/msg/String"]
    signals = sense_signals(textures, seconds)
    rng = np.random.default_rng(seed)
    zero = 1_700_000_000 * 10**9                       # the recorder's clock, ns
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    messages = []                                      # (log time, topic, message)
    x, rate = signals["whiskers"]
    start = zero + 1_234_000_000
    for k, i in enumerate(range(0, x.shape[0], 50)):
        block = x[i:i + 50].astype("<f4")
        if nan_at is not None and k == nan_at:
            block[3, 4] = np.nan
        stamp = start + (i + block.shape[0] - 1) * 10**9 // rate
        msg = Image(header=Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="whisker_array"),
                    height=block.shape[0], width=block.shape[1], encoding="32FC1", is_bigendian=0,
                    step=4 * block.shape[1], data=np.frombuffer(block.tobytes(), np.uint8))
        messages.append((stamp + int(rng.uniform(1e6, 3e6)), "/whiskers", msg))
    m, mrate = signals["mic"]
    pcm = np.clip(np.round(m * 32768), -32768, 32767).astype(np.int16)
    for i in range(0, pcm.shape[0], 441):
        block = pcm[i:i + 441]
        last = zero + (i + block.shape[0] - 1) * 10**9 // mrate
        msg = I16(layout=Layout(dim=[Dim(label="samples", size=block.shape[0], stride=block.shape[0]),
                                     Dim(label="channels", size=1, stride=1)], data_offset=0),
                  data=block.ravel())
        messages.append((last + int(rng.uniform(2e6, 6e6)), "/mic", msg))
    names = reference_texture_set("whisker").names
    for k in range(textures):
        messages.append((zero + 1_234_000_000 + int(k * seconds * 1e9), "/texture", String(data=names[k])))
    messages.sort(key=lambda m: m[0])
    with Writer(path, version=9, storage_plugin=plugin) as w:
        types = {"/whiskers": Image, "/mic": I16, "/texture": String}
        cons = {topic: w.add_connection(topic, kind.__msgtype__, typestore=ts) for topic, kind in types.items()}
        for logged, topic, msg in messages:
            w.write(cons[topic], logged, ts.serialize_cdr(msg, types[topic].__msgtype__))
    return {"whiskers": x, "mic": pcm.astype(np.float64) / 32768}
