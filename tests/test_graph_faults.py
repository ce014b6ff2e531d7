"""Faults at run time, real processes over DDS (issue items 5 and 6).

The test process plays a two-camera rig (latched camera_info/extrinsics) and per-camera blob
messages to a free-running `skeleton` executable and checks after each fault that the node is
alive and still publishing bodies: a camera that stops (the tracker goes on with the other and
says so) and comes back, late and out-of-order messages, bad messages (unknown camera, NaN
blob, NaN calibration), the node killed and restarted mid-run (it re-synchronises from the
latched calibration). A truncated bag is played by `bag_player` up to the damage, and not before
the nodes it waits for have said they are ready.
"""

from __future__ import annotations

import subprocess
import time

import numpy as np
import pytest
from conftest import NODE_BIN, spin_until

from artrack.messages import blob_array_msg, camera_info_msg, extrinsics_msg, ns_from_time, rclpy_factory
from artrack.synth import default_rig
from artrack.types import Blob2D

pytestmark = pytest.mark.graph
FRAME_NS = 100_000_000  # 10 Hz


def _start_skeleton(env, log_path):
    out = open(log_path, "ab")  # noqa: SIM115 - closed with the process
    return subprocess.Popen([str(NODE_BIN / "skeleton"), "--ros-args", "-p", "camera_names:=[camA, camB]",
                             "-p", "lockstep:=false", "-p", "sync_timeout_s:=0.15", "-p", "fps:=10.0"],
                            env=env, stdout=out, stderr=subprocess.STDOUT)


def test_skeleton_survives_camera_loss_late_bad_input_and_restart(env, probe, tmp_path):
    node, executor = probe
    f = rclpy_factory()
    from artrack_nodes.common import LATCHED_QOS, RESULT_QOS

    cams = {c.name: c for c in (c.__class__(**{**c.__dict__, "name": n}) for c, n in
                                zip(default_rig(2, 160, 120), ["camA", "camB"], strict=True))}
    info = {n: node.create_publisher(f.cls("sensor_msgs/msg/CameraInfo"), f"/cameras/{n}/camera_info", LATCHED_QOS)
            for n in cams}
    extr = {n: node.create_publisher(f.cls("geometry_msgs/msg/TransformStamped"), f"/cameras/{n}/extrinsics",
                                     LATCHED_QOS) for n in cams}
    blobs = {n: node.create_publisher(f.cls("artrack_msgs/msg/Blob2DArray"), f"/cameras/{n}/blobs", RESULT_QOS)
             for n in cams}
    bodies: list[int] = []
    node.create_subscription(f.cls("artrack_msgs/msg/TrackedBody"), "/artrack/body",
                             lambda m: bodies.append(ns_from_time(m.header.stamp)), RESULT_QOS)
    log = tmp_path / "skeleton.log"

    def logged(fragment: str) -> bool:
        return fragment in log.read_text(errors="replace")

    # NaN in the calibration first (dropped, one line), then the good one completes the rig
    bad_info = camera_info_msg(f, cams["camA"], 0)
    bad_info.k = [float("nan")] * 9
    info["camA"].publish(bad_info)
    info["camB"].publish(camera_info_msg(f, cams["camB"], 0))
    for n, cam in cams.items():
        extr[n].publish(extrinsics_msg(f, cam, 0))
    proc = _start_skeleton(env, log)
    try:
        assert spin_until(executor, lambda: logged("dropped bad calibration of camera 'camA'"), 30), log.read_text()
        info["camA"].publish(camera_info_msg(f, cams["camA"], 0))
        assert spin_until(executor, lambda: logged("camera rig complete"), 30), log.read_text()
        frame = [0]

        def play(names, n_frames: int) -> int:
            """Send n frames of (empty) blobs from ``names`` at 10 Hz; return the first stamp."""
            first = (frame[0] + 1) * FRAME_NS
            for _ in range(n_frames):
                frame[0] += 1
                for n in names:
                    blobs[n].publish(blob_array_msg(f, frame[0] * FRAME_NS, n, f"{n}_optical_frame", []))
                spin_until(executor, lambda: False, 0.1)
            return first

        def published_since(stamp: int) -> int:
            return sum(s >= stamp for s in bodies)

        s0 = play(["camA", "camB"], 5)
        assert spin_until(executor, lambda: published_since(s0) >= 4, 20), f"no bodies:\n{log.read_text()}"
        # camera B stops: bodies go on from camera A alone, and the node says so
        s1 = play(["camA"], 20)
        assert spin_until(executor, lambda: logged("camera camB silent"), 10), log.read_text()
        assert published_since(s1) >= 15, "the tracker must go on with the remaining camera"
        # camera B comes back
        s2 = play(["camA", "camB"], 15)
        assert spin_until(executor, lambda: logged("camera camB is back"), 10), log.read_text()
        assert published_since(s2) >= 10
        # late, out-of-order and bad messages: logged and dropped, one line each
        late = frame[0] - 3
        blobs["camA"].publish(blob_array_msg(f, late * FRAME_NS, "camA", "camA_optical_frame", []))
        # on camA's topic, naming a camera the node does not know
        blobs["camA"].publish(blob_array_msg(f, (frame[0] + 1) * FRAME_NS, "camZ", "camZ_optical_frame", []))
        nan_blob = Blob2D("head", np.array([np.nan, 1.0]), np.eye(2))
        blobs["camA"].publish(blob_array_msg(f, (frame[0] + 1) * FRAME_NS, "camA", "camA_optical_frame", [nan_blob]))
        for n in ("camA", "camB"):  # frame k+2 complete before k+1
            blobs[n].publish(blob_array_msg(f, (frame[0] + 2) * FRAME_NS, n, f"{n}_optical_frame", []))
        spin_until(executor, lambda: False, 0.5)
        for n in ("camA", "camB"):
            blobs[n].publish(blob_array_msg(f, (frame[0] + 1) * FRAME_NS, n, f"{n}_optical_frame", []))
        frame[0] += 2
        assert spin_until(executor, lambda: logged(f"dropped late blobs of camA for frame {late * FRAME_NS}")
                           and logged("dropped blobs of unknown camera 'camZ' (field camera_name)")
                           and logged("blobs[0].mean is not finite")
                           and logged(f"for frame {(frame[0] - 1) * FRAME_NS}"), 10), log.read_text()
        s3 = play(["camA", "camB"], 5)
        assert spin_until(executor, lambda: published_since(s3) >= 4, 10), "still publishing after bad input"
        # a frame older than a complete one is dropped (free-running keeps the newest), not estimated late
        k = frame[0]
        blobs["camA"].publish(blob_array_msg(f, (k + 1) * FRAME_NS, "camA", "camA_optical_frame", []))
        for n in ("camA", "camB"):
            blobs[n].publish(blob_array_msg(f, (k + 2) * FRAME_NS, n, f"{n}_optical_frame", []))
        frame[0] += 2
        assert spin_until(executor, lambda: (k + 2) * FRAME_NS in bodies, 10), log.read_text()
        spin_until(executor, lambda: False, 0.5)
        assert (k + 1) * FRAME_NS not in bodies, "an incomplete older frame was estimated after a newer one"
        assert proc.poll() is None, f"skeleton died:\n{log.read_text()}"
        # killed mid-run and restarted: re-synchronises from the latched calibration
        proc.kill()
        proc.wait(timeout=10)
        proc = _start_skeleton(env, log)
        assert spin_until(executor, lambda: log.read_text().count("camera rig complete") >= 2, 30), log.read_text()
        s4 = play(["camA", "camB"], 10)
        assert spin_until(executor, lambda: published_since(s4) >= 8, 20), \
            f"no bodies after the restart:\n{log.read_text()}"
        assert proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    assert "Traceback" not in log.read_text()


