"""Bags: rosbag2 mcap / sqlite3 and ROS 1 round trips, scene layout, truncation recovery."""

from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.typesys import Stores, get_typestore

from artrack.bags import (
    GROUND_TRUTH_TOPIC,
    BagWriter,
    find_msgs_dir,
    image_from_msg,
    open_bag,
    read_body_topic,
    read_scene,
    typestore,
    write_scene_bag,
)
from artrack.cameras import Camera
from artrack.errors import BagError, InputError
from artrack.messages import (
    blob_array_msg,
    blobs_from_msg,
    body_from_msg,
    body_msg,
    camera_info_msg,
    extrinsics_msg,
    header_msg,
    image_msg,
    rosbags_factory,
)
from artrack.types import Blob2D, Blob3D, BodyEstimate, LinkEstimate

REPO = Path(__file__).resolve().parents[1]
JOINTS = [f"j{i:02d}" for i in range(15)]
T0 = 1_700_000_000_000_000_000


def _cameras(w: int = 64, h: int = 48) -> list[Camera]:
    K = np.array([[1.2 * w, 0, (w - 1) / 2], [0, 1.2 * w, (h - 1) / 2], [0, 0, 1.0]])
    return [
        Camera.look_at("cam01", w, h, K, [3.0, 0.2, 1.5], [0, 0, 1.0]),
        Camera.look_at("cam02", w, h, K, [0.1, 3.0, 1.6], [0, 0, 1.0], dist=[0.02, -0.01, 0.001, 0.0, 0.0]),
    ]


def _frames(cameras, n: int = 3, seed: int = 0):
    rng = np.random.default_rng(seed)
    return [
        SimpleNamespace(
            stamp_ns=T0 + i * 33_333_333,
            images={c.name: rng.integers(0, 256, (c.height, c.width, 3), dtype=np.uint8) for c in cameras},
            joints=rng.normal(size=(15, 3)),
        )
        for i in range(n)
    ]


def _assert_same_camera(a: Camera, b: Camera) -> None:
    assert (a.name, a.width, a.height) == (b.name, b.width, b.height)
    np.testing.assert_allclose(a.K, b.K, atol=1e-12)
    np.testing.assert_allclose(a.dist, b.dist, atol=1e-12)
    np.testing.assert_allclose(a.R, b.R, atol=1e-12)
    np.testing.assert_allclose(a.t, b.t, atol=1e-12)


def _check_scene(path: Path, cameras, frames) -> None:
    scene = read_scene(path)
    assert scene.camera_names == ["cam01", "cam02"]
    assert scene.n_frames == len(frames)
    for a, b in zip(scene.cameras, cameras, strict=True):
        _assert_same_camera(a, b)
    got = list(scene.frames())
    assert [s for s, _ in got] == [f.stamp_ns for f in frames]
    for (_, images), f in zip(got, frames, strict=True):
        assert images.keys() == f.images.keys()
        for name in images:
            np.testing.assert_array_equal(images[name], f.images[name])
    truth = scene.truth
    assert truth.joint_names == JOINTS
    np.testing.assert_array_equal(truth.stamps, [f.stamp_ns for f in frames])
    np.testing.assert_array_equal(truth.joints, np.stack([f.joints for f in frames]))


# ------------------------------------------------------------------ typestore


def test_typestore_has_artrack_types(monkeypatch):
    store = typestore()
    assert typestore() is store  # cached
    for name in ("TrackedBody", "Blob2DArray", "BlobPrior2DArray", "LinkState", "EdgeMeasurementArray"):
        assert f"artrack_msgs/msg/{name}" in store.types
    assert "sensor_msgs/msg/CompressedImage" in store.types
    assert find_msgs_dir().samefile(REPO / "src" / "artrack_msgs" / "msg")
    installed = REPO / "ros2_ws" / "install" / "artrack_msgs" / "share" / "artrack_msgs" / "msg"
    if installed.is_dir():
        monkeypatch.setenv("ARTRACK_MSGS_DIR", str(installed))
        assert find_msgs_dir() == installed
    monkeypatch.setenv("ARTRACK_MSGS_DIR", str(REPO / "docs"))
    with pytest.raises(BagError, match="ARTRACK_MSGS_DIR"):
        find_msgs_dir()


