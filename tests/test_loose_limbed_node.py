"""The loose_limbed node as a real process over DDS (ALGORITHMS.md §4 in the graph).

The test process publishes a 2-camera rig, empty-room frames (the node's background seed),
then frames with a person; in mode=initialiser the node answers while the skeleton has not
reported a good body, stops while it reports TRACKING, and re-initialises after LOST.
"""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
from conftest import NODE_BIN, spin_until

from artrack.body_model import load_body_model
from artrack.messages import body_msg, image_msg, rclpy_factory
from artrack.motion import pose_at
from artrack.synth import Renderer, default_rig
from artrack.types import STATUS_INITIALIZING, STATUS_LOST, STATUS_TRACKING, BodyEstimate

pytestmark = pytest.mark.graph


def test_loose_limbed_node_initialises_and_reinitialises_on_lost(env, probe, tmp_path):
    node, executor = probe
    f = rclpy_factory()
    from artrack_nodes.common import BODY_TOPIC, IMAGE_QOS_RELIABLE, RESULT_QOS, CameraPublishers

    body = load_body_model()
    cams = default_rig(2, 320, 240)
    renderer = Renderer(body, cams, seed=3)
    empty = renderer.render(None, noise_sigma=2.0)
    person = renderer.render(pose_at("self_occlusion", 5.2, body), noise_sigma=2.0, frame_index=1)
    log = tmp_path / "loose_limbed.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen([str(NODE_BIN / "loose_limbed"), "--ros-args", "-p", "camera_names:=[cam01,cam02]",
                                 "-p", "reliable_images:=true", "-p", "init_iterations:=2", "-p", "particles:=20",
                                 "-p", "background_frames:=2", "-p", "background_stride:=1"],
                                env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        got = []
        sub = node.create_subscription(f.cls("artrack_msgs/msg/TrackedBody"), "/artrack/loose_limbed/body",
                                       got.append, RESULT_QOS)
        cam_pub = CameraPublishers(node, cams, reliable_images=True)
        skel_pub = node.create_publisher(f.cls("artrack_msgs/msg/TrackedBody"), BODY_TOPIC, RESULT_QOS)
        bad_pub = node.create_publisher(f.cls("sensor_msgs/msg/Image"), "/cameras/cam01/image_raw",
                                        IMAGE_QOS_RELIABLE)
        assert spin_until(executor, lambda: cam_pub.subscriber_count() > 0 and sub.get_publisher_count() > 0
                           and skel_pub.get_subscription_count() > 0, 60), log.read_text()
        cam_pub.publish_calibration(0)
        bad = image_msg(f, empty[0], 1, "cam01_optical_frame")
        bad.encoding = "yuv422_weird"
        bad_pub.publish(bad)
        assert spin_until(executor, lambda: "dropped bad image" in log.read_text(), 20), log.read_text()
        for k in range(2):
            cam_pub.publish_images(10 + k, {c.name: im for c, im in zip(cams, empty)})
            spin_until(executor, lambda: False, 0.3)
        cam_pub.publish_images(20, {c.name: im for c, im in zip(cams, person)})
        assert spin_until(executor, lambda: len(got) >= 1, 120), log.read_text()
        first = got[0]
        assert first.status == STATUS_INITIALIZING and len(first.joints) == 15 and first.header.frame_id == "world"
        assert all(np.isfinite([p.x, p.y, p.z]).all() for p in first.joints)

        def skeleton(status: int, stamp: int) -> None:
            est = BodyEstimate(stamp_ns=stamp, joint_names=list(body.joint_names), joints=np.zeros((15, 3)),
                               links=[], blobs=[], status=status)
            skel_pub.publish(body_msg(f, est))

        skeleton(STATUS_TRACKING, 20)  # the skeleton is fine: the initialiser stays quiet
        spin_until(executor, lambda: False, 1.0)
        cam_pub.publish_images(21, {c.name: im for c, im in zip(cams, person)})
        spin_until(executor, lambda: False, 3.0)
        assert len(got) == 1
        skeleton(STATUS_LOST, 21)  # lost: the next frame is found again from no prior pose
        assert spin_until(executor, lambda: "re-initialising" in log.read_text(), 20), log.read_text()
        cam_pub.publish_images(22, {c.name: im for c, im in zip(cams, person)})
        assert spin_until(executor, lambda: len(got) >= 2, 120), log.read_text()
        assert got[-1].status == STATUS_INITIALIZING and got[-1].header.stamp.nanosec == 22
        assert proc.poll() is None, log.read_text()
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    assert "Traceback" not in log.read_text()