def _play_to_the_end(executor, cmd: list[str], env) -> tuple[int, str]:
    """Run a bag_player to its end while the probe's executor spins; (exit status, its output)."""
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        spin_until(executor, lambda: proc.poll() is not None, 120)
        output = proc.communicate(timeout=10)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, output


def test_bag_player_plays_a_truncated_bag_up_to_the_damage(env, probe, tmp_path, small_scene):
    from artrack.bags import open_bag

    node, executor = probe
    f = rclpy_factory()
    from artrack_nodes.common import IMAGE_QOS_RELIABLE

    data = small_scene.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    with open_bag(cut, allow_truncated=True) as reader:
        readable = sum(1 for _ in reader.messages(["/cameras/cam01/image_raw"]))
    assert 0 < readable < 75
    got: list[int] = []
    from artrack.messages import header_msg
    from artrack_nodes.common import RESULT_QOS

    body_pub = node.create_publisher(f.cls("artrack_msgs/msg/TrackedBody"), "/artrack/body", RESULT_QOS)

    def on_image(m) -> None:  # the probe closes the lockstep loop: a body for every frame
        got.append(ns_from_time(m.header.stamp))
        body_pub.publish(f("artrack_msgs/msg/TrackedBody", header=header_msg(f, got[-1], "world")))

    node.create_subscription(f.cls("sensor_msgs/msg/Image"), "/cameras/cam01/image_raw", on_image,
                             IMAGE_QOS_RELIABLE)
    base = [str(NODE_BIN / "bag_player"), "--ros-args", "-p", f"bag:={cut}", "-p", "lockstep:=true",
            "-p", "cameras:=[cam01]", "-p", "start_timeout_s:=20.0", "-p", "linger_s:=0.2"]
    refused = subprocess.run(base, env=env, capture_output=True, text=True, timeout=60)
    assert refused.returncode == 1 and "truncated" in refused.stderr and "Traceback" not in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1, refused.stderr
    returncode, output = _play_to_the_end(executor, [*base, "-p", "allow_truncated:=true"], env)
    assert returncode == 0, output
    assert "playing the frames before the damage" in output
    assert len(got) == len(set(got)) == readable, f"{len(set(got))} of the {readable} readable frames were played"