# ------------------------------------------------------------------ scene bags


def test_scene_mcap_file_round_trip(tmp_path):
    cameras, frames = _cameras(), _frames(_cameras())
    out = tmp_path / "scene.mcap"
    assert write_scene_bag(out, cameras, frames, joint_names=JOINTS) == 3
    assert out.is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.mcap"]  # no temp or metadata left
    _check_scene(out, cameras, frames)

    # rosbags' own reader
    with AnyReader([out]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts["/cameras/cam01/image_raw"] == 3
        assert counts["/cameras/cam02/extrinsics"] == 1
        assert counts[GROUND_TRUTH_TOPIC] == 3
        conn = next(c for c in reader.connections if c.topic == GROUND_TRUTH_TOPIC)
        _, _, raw = next(reader.messages(connections=[conn]))
        msg = reader.deserialize(raw, conn.msgtype)
        assert list(msg.joint_names) == JOINTS

    # mcap's own reader: schemas, channels, counts, custom definition text
    with out.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert reader.get_header().profile == "ros2"
        topics = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
        assert len(topics) == 7
        assert topics["/cameras/cam01/image_raw"].name == "sensor_msgs/msg/Image"
        schema = topics[GROUND_TRUTH_TOPIC]
        assert (schema.name, schema.encoding) == ("artrack_msgs/msg/TrackedBody", "ros2msg")
        text = schema.data.decode()
        assert "string[] joint_names" in text and "geometry_msgs/Point[] joints" in text
        assert "MSG: artrack_msgs/LinkState" in text and "float64[36] covariance" in text
        assert summary.statistics.message_count == 2 * (3 + 3 + 1) + 3
        assert sum(1 for _ in reader.iter_messages()) == 17
        ext = next(c for c in summary.channels.values() if c.topic == "/cameras/cam01/extrinsics")
        assert "transient_local" in ext.metadata["offered_qos_profiles"]


def test_scene_directory_and_sqlite3(tmp_path):
    cameras, frames = _cameras(), _frames(_cameras(), seed=1)
    d = tmp_path / "scene"
    write_scene_bag(d, cameras, frames, joint_names=JOINTS)
    assert sorted(p.name for p in d.iterdir()) == ["metadata.yaml", "scene.mcap"]
    _check_scene(d, cameras, frames)
    _check_scene(d / "scene.mcap", cameras, frames)  # the storage file alone also reads

    s = tmp_path / "scene_sqlite"
    write_scene_bag(s, cameras, frames, joint_names=JOINTS, storage="sqlite3")
    assert sorted(p.name for p in s.iterdir()) == ["metadata.yaml", "scene_sqlite.db3"]
    _check_scene(s, cameras, frames)
    write_scene_bag(tmp_path / "one.db3", cameras, frames, joint_names=JOINTS)
    _check_scene(tmp_path / "one.db3", cameras, frames)


def test_compressed_images(tmp_path):
    cameras = _cameras()
    frames = _frames(cameras)
    write_scene_bag(tmp_path / "png.mcap", cameras, frames, joint_names=JOINTS, image_format="png")
    _check_scene(tmp_path / "png.mcap", cameras, frames)
    scene = read_scene(tmp_path / "png.mcap")
    assert scene.image_topics["cam01"] == "/cameras/cam01/image_raw/compressed"

    smooth = [
        SimpleNamespace(
            stamp_ns=f.stamp_ns,
            joints=f.joints,
            images={k: cv2.GaussianBlur(v, (9, 9), 3) for k, v in f.images.items()},
        )
        for f in frames
    ]
    write_scene_bag(tmp_path / "jpg.mcap", cameras, smooth, truth=False, image_format="jpeg")
    scene = read_scene(tmp_path / "jpg.mcap")
    assert scene.truth is None
    for (_, images), f in zip(scene.frames(), smooth, strict=True):
        assert np.abs(images["cam02"].astype(int) - f.images["cam02"]).mean() < 3.0


def test_image_encodings():
    store = typestore()
    f = rosbags_factory()
    rng = np.random.default_rng(3)
    bgr = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    Image = store.types["sensor_msgs/msg/Image"]

    def img(enc: str, arr: np.ndarray, step_pad: int = 0):
        h, w = arr.shape[:2]
        ch = arr.shape[2] if arr.ndim == 3 else 1
        rows = np.zeros((h, w * ch + step_pad), np.uint8)
        rows[:, : w * ch] = arr.reshape(h, -1)
        return Image(
            header=header_msg(f, 5, "x"),
            height=h,
            width=w,
            encoding=enc,
            is_bigendian=0,
            step=w * ch + step_pad,
            data=rows.reshape(-1),
        )

    np.testing.assert_array_equal(image_from_msg(img("bgr8", bgr, step_pad=3)), bgr)
    np.testing.assert_array_equal(image_from_msg(img("rgb8", bgr[..., ::-1])), bgr)
    bgra = np.dstack([bgr, np.full((5, 7), 255, np.uint8)])
    np.testing.assert_array_equal(image_from_msg(img("bgra8", bgra)), bgr)
    mono = bgr[..., 0]
    np.testing.assert_array_equal(image_from_msg(img("mono8", mono)), np.dstack([mono] * 3))
    with pytest.raises(BagError, match="encoding"):
        image_from_msg(img("yuv422", bgr), "cam.mcap: topic '/x'")
    bad = store.types["sensor_msgs/msg/CompressedImage"](
        header=header_msg(f, 5, "x"), format="jpeg", data=np.arange(20, dtype=np.uint8)
    )
    with pytest.raises(BagError, match="cannot decode compressed image"):
        image_from_msg(bad, "cam.mcap")


# ------------------------------------------------------------------ custom messages, raw, errors


def _body_msg(f, est: BodyEstimate):
    """TrackedBody with its LinkStates built straight from the typestore classes."""
    msg = body_msg(
        f, BodyEstimate(est.stamp_ns, est.joint_names, est.joints, [], est.blobs, quality=est.quality)
    )
    T = typestore().types
    for link in est.links:
        p, v, w = link.position, link.velocity, link.angular_velocity
        V3 = T["geometry_msgs/msg/Vector3"]
        msg.links.append(
            T["artrack_msgs/msg/LinkState"](
                name=link.name,
                pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                ),
                velocity=T["geometry_msgs/msg/Twist"](
                    linear=V3(x=v[0], y=v[1], z=v[2]), angular=V3(x=w[0], y=w[1], z=w[2])
                ),
                covariance=link.cov.reshape(-1),
            )
        )
    return msg


