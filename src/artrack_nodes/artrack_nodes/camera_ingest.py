"""camera_ingest: cameras into the graph from video files, a V4L2 device or a bag.

Publishes /cameras/<cam>/image_raw (sensor-data QoS), camera_info and
extrinsics (latched), paced at the recording's frame rate. Video sizes are
checked against the calibration; a mismatch is one clear error and exit 1.
"""

from __future__ import annotations

import sys

import cv2
from rclpy.node import Node

from artrack.bags import read_scene
from artrack.cameras import load_calibration
from artrack.errors import InputError
from artrack.video import open_videos

from .common import CameraPublishers, Pacer, declare_all, run_node

PARAMS = [
    ("videos", [""], "video files, one per camera, in the order of camera_names"),
    ("calibration", "", "calibration file (.yaml rig / camera_info, Calib.toml, .qca.txt)"),
    ("camera_names", [""], "names of the cameras in the calibration (empty: all, in file order)"),
    ("device", -1, "V4L2 device index to read instead of videos (single camera)"),
    ("bag", "", "play the cameras of this recording instead of videos"),
    ("scale", 1.0, "downscale factor to the working resolution (0 < scale <= 1)"),
    ("fps", 30.0, "frame rate used for a device (videos use their own)"),
    ("rate", 1.0, "playback speed factor"),
]


class CameraIngestNode(Node):
    """The camera_ingest node (module docstring): videos, a device or a bag into camera topics."""

    def __init__(self):
        super().__init__("camera_ingest")
        p = declare_all(self, PARAMS)
        self.rate = float(p["rate"])
        names = [n for n in p["camera_names"] if n]
        if p["bag"]:
            scene = read_scene(p["bag"])
            cameras = [c for c in scene.cameras if not names or c.name in names]
            self.frames = scene.frames()
        else:
            if not p["calibration"]:
                raise InputError("camera_ingest: parameter 'calibration' is empty")
            cameras = load_calibration(p["calibration"])
            if names:
                by_name = {c.name: c for c in cameras}
                missing = [n for n in names if n not in by_name]
                if missing:
                    raise InputError(f"{p['calibration']}: no camera named '{missing[0]}'")
                cameras = [by_name[n] for n in names]
            if int(p["device"]) >= 0:
                cameras = cameras[:1]
                self.frames = self._device_frames(int(p["device"]), cameras[0].name, float(p["fps"]))
            else:
                videos = [v for v in p["videos"] if v]
                video_set = open_videos(videos, cameras[: len(videos)], float(p["scale"]))
                cameras = list(video_set.cameras)  # scaled to the working resolution
                self.frames = ((stamp, images) for _, stamp, images in video_set)
        self.pubs = CameraPublishers(self, cameras, reliable_images=False)
        self.next = next(self.frames, None)
        self.pacer = Pacer(self, self.tick)  # woken when the next frame is due, not polled
        self.pacer.arm(0.0)

    @staticmethod
    def _device_frames(index: int, name: str, fps: float):
        cap = cv2.VideoCapture(index)
        if not cap.isOpened():
            raise InputError(f"camera_ingest: cannot open V4L2 device {index}")
        i = 0
        while True:
            ok, frame = cap.read()
            if not ok:
                return
            yield int(round(i * 1e9 / fps)), {name: frame}
            i += 1

    def tick(self) -> None:
        """Publish the next frame if it is due, then sleep (the pacer) until the one after is
        (one frame per call: the executor serves its other callbacks in between)."""
        if self.next is None:
            raise SystemExit(0)
        stamp, images = self.next
        if self.pacer.due_in(stamp, self.rate) <= 0:
            self.pubs.publish_images(stamp, images)
            self.next = next(self.frames, None)
            if self.next is None:
                raise SystemExit(0)
        self.pacer.arm(max(0.0, self.pacer.due_in(self.next[0], self.rate)))


def main(args=None) -> None:
    sys.exit(run_node(CameraIngestNode, __doc__, PARAMS, args))


if __name__ == "__main__":
    main()
