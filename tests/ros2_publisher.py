"""A robot's sensor driver on ROS 2, for the tests: a plain rclpy process that publishes a WAV file's
samples on a topic in real time, on a sample clock of its own, as a whisker array's ROS driver would.

    python tests/ros2_publisher.py TOPIC FILE.wav --kind image|float32|int16 [--t0-ns NS] [--block N]
        [--hold-at N] [--wait-subscriber S]

Sample ``i`` is due at ``t0 + i / rate`` (``--t0-ns``: ROS time of sample 0, default now + 0.5 s), so
that a publisher started again with the same ``t0`` goes on where its sample clock has got to: the
samples due while it was down are lost, as a restarted device's are. Each block of ``--block`` samples
is published once its last sample is due; the stamped kind (``image``, ``sensor_msgs/Image``, encoding
``32FC1``) carries that sample's time in ``header.stamp``. A block late (the process was stopped) goes
out at once, with the blocks after it: a backlog flushed.

Prints ``first I`` (the first sample it publishes), then ``held N`` and waits, publishing nothing,
once it has published the samples before ``--hold-at`` (a device that hangs, to be killed).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import rclpy
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Image
from std_msgs.msg import Float32MultiArray, Int16MultiArray, MultiArrayDimension

from supramodal.replay.wavio import read_wav


def message(kind: str, block: np.ndarray, stamp_ns: int):
    n, c = block.shape
    if kind == "image":
        msg = Image()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
        msg.height, msg.width, msg.encoding, msg.is_bigendian, msg.step = n, c, "32FC1", 0, 4 * c
        msg.data = block.astype("<f4").tobytes()
        return msg
    msg = Float32MultiArray() if kind == "float32" else Int16MultiArray()
    msg.layout.dim = [MultiArrayDimension(label="samples", size=n, stride=n * c),
                      MultiArrayDimension(label="channels", size=c, stride=c)]
    if kind == "float32":
        msg.data = block.astype(np.float32).ravel().tolist()
    else:
        msg.data = np.clip(np.round(block * 32768.0), -32768, 32767).astype(np.int16).ravel().tolist()
    return msg


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("topic")
    p.add_argument("wav")
    p.add_argument("--kind", choices=("image", "float32", "int16"), default="image")
    p.add_argument("--t0-ns", type=int, default=None)
    p.add_argument("--block", type=int, default=50)
    p.add_argument("--hold-at", type=int, default=None)
    p.add_argument("--wait-subscriber", type=float, default=60.0)
    args = p.parse_args()
    x, rate = read_wav(args.wav)
    x = np.asarray(x, dtype=np.float32)
    if x.ndim == 1:
        x = x[:, None]
    rclpy.init()
    node = rclpy.create_node("whisker_driver")
    kinds = {"image": Image, "float32": Float32MultiArray, "int16": Int16MultiArray}
    pub = node.create_publisher(kinds[args.kind], args.topic, QoSProfile(depth=1000))
    deadline = time.monotonic() + args.wait_subscriber
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.3)                                # the subscriber's side of the match
    now = node.get_clock().now().nanoseconds
    t0 = args.t0_ns if args.t0_ns is not None else now + 500_000_000
    # the first whole block not yet due: a restarted device takes up its sample clock where it is now
    first = max(0, -(-((now - t0) * rate // 10**9) // args.block) * args.block)
    print(f"first {first}", flush=True)
    i = first
    while i < x.shape[0]:
        if args.hold_at is not None and i >= args.hold_at:
            print(f"held {i}", flush=True)
            while True:
                time.sleep(1.0)
        n = min(args.block, x.shape[0] - i)
        due = t0 + (i + n - 1) * 10**9 // rate
        wait = (due - node.get_clock().now().nanoseconds) / 1e9
        if wait > 0:
            time.sleep(wait)
        pub.publish(message(args.kind, x[i:i + n], due))
        i += n
    print(f"done {i}", flush=True)
    time.sleep(1.0)                                # reliable delivery of the last blocks
    sys.exit(0)


if __name__ == "__main__":
    main()