def test_custom_messages_and_write_raw(tmp_path):
    f = rosbags_factory()
    rng = np.random.default_rng(7)
    est = BodyEstimate(
        stamp_ns=T0 + 5,
        joint_names=JOINTS,
        joints=rng.normal(size=(15, 3)),
        links=[
            LinkEstimate(
                "pelvis",
                rng.normal(size=3),
                np.eye(3),
                rng.normal(size=3),
                rng.normal(size=3),
                np.diag(rng.uniform(1, 2, 6)),
            )
        ],
        blobs=[Blob3D("head", rng.normal(size=3), np.eye(3) * 0.01)],
        quality=0.75,
    )
    blobs = [Blob2D("head", np.array([3.0, 4.0]), np.array([[2.0, 0.1], [0.1, 3.0]]), pixel_count=12)]
    body = _body_msg(f, est)
    out = tmp_path / "run" / "track"
    with BagWriter(out) as bag:
        bag.add_topic("/artrack/body", "artrack_msgs/msg/TrackedBody")
        bag.add_topic("/artrack/body", "artrack_msgs/msg/TrackedBody")  # idempotent
        bag.write("/artrack/body", est.stamp_ns, body)
        # auto-registered from the message's own type
        bag.write(
            "/cameras/cam01/blobs", est.stamp_ns, blob_array_msg(f, est.stamp_ns, "cam01", "c", blobs, T0)
        )
        bag.add_topic("/raw", "artrack_msgs/msg/TrackedBody", qos="latched")
        raw = bytes(typestore().serialize_cdr(body, "artrack_msgs/msg/TrackedBody"))
        bag.write_raw("/raw", est.stamp_ns + 1, raw)
        with pytest.raises(BagError, match="'/nope' was not added"):
            bag.write_raw("/nope", 0, raw)
        with pytest.raises(BagError, match="already has type"):
            bag.add_topic("/raw", "sensor_msgs/msg/Image")
        with pytest.raises(BagError, match="unknown message type 'foo_msgs/msg/Bar'"):
            bag.add_topic("/foo", "foo_msgs/msg/Bar")
        assert bag.count == 3
    assert (out / "metadata.yaml").is_file()
    with open_bag(out) as reader:
        assert reader.topics()["/cameras/cam01/blobs"] == "artrack_msgs/msg/Blob2DArray"
        msgs = list(reader.messages())
        assert [t for t, _, _ in msgs] == ["/artrack/body", "/cameras/cam01/blobs", "/raw"]
        for _, _, m in (msgs[0], msgs[2]):
            back = body_from_msg(m)
            np.testing.assert_array_equal(back.joints, est.joints)
            np.testing.assert_array_equal(back.links[0].cov, est.links[0].cov)
            assert back.quality == 0.75 and back.blobs[0].label == "head"
        stamp, cam, got = blobs_from_msg(msgs[1][2])
        assert (stamp, cam, got[0].pixel_count) == (est.stamp_ns, "cam01", 12)
        assert list(reader.messages("/raw", raw=True))[0][2] == raw
        with pytest.raises(BagError, match=r"track: no topic '/artrack/missing'"):
            list(reader.messages(["/artrack/missing"]))
    track = read_body_topic(out, "/artrack/body")
    assert track.joint_names == JOINTS and track.joints.shape == (1, 15, 3)


