"""What every test module that talks ROS 2 starts with: a skip without rclpy, a fixture that refuses to
run a test whose DDS traffic could leave this machine or reach a robot's domain (tests/harness/environment.py sets
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and a ``ROS_DOMAIN_ID`` of the run's own; this checks them
again before each test), and a plain rclpy subscriber, as a user would write one.

    from ros2_only import localhost_only, require_ros2  # noqa: F401  (the fixture applies itself)
    require_ros2()
"""

from __future__ import annotations

import os
import threading
import time
import uuid
from collections.abc import Callable
from typing import Any

import pytest

from supramodal.drivers.ros2 import Ros2Unavailable, import_rclpy


def require_ros2() -> None:
    """Skip the calling module where rclpy (and the stock messages) cannot be imported."""
    try:
        import_rclpy()
    except Ros2Unavailable as exc:
        pytest.skip(f"the ROS 2 tests need the ros2 extra (CI installs it): {exc}", allow_module_level=True)


@pytest.fixture(autouse=True)
def localhost_only():
    """A test that could discover or be discovered beyond this machine, or on a robot's domain, does not run;
    and none starts on a Fast DDS segment that a process killed earlier in the run left empty."""
    assert os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST", "tests/harness/environment.py keeps ROS 2 on localhost"
    assert os.environ.get("ROS_DOMAIN_ID") == os.environ.get("SUPRAMODAL_TEST_ROS_DOMAIN"), \
        "tests/harness/environment.py sets a ROS domain of the run's own"
    assert not os.environ.get("ROS_STATIC_PEERS")
    remove_stale_segments()


def remove_stale_segments() -> None:
    """Remove the Fast DDS port segments a killed process left empty (the suite kills publishers and nodes on
    purpose): every later participant would wait on them for ever (drivers/ros2.py
    ``stale_port_segments``; the node itself refuses to start on one, naming it)."""
    from supramodal.drivers.ros2 import stale_port_segments

    for path in stale_port_segments():
        path.unlink(missing_ok=True)


def unique_namespace() -> str:
    """A namespace no other test of the run (on any worker) uses."""
    return f"/t{uuid.uuid4().hex[:10]}"


class Subscriber:
    """A plain rclpy node with subscriptions, on a context of its own, spun on a thread: what a user's
    subscriber does, in the test's process.

    Each message is kept with the host's ``time.monotonic()`` when it came, per topic.
    """

    def __init__(self, name: str = "listener") -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        remove_stale_segments()          # a process killed since the test began may have left one
        self.context = rclpy.Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(f"{name}_{uuid.uuid4().hex[:6]}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.got: dict[str, list[tuple[float, Any]]] = {}
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def subscribe(self, topic: str, kind: Any, qos: Any = 10) -> None:
        def keep(msg: Any) -> None:
            with self._lock:
                self.got.setdefault(topic, []).append((time.monotonic(), msg))

        self.node.create_subscription(kind, topic, keep, qos)

    def messages(self, topic: str) -> list[Any]:
        with self._lock:
            return [m for _, m in self.got.get(topic, [])]

    def timed(self, topic: str) -> list[tuple[float, Any]]:
        with self._lock:
            return list(self.got.get(topic, []))

    def wait_for(self, done: Callable[[], bool], timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if done():
                return True
            time.sleep(0.02)
        return done()

    def publishes(self, namespace: str, topic: str) -> bool:
        """Whether a node in ``namespace`` publishes ``topic``, as this subscriber's side of the
        discovery sees it (the ros2 sink's publisher runs in a process of its own)."""
        return any(info.node_namespace == namespace for info in self.node.get_publishers_info_by_topic(topic))

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        self.context.try_shutdown()
        self._thread.join(2.0)