def test_free_running_bag_player_paces_every_frame_out_in_order(env, probe, small_scene):
    """Free-running (lockstep false): the player sends every frame at its stamp's time (rate 2: the
    75-frame scene in 1.25 s), woken by its pacer rather than polling; nobody answers with bodies."""
    node, executor = probe
    f = rclpy_factory()
    from artrack_nodes.common import IMAGE_QOS_SENSOR

    got: list[int] = []
    node.create_subscription(f.cls("sensor_msgs/msg/Image"), "/cameras/cam01/image_raw",
                             lambda m: got.append(ns_from_time(m.header.stamp)), IMAGE_QOS_SENSOR)
    returncode, output = _play_to_the_end(
        executor, [str(NODE_BIN / "bag_player"), "--ros-args", "-p", f"bag:={small_scene}", "-p", "lockstep:=false",
                   "-p", "rate:=2.0", "-p", "cameras:=[cam01]", "-p", "start_timeout_s:=20.0", "-p", "linger_s:=0.2"],
        env)
    assert returncode == 0, output
    assert "done: 75 frames" in output and "Traceback" not in output, output
    from artrack.bags import read_scene

    stamps = [s for s, _ in read_scene(small_scene).frames()]
    # best effort (sensor-data QoS): a frame may be lost, but none repeated, reordered or invented
    assert got == sorted(set(got)) and set(got) <= set(stamps)
    assert len(got) >= len(stamps) // 2, f"only {len(got)} of {len(stamps)} frames arrived"