def test_writer_leaves_nothing_on_error(tmp_path):
    f = rosbags_factory()
    cameras = _cameras()
    out = tmp_path / "scene.mcap"
    with pytest.raises(RuntimeError), BagWriter(out) as bag:
        bag.add_topic("/a", "sensor_msgs/msg/Image")
        bag.write("/a", 1, image_msg(f, np.zeros((4, 4, 3), np.uint8), 1, "x"))
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []

    # a failing scene write (bad image size) leaves an existing bag untouched
    frames = _frames(cameras)
    write_scene_bag(out, cameras, frames, joint_names=JOINTS)
    before = out.read_bytes()
    broken = _frames(cameras)
    broken[1].images["cam02"] = np.zeros((10, 10, 3), np.uint8)
    with pytest.raises(InputError, match=r"scene.mcap: frame 1 camera 'cam02'"):
        write_scene_bag(out, cameras, broken, joint_names=JOINTS)
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.mcap"]
    with pytest.raises(InputError, match="unknown camera 'cam09'"):
        write_scene_bag(
            out,
            cameras[:1],
            [SimpleNamespace(stamp_ns=1, images={"cam09": frames[0].images["cam01"]}, joints=None)],
            truth=False,
        )

    # replacing an existing bag directory works; a non-bag directory is refused
    d = tmp_path / "dir"
    write_scene_bag(d, cameras, frames, joint_names=JOINTS)
    write_scene_bag(d, cameras, frames[:2], joint_names=JOINTS)
    assert read_scene(d).n_frames == 2
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "notes.txt").write_text("keep me")
    with pytest.raises(BagError, match="not a rosbag2 directory"):
        write_scene_bag(tmp_path / "docs", cameras, frames, joint_names=JOINTS)
    assert (tmp_path / "docs" / "notes.txt").read_text() == "keep me"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_missing_topics_and_bad_files(tmp_path):
    f = rosbags_factory()
    out = tmp_path / "nocal.mcap"
    with BagWriter(out) as bag:
        bag.add_topic("/cameras/cam01/image_raw", "sensor_msgs/msg/Image")
        bag.write("/cameras/cam01/image_raw", 1, image_msg(f, np.zeros((4, 4, 3), np.uint8), 1, "x"))
    with pytest.raises(BagError, match=r"nocal.mcap: no topic '/cameras/cam01/camera_info'"):
        read_scene(out)
    cam = Camera("cam01", 4, 4, np.array([[4.0, 0, 1.5], [0, 4.0, 1.5], [0, 0, 1]]))
    scene = read_scene(out, cameras=[cam])  # external calibration
    assert [s for s, _ in scene.frames()] == [1]
    with pytest.raises(BagError, match=r"no topic '/cameras/cam02/image_raw' for camera 'cam02'"):
        read_scene(out, cameras=[Camera("cam02", 4, 4, cam.K)])
    with pytest.raises(BagError, match=r"nocal.mcap: no topic '/artrack/ground_truth'"):
        read_body_topic(out)
    with pytest.raises(BagError, match="no such bag"):
        open_bag(tmp_path / "missing.mcap")
    (tmp_path / "junk.mcap").write_bytes(b"this is not a bag at all" * 10)
    with pytest.raises(BagError, match=r"junk.mcap: not an MCAP file"):
        open_bag(tmp_path / "junk.mcap", allow_truncated=True)
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(BagError, match=r"empty.mcap: "):
        open_bag(tmp_path / "empty.mcap")
    (tmp_path / "x.txt").write_text("x")
    with pytest.raises(BagError, match="unknown bag format"):
        open_bag(tmp_path / "x.txt")
    (tmp_path / "emptydir").mkdir()
    with pytest.raises(BagError, match="not a bag directory"):
        open_bag(tmp_path / "emptydir")


