"""A node that gets a bad message logs it and keeps running (real processes over real DDS).

The test process is itself an rclpy participant on the private domain of the
test run: it publishes malformed messages to a running node executable, then a
good one, and checks that the node logged the bad ones and answered the good one.
"""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import NODE_BIN, spin_until

from artrack.messages import image_msg, rclpy_factory

pytestmark = pytest.mark.graph


def test_blob_features_survives_bad_images_and_priors(env, probe, tmp_path):
    node, executor = probe
    f = rclpy_factory()
    from artrack_nodes.common import IMAGE_QOS_RELIABLE, RESULT_QOS

    log = tmp_path / "blob.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen([str(NODE_BIN / "blob_features"), "--ros-args", "-p", "camera_name:=camx",
                                 "-p", "lockstep:=false"], env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        got = []
        blob_sub = node.create_subscription(f.cls("artrack_msgs/msg/Blob2DArray"), "/cameras/camx/blobs",
                                            got.append, RESULT_QOS)
        img_pub = node.create_publisher(f.cls("sensor_msgs/msg/Image"), "/cameras/camx/image_raw",
                                        IMAGE_QOS_RELIABLE)
        prior_pub = node.create_publisher(f.cls("artrack_msgs/msg/BlobPrior2DArray"), "/cameras/camx/blob_priors",
                                          RESULT_QOS)
        assert spin_until(executor, lambda: (img_pub.get_subscription_count() > 0 and blob_sub.get_publisher_count()
                                              > 0 and prior_pub.get_subscription_count() > 0), 30), \
            f"node never matched the probe's topics:\n{log.read_text()}"

        def logged(fragment: str) -> bool:
            return fragment in log.read_text()

        good = np.full((60, 80, 3), 90, np.uint8)
        bad_encoding = image_msg(f, good, 1, "camx_optical_frame")
        bad_encoding.encoding = "yuv422_weird"
        short_data = image_msg(f, good, 2, "camx_optical_frame")
        short_data.height = 120  # data holds only 60 rows
        bad_prior = f("artrack_msgs/msg/BlobPrior2DArray", camera_name="camx", priors=[
            f("artrack_msgs/msg/BlobPrior2D", label="head", mean=[float("nan"), 1.0], covariance=[1.0, 0, 0, 1.0],
              confidence=1.0, visibility=0)])
        # One message at a time, each answered before the next (the node's image subscription is
        # best effort and free-running: a burst may legitimately lose frames).
        steps = [
            (img_pub, bad_encoding, lambda: logged("unsupported encoding")),
            (img_pub, short_data, lambda: logged("dropped bad image") and logged("height")),
            (prior_pub, bad_prior, lambda: logged("dropped bad prior message")),
            (img_pub, image_msg(f, good, 3, "camx_optical_frame"), lambda: len(got) >= 1),
            (img_pub, image_msg(f, np.full((30, 40, 3), 90, np.uint8), 4, "camx_optical_frame"),
             lambda: logged("earlier frames were")),  # the image size changed
            (img_pub, image_msg(f, good, 5, "camx_optical_frame"), lambda: len(got) >= 2),
        ]
        for i, (pub, msg, answered) in enumerate(steps):
            for _attempt in range(15):  # re-send what best-effort transport lost
                pub.publish(msg)
                if spin_until(executor, answered, 2.0):
                    break
            else:
                raise AssertionError(f"no answer to message {i}:\n{log.read_text()}")
        time.sleep(0.5)
        assert proc.poll() is None, f"node died:\n{log.read_text()}"
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    text = log.read_text()
    stamps = [m.header.stamp.nanosec for m in got]
    assert set(stamps) == {3, 5} and stamps == sorted(stamps), stamps  # a re-sent frame may answer twice
    assert "unsupported encoding 'yuv422_weird' (field 'encoding')" in text
    assert "fields 'height'/'step'" in text
    assert "priors[0] ('head') has a non-finite mean or covariance" in text
    assert "image is 40x30, earlier frames were 80x60" in text
    assert "Traceback" not in text


HANGING_NODE = """
import time
import artrack_nodes.common as common
from rclpy.node import Node

class Hangs(Node):
    def __init__(self):
        super().__init__("hangs")
        self.get_logger().info("up")

    def destroy_node(self):  # a participant that deadlocks on destruction
        time.sleep(1000)

common.TEARDOWN_TIMEOUT_S = 2.0
raise SystemExit(common.run_node(Hangs, "a node whose teardown hangs", []))
"""


def test_node_teardown_is_bounded_and_stacks_dump_on_sigusr1(env, tmp_path):
    """run_node (every node's main): SIGUSR1 dumps the Python stacks and the node keeps running;
    after SIGTERM a teardown that hangs is cut off after TEARDOWN_TIMEOUT_S with the stacks on
    stderr and exit code 1 instead of a node that never exits."""
    import signal

    script = tmp_path / "hangs.py"
    script.write_text(HANGING_NODE)
    log = tmp_path / "hangs.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen([sys.executable, str(script)], env=env, stdout=out,
                                stderr=subprocess.STDOUT)
    try:
        t0 = time.monotonic()
        while "up" not in log.read_text() and time.monotonic() - t0 < 60 and proc.poll() is None:
            time.sleep(0.2)
        assert "up" in log.read_text(), log.read_text()
        proc.send_signal(signal.SIGUSR1)
        t0 = time.monotonic()
        while "spin" not in log.read_text() and time.monotonic() - t0 < 30:
            time.sleep(0.2)
        assert proc.poll() is None and "in run_node" in log.read_text(), log.read_text()
        proc.terminate()
        code = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = log.read_text()
    assert code == 1, (code, text)
    assert "in destroy_node" in text, text


SILENT_SHUTDOWN_NODE = """
import threading, time
import artrack_nodes.common as common
from rclpy.node import Node

class ShutsDownSilently(Node):
    def __init__(self):
        super().__init__("silent")
        threading.Thread(target=self.later, daemon=True).start()

    def later(self):  # rclpy's signal path: the context goes down, no waiting executor is woken
        time.sleep(1.0)
        self.context._Context__context.shutdown()
        print("context down", flush=True)

raise SystemExit(common.run_node(ShutsDownSilently, "a node whose context is shut down silently", []))
"""


def test_spin_ends_when_the_context_is_shut_down_without_a_wake_up(env, tmp_path):
    """run_node's spin bounds every wait (common.SPIN_POLL_S): a context shut down while the
    executor waits, with nothing to wake it (the race in rclpy's SIGTERM handling that left an
    objects node in rcl_wait after SIGTERM), still ends the node with exit code 0. rclpy.spin
    waits forever here (checked: it returned only when a signal arrived, 60 s later)."""
    script = tmp_path / "silent.py"
    script.write_text(SILENT_SHUTDOWN_NODE)
    proc = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "context down" in proc.stdout, proc.stdout + proc.stderr
