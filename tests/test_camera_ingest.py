"""camera_ingest (a real process over DDS): videos + calibration in, images and camera_info out at
the working resolution `scale` (intrinsics scaled with the images)."""

from __future__ import annotations

import subprocess
import time

import cv2
import numpy as np
import pytest
import rclpy
from conftest import NODE_BIN
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from artrack.cameras import Camera, save_rig_yaml
from artrack.messages import bgr_from_image_msg, rclpy_factory

pytestmark = pytest.mark.graph


def test_camera_ingest_downscales_images_and_intrinsics(env, tmp_path):
    from artrack_nodes.common import IMAGE_QOS_SENSOR, LATCHED_QOS

    K = np.array([[120.0, 0.0, 79.5], [0.0, 120.0, 59.5], [0.0, 0.0, 1.0]])
    cam = Camera("camq", 160, 120, K, np.array([0.01, 0.0, 0.0, 0.0, 0.0]), np.eye(3), np.array([0.0, 0.0, 3.0]))
    save_rig_yaml([cam], tmp_path / "rig.yaml")
    video = tmp_path / "camq.mp4"
    vw = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (160, 120))
    for i in range(90):
        img = np.full((120, 160, 3), 40, np.uint8)
        img[30:90, 60 + i % 20:100 + i % 20] = (20, 200, 240)
        vw.write(img)
    vw.release()

    context = Context()
    rclpy.init(context=context, domain_id=int(env["ROS_DOMAIN_ID"]))
    node = Node("ingest_probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    f = rclpy_factory()
    infos, images = [], []
    node.create_subscription(f.cls("sensor_msgs/msg/CameraInfo"), "/cameras/camq/camera_info", infos.append,
                             LATCHED_QOS)
    node.create_subscription(f.cls("sensor_msgs/msg/Image"), "/cameras/camq/image_raw", images.append,
                             IMAGE_QOS_SENSOR)
    log = tmp_path / "ingest.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen([str(NODE_BIN / "camera_ingest"), "--ros-args", "-p", f"videos:=['{video}']",
                                 "-p", f"calibration:={tmp_path / 'rig.yaml'}", "-p", "scale:=0.5",
                                 "-p", "rate:=0.1"], env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        # 90 frames at a tenth of 30 fps: 30 s of playback for the probe's discovery on a busy machine
        # (the node exits at the end of the video, and its latched camera_info with it)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (infos and len(images) >= 3) and proc.poll() is None:
            executor.spin_once(timeout_sec=0.05)
        assert infos and len(images) >= 3, f"no camera_info / images from camera_ingest:\n{log.read_text()}"
        info = infos[-1]
        want = cam.scaled(0.5)
        assert (info.width, info.height) == (80, 60)
        np.testing.assert_allclose(np.asarray(info.k).reshape(3, 3), want.K, atol=1e-12)
        np.testing.assert_allclose(info.d, cam.dist, atol=1e-15)
        img = bgr_from_image_msg(images[-1])
        assert img.shape == (60, 80, 3)
        assert img[30, 40, 2] > 150  # the bright bar, at its half-size place
        stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in images]
        assert all(round((b - a) * 30 / 1e9) >= 1 for a, b in zip(stamps, stamps[1:], strict=False))
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)


def test_rclpy_messages_take_image_and_cloud_bytes_whole():
    """The publishers' fast path (MsgFactory.bytes_field: rclpy takes an array('B') as it is, anything
    else element by element, ~37 ms per 272x480 image): the bytes arrive unchanged and in order, from
    a non-contiguous image too."""
    import array

    from artrack.messages import image_msg, pointcloud_msg, points_from_pointcloud_msg

    f = rclpy_factory()
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (7, 9, 3), np.uint8)
    for source in (img, img[:, ::-1]):  # the second is a strided view
        msg = image_msg(f, source, 5, "cam_optical_frame")
        assert isinstance(msg.data, array.array) and (msg.height, msg.width, msg.step) == (7, 9, 27)
        np.testing.assert_array_equal(bgr_from_image_msg(msg), source)
    pts = rng.normal(size=(11, 3)).astype(np.float32)
    cloud = pointcloud_msg(f, pts, 5, "rgbd_optical_frame")
    assert isinstance(cloud.data, array.array) and len(cloud.data) == 11 * 12
    np.testing.assert_array_equal(points_from_pointcloud_msg(cloud), pts.astype(float))