def test_frames_grouping_out_of_order_and_missing(tmp_path):
    """Images grouped by header stamp; a camera missing a frame still yields the frame."""
    f = rosbags_factory()
    cameras = _cameras(8, 6)
    out = tmp_path / "g.mcap"
    rng = np.random.default_rng(5)
    imgs = {}
    # (log time, camera, header stamp): cam02 of stamp 200 arrives after cam01 of 300; cam01 misses 400
    order = [
        (1, "cam01", 100),
        (2, "cam02", 100),
        (3, "cam01", 200),
        (4, "cam01", 300),
        (5, "cam02", 200),
        (6, "cam02", 300),
        (7, "cam02", 400),
        (8, "cam01", 500),
        (9, "cam02", 500),
    ]
    with BagWriter(out) as bag:
        for c in cameras:
            bag.write(f"/cameras/{c.name}/extrinsics", 0, extrinsics_msg(f, c, 0))
            bag.write(f"/cameras/{c.name}/camera_info", 0, camera_info_msg(f, c, 0))
        for log, name, stamp in order:
            imgs[(name, stamp)] = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
            bag.write(f"/cameras/{name}/image_raw", log, image_msg(f, imgs[(name, stamp)], stamp, name))
    scene = read_scene(out)
    got = list(scene.frames())
    assert [(s, sorted(i)) for s, i in got] == [
        (100, ["cam01", "cam02"]),
        (200, ["cam01", "cam02"]),
        (300, ["cam01", "cam02"]),
        (400, ["cam02"]),
        (500, ["cam01", "cam02"]),
    ]
    for s, images in got:
        for name, im in images.items():
            np.testing.assert_array_equal(im, imgs[(name, s)])
    assert [s for s, _ in scene.frames(["cam02"])] == [100, 200, 300, 400, 500]


# ------------------------------------------------------------------ ROS 1


