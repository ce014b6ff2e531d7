"""object_features: the 2-D image of the held stick in one camera (ALGORITHMS.md §3.1).

Subscribes /cameras/<camera_name>/image_raw; publishes /cameras/<camera_name>/stick_2d
(artrack_msgs/Stick2D, found=false when there is none) for every image, which the
particle_tracker node uses with stick_source=detection2d (prior p_stick2d).
"""

from __future__ import annotations

import sys

from rclpy.node import Node

from artrack.config import config_path, load_dataclass_yaml
from artrack.messages import bgr_from_image_msg, header_msg, ns_from_time
from artrack.stick_detection import StickDetectorConfig, detect_stick

from .common import (
    IMAGE_QOS_RELIABLE,
    IMAGE_QOS_SENSOR,
    RESULT_QOS,
    camera_topic,
    declare_all,
    msgs,
    run_node,
)

PARAMS = [
    ("camera_name", "rgbd", "camera this node serves (topic /cameras/<camera_name>/...)"),
    ("lockstep", False, "reliable image QoS (bag replay)"),
    ("detector_config", "", "StickDetectorConfig YAML (empty: config/object_features.yaml)"),
]
LIMITS: dict[str, tuple] = {}
RUNTIME: tuple[str, ...] = ()  # all read-only once running


class ObjectFeaturesNode(Node):
    """The object_features node (module docstring): the held stick's 2-D image in one camera."""

    def __init__(self):
        super().__init__("object_features")
        p = declare_all(self, PARAMS, LIMITS, runtime={})
        self.camera = p["camera_name"]
        cfg = load_dataclass_yaml(config_path(p["detector_config"], "object_features.yaml"), StickDetectorConfig)
        cfg.hsv_lower, cfg.hsv_upper = tuple(cfg.hsv_lower), tuple(cfg.hsv_upper)
        self.config = cfg
        f = msgs()
        self.topic = camera_topic(self.camera, "image_raw")
        self.pub = self.create_publisher(f.cls("artrack_msgs/msg/Stick2D"), camera_topic(self.camera, "stick_2d"),
                                         RESULT_QOS)
        self.create_subscription(f.cls("sensor_msgs/msg/Image"), self.topic, self.on_image,
                                 IMAGE_QOS_RELIABLE if p["lockstep"] else IMAGE_QOS_SENSOR)

    def on_image(self, msg) -> None:
        try:
            image = bgr_from_image_msg(msg, self.topic)
        except ValueError as exc:
            self.get_logger().error(f"dropped bad image: {exc}")
            return
        det = detect_stick(image, self.config)
        f = msgs()
        out = f("artrack_msgs/msg/Stick2D", header=header_msg(f, ns_from_time(msg.header.stamp), msg.header.frame_id),
                camera_name=self.camera, found=det is not None)
        if det is not None:
            out.a = [float(x) for x in det.a_uv]
            out.b = [float(x) for x in det.b_uv]
            out.pixel_count = int(det.pixel_count)
        self.pub.publish(out)


def main(args=None) -> None:
    sys.exit(run_node(ObjectFeaturesNode, __doc__, PARAMS, args, LIMITS, RUNTIME))


if __name__ == "__main__":
    main()