def test_bag_player_waits_for_the_named_nodes_to_say_they_are_ready(env, probe, small_scene):
    """A node already in the ROS graph may still be loading its models before it creates its image
    readers (the loose_limbed node under a loaded machine missed the first 11 frames, and with them
    its empty-room background): the player waits for each node of ``wait_for_nodes`` to say it is
    ready on /artrack_nodes/ready (every artrack node does, once constructed), not for it to be
    present. The probe node, present from the start, says so only after 3 s: no frame goes out
    before, every frame after."""
    node, executor = probe
    f = rclpy_factory()
    from artrack_nodes.common import IMAGE_QOS_SENSOR, announce_ready

    got: list[float] = []
    node.create_subscription(f.cls("sensor_msgs/msg/Image"), "/cameras/cam01/image_raw",
                             lambda m: got.append(time.monotonic()), IMAGE_QOS_SENSOR)
    proc = subprocess.Popen([str(NODE_BIN / "bag_player"), "--ros-args", "-p", f"bag:={small_scene}",
                             "-p", "lockstep:=false", "-p", "rate:=4.0", "-p", "cameras:=[cam01]",
                             "-p", "start_timeout_s:=60.0", "-p", "linger_s:=0.2",
                             "-p", f"wait_for_nodes:=[{node.get_name()}]"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        spin_until(executor, lambda: proc.poll() is not None, 3.0)
        assert proc.poll() is None and not got, "the player must not play before the node said it is ready"
        announce_ready(node)
        said = time.monotonic()
        spin_until(executor, lambda: proc.poll() is not None, 60)
        output = proc.communicate(timeout=10)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0 and "done: 75 frames" in output, output
    assert "not ready" not in output, output
    assert got and min(got) >= said, "frames went out before the node said it is ready"


def test_lockstep_skeleton_goes_on_without_a_dead_camera(env, probe, tmp_path):
    """Lockstep waits for every camera of a frame, but not for ever (lockstep_timeout_s)."""
    node, executor = probe
    f = rclpy_factory()
    from artrack_nodes.common import LATCHED_QOS, RESULT_QOS

    cams = dict(zip(["camA", "camB"], default_rig(2, 160, 120), strict=True))
    pubs = []
    for n, cam in cams.items():
        cam.name = n
        for leaf, cls, msg in (("camera_info", "sensor_msgs/msg/CameraInfo", camera_info_msg(f, cam, 0)),
                               ("extrinsics", "geometry_msgs/msg/TransformStamped", extrinsics_msg(f, cam, 0))):
            pubs.append(node.create_publisher(f.cls(cls), f"/cameras/{n}/{leaf}", LATCHED_QOS))
            pubs[-1].publish(msg)
    blob_pub = node.create_publisher(f.cls("artrack_msgs/msg/Blob2DArray"), "/cameras/camA/blobs", RESULT_QOS)
    bodies: list[int] = []
    node.create_subscription(f.cls("artrack_msgs/msg/TrackedBody"), "/artrack/body",
                             lambda m: bodies.append(ns_from_time(m.header.stamp)), RESULT_QOS)
    log = tmp_path / "skeleton.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen([str(NODE_BIN / "skeleton"), "--ros-args", "-p", "camera_names:=[camA, camB]",
                                 "-p", "lockstep:=true", "-p", "lockstep_timeout_s:=1.0"], env=env, stdout=out,
                                stderr=subprocess.STDOUT)
    try:
        assert spin_until(executor, lambda: "camera rig complete" in log.read_text(), 30), log.read_text()
        for k in (1, 2):  # camB's node is dead: only camA reports
            blob_pub.publish(blob_array_msg(f, k * FRAME_NS, "camA", "camA_optical_frame", []))
            assert spin_until(executor, lambda k=k: k * FRAME_NS in bodies, 15), log.read_text()
        assert "no blobs from camB after" in log.read_text()
        assert proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_skeleton_reseeded_from_another_estimators_body(env, probe, tmp_path):
    """reseed_topic (ALGORITHMS.md §4: the loose-limbed body hands its pose to the skeleton): a
    TRACKING body arriving there starts the not-yet-started estimator at that pose; the bodies
    published afterwards are TRACKING there although no blob was ever seen."""
    node, executor = probe
    f = rclpy_factory()
    from artrack.body_model import load_body_model
    from artrack.messages import body_from_msg, body_msg
    from artrack.motion import pose_at
    from artrack.types import STATUS_TRACKING, BodyEstimate
    from artrack_nodes.common import LATCHED_QOS, RESULT_QOS

    body = load_body_model()
    cams = {c.name: c for c in (c.__class__(**{**c.__dict__, "name": n}) for c, n in
                                zip(default_rig(2, 160, 120), ["camA", "camB"], strict=True))}
    pubs = [(node.create_publisher(f.cls("sensor_msgs/msg/CameraInfo"), f"/cameras/{n}/camera_info", LATCHED_QOS),
             camera_info_msg(f, cam, 0)) for n, cam in cams.items()]
    pubs += [(node.create_publisher(f.cls("geometry_msgs/msg/TransformStamped"), f"/cameras/{n}/extrinsics",
                                    LATCHED_QOS), extrinsics_msg(f, cam, 0)) for n, cam in cams.items()]
    blobs = {n: node.create_publisher(f.cls("artrack_msgs/msg/Blob2DArray"), f"/cameras/{n}/blobs", RESULT_QOS)
             for n in cams}
    reseed = node.create_publisher(f.cls("artrack_msgs/msg/TrackedBody"), "/test/reseed", RESULT_QOS)
    got: list = []
    node.create_subscription(f.cls("artrack_msgs/msg/TrackedBody"), "/artrack/body",
                             lambda m: got.append(body_from_msg(m)), RESULT_QOS)
    for pub, msg in pubs:
        pub.publish(msg)
    log = tmp_path / "skeleton.log"
    proc = subprocess.Popen([str(NODE_BIN / "skeleton"), "--ros-args", "-p", "camera_names:=[camA, camB]",
                             "-p", "sync_timeout_s:=0.15", "-p", "fps:=10.0", "-p", "reseed_topic:=/test/reseed"],
                            env=env, stdout=open(log, "wb"), stderr=subprocess.STDOUT)  # noqa: SIM115
    try:
        assert spin_until(executor, lambda: "camera rig complete" in log.read_text(), 30), log.read_text()
        joints = body.joint_positions(pose_at("default", 0.0, body))
        seed = BodyEstimate(FRAME_NS, list(body.joint_names), joints, [], [], STATUS_TRACKING, 1.0)
        assert spin_until(executor, lambda: reseed.get_subscription_count() > 0, 20)
        reseed.publish(body_msg(f, seed, "world", 7))
        assert spin_until(executor, lambda: "estimator re-initialised from /test/reseed" in log.read_text(), 20), \
            log.read_text()
        for k in (2, 3, 4):
            for n in cams:
                blobs[n].publish(blob_array_msg(f, k * FRAME_NS, n, f"{n}_optical_frame", []))
            spin_until(executor, lambda: False, 0.1)
        assert spin_until(executor, lambda: len(got) >= 3, 20), log.read_text()
        assert all(b.status == STATUS_TRACKING for b in got)
        assert np.linalg.norm(got[0].joints - joints, axis=1).mean() < 0.05
        assert proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    assert "Traceback" not in log.read_text()