def test_ros1_bag(tmp_path):
    """A ROS 1 bag (ROS 1 serialisation, upper-case CameraInfo fields) reads like a rosbag2 one."""
    s1 = get_typestore(Stores.ROS1_NOETIC)
    T = s1.types
    cam = _cameras()[1]
    f2 = rosbags_factory()
    ext2 = extrinsics_msg(f2, cam, 0)
    rng = np.random.default_rng(2)
    imgs = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(3)]

    def header(i: int, frame: str):
        return T["std_msgs/msg/Header"](
            seq=i, stamp=T["builtin_interfaces/msg/Time"](sec=7, nanosec=i * 10), frame_id=frame
        )

    P = np.hstack([cam.K, np.zeros((3, 1))]).reshape(-1)
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    info = T["sensor_msgs/msg/CameraInfo"](
        header=header(0, cam.frame_id),
        height=48,
        width=64,
        distortion_model="plumb_bob",
        D=cam.dist.copy(),
        K=cam.K.reshape(-1),
        R=np.eye(3).reshape(-1),
        P=P,
        binning_x=0,
        binning_y=0,
        roi=roi,
    )
    tr = ext2.transform
    V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    ext = T["geometry_msgs/msg/TransformStamped"](
        header=header(0, "world"),
        child_frame_id=cam.frame_id,
        transform=T["geometry_msgs/msg/Transform"](
            translation=V3(x=tr.translation.x, y=tr.translation.y, z=tr.translation.z),
            rotation=Q(x=tr.rotation.x, y=tr.rotation.y, z=tr.rotation.z, w=tr.rotation.w),
        ),
    )
    path = tmp_path / "old.bag"
    with Writer1(path) as w:
        ci = w.add_connection("/cameras/cam02/camera_info", "sensor_msgs/msg/CameraInfo", typestore=s1)
        ce = w.add_connection("/cameras/cam02/extrinsics", "geometry_msgs/msg/TransformStamped", typestore=s1)
        cimg = w.add_connection("/cameras/cam02/image_raw", "sensor_msgs/msg/Image", typestore=s1)
        w.write(ce, 7 * 10**9, s1.serialize_ros1(ext, "geometry_msgs/msg/TransformStamped"))
        for i, im in enumerate(imgs):
            t = 7 * 10**9 + i * 10
            w.write(ci, t, s1.serialize_ros1(info, "sensor_msgs/msg/CameraInfo"))
            msg = T["sensor_msgs/msg/Image"](
                header=header(i, cam.frame_id),
                height=48,
                width=64,
                encoding="rgb8",
                is_bigendian=0,
                step=192,
                data=np.ascontiguousarray(im[..., ::-1]).reshape(-1),
            )
            w.write(cimg, t, s1.serialize_ros1(msg, "sensor_msgs/msg/Image"))
    with open_bag(path) as reader:
        assert reader.message_counts()["/cameras/cam02/image_raw"] == 3
        got = list(reader.images())
        assert [s for _, s, _ in got] == [7 * 10**9, 7 * 10**9 + 10, 7 * 10**9 + 20]
        for (_, _, a), b in zip(got, imgs, strict=True):
            np.testing.assert_array_equal(a, b)
    scene = read_scene(path)
    _assert_same_camera(scene.cameras[0], cam)
    assert len(list(scene.frames())) == 3


# ------------------------------------------------------------------ truncation


@pytest.fixture(scope="module")
def big_bag(tmp_path_factory):
    """~2.8 MB bag: rosbags closes MCAP chunks at 1 MiB, so this has three chunks."""
    cameras = _cameras(320, 240)
    frames = _frames(cameras, n=6, seed=4)
    path = tmp_path_factory.mktemp("big") / "big.mcap"
    write_scene_bag(path, cameras, frames, joint_names=JOINTS)
    with open_bag(path) as reader:
        full = [(t, s, bytes(m)) for t, s, m in reader.messages(raw=True)]
    return path, full


def _chunk_offsets(path: Path) -> tuple[list[tuple[int, int]], int]:
    """(start, end) of every top-level chunk record, and the end of the data-end record."""
    data = path.read_bytes()
    pos, out, data_end = 8, [], -1
    while pos < len(data):
        op, length = data[pos], int.from_bytes(data[pos + 1 : pos + 9], "little")
        if op == 0x06:
            out.append((pos, pos + 9 + length))
        if op == 0x0F:
            data_end = pos + 9 + length
        if op == 0x02:
            break
        pos += 9 + length
    return out, data_end


def test_truncated_mcap(big_bag, tmp_path):
    path, full = big_bag
    data = path.read_bytes()
    chunks, data_end = _chunk_offsets(path)
    assert len(chunks) >= 3
    (c0s, c0e), (c1s, _), (c2s, c2e) = chunks[0], chunks[1], chunks[-1]
    # messages fully inside the first k chunks
    per_chunk = []
    for start, _ in chunks:
        cut = tmp_path / "probe.mcap"
        cut.write_bytes(data[:start])
        with open_bag(cut, allow_truncated=True) as r:
            per_chunk.append(sum(1 for _ in r.messages(raw=True)))
    assert per_chunk[0] == 0 and per_chunk[1] > 0 and per_chunk[2] > per_chunk[1]

    cases = [
        (20, 0, "header at offset 8 is incomplete"),
        (c0s + 100, 0, f"chunk at offset {c0s} is incomplete"),
        ((c1s + c0e) // 2 if c1s > c0e else c1s + 7, per_chunk[1], "is incomplete"),
        (c2s + 5000, per_chunk[2], f"chunk at offset {c2s} is incomplete"),
        (c2e + 30, len(full), "message index at offset"),
        (data_end + 30, len(full), "summary section"),
        (len(data) - 4, len(full), "closing magic"),
    ]
    for size, n_ok, what in cases:
        cut = tmp_path / "cut.mcap"
        cut.write_bytes(data[:size])
        with pytest.raises(BagError) as err:
            open_bag(cut)
        msg = str(err.value)
        assert msg.startswith(f"{cut}: ") and "\n" not in msg
        assert what in msg, msg
        assert f"{n_ok} messages" in msg or f"all {n_ok} messages" in msg, msg
        with open_bag(cut, allow_truncated=True) as reader:
            assert reader.truncated and reader.problem
            got = [(t, s, bytes(m)) for t, s, m in reader.messages(raw=True)]
            assert got == full[:n_ok]
            if n_ok:
                decoded = list(reader.messages())
                assert len(decoded) == n_ok
    # read_scene on a bag cut in its last chunk: the complete frames and their truth
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: c2s + 5000])
    with pytest.raises(BagError, match="truncated after"):
        read_scene(cut)
    scene = read_scene(cut, allow_truncated=True)
    assert scene.truncated
    frames = list(scene.frames())
    assert 0 < len(frames) < 6
    assert all(len(images) == 2 for _, images in frames[:-1])
    assert scene.truth is not None and len(scene.truth.stamps) >= len(frames) - 1


def test_truncated_inside_bag_directory(big_bag, tmp_path):
    path, full = big_bag
    d = tmp_path / "rec"
    d.mkdir()
    chunks, _ = _chunk_offsets(path)
    (d / "rec.mcap").write_bytes(path.read_bytes()[: chunks[2][0] + 10])
    (d / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  version: 9\n  storage_identifier: mcap\n"
        "  relative_file_paths: [rec.mcap]\n  duration: {nanoseconds: 1}\n"
        "  starting_time: {nanoseconds_since_epoch: 0}\n  message_count: 32\n"
        "  topics_with_message_count: []\n"
    )
    with pytest.raises(BagError, match=r"rec: rec.mcap: truncated after \d+ messages \(chunk at offset"):
        open_bag(d)
    with open_bag(d, allow_truncated=True) as reader:
        got = [(t, s, bytes(m)) for t, s, m in reader.messages(raw=True)]
        assert got and got == full[: len(got)]
    os.remove(d / "metadata.yaml")  # a directory of storage files only
    with open_bag(d, allow_truncated=True) as reader:
        assert reader.truncated


def test_corrupt_chunk_in_complete_file(big_bag, tmp_path):
    """Damage inside an indexed file surfaces while reading, as one BagError line."""
    path, full = big_bag
    data = bytearray(path.read_bytes())
    (_, _), (c1s, _), *_ = _chunk_offsets(path)[0]
    first_record = c1s + 9 + 28 + 4 + 8  # chunk header: times, sizes, crc, compression "" and length
    data[first_record + 1 : first_record + 9] = (10**12).to_bytes(8, "little")
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with open_bag(bad) as reader, pytest.raises(BagError, match=r"bad.mcap: corrupt after \d+ messages"):
        for _ in reader.messages():
            pass
