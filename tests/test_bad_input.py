"""Bad input through the real `artrack` CLI: one clear line, exit 1, nothing half-written.

Acceptance criterion: "Bad input gets one clear line naming the file and field, a non-zero
exit and no half-written output: a truncated or corrupt bag, a calibration missing a field,
video frames whose size differs from the calibration, an unknown camera name, a body model
whose link has no parent."

Every case runs the installed `artrack` executable (conftest.run_artrack) in its own empty
folder and checks: exit status 1; stderr is exactly one line ``artrack <cmd>: ...`` naming
the offending file and the field / topic / camera; that folder (where every --out points)
and the shared inputs are byte-for-byte unchanged afterwards (no output, no temp files).
The cases are independent processes, so they run a few at a time to keep the file fast.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import struct
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from conftest import REPO, run_artrack
from scipy.spatial.transform import Rotation

W, H = 160, 120  # size of the synthetic scene (and of the matching videos / calibrations)


# ------------------------------------------------------------------ helpers
def snapshot(root: Path) -> dict[str, str]:
    """relative path -> content hash ('dir' for folders) of everything under ``root``."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for d in dirnames:
            out[os.path.relpath(os.path.join(dirpath, d), root)] = "dir"
        for f in filenames:
            p = os.path.join(dirpath, f)
            out[os.path.relpath(p, root)] = hashlib.sha1(Path(p).read_bytes()).hexdigest()
    return out


@dataclass
class Case:
    """``args``/``expect``: strings where {I} is the inputs folder and {O} the case's own folder.

    expect: fragments the single stderr line must contain (the file first).
    setup: files to create in {O} before the run (name -> text), e.g. a pre-existing --out.
    """

    id: str
    args: list[str]
    expect: list[str]
    setup: dict[str, str] = field(default_factory=dict)


CASES = [
    # ---- 1. truncated / corrupt bags
    Case("track-truncated-mcap", ["track", "{I}/half.mcap", "--out", "{O}/out"],
         ["{I}/half.mcap", "truncated after 0 messages", "chunk", "no message is readable"]),
    Case("track-truncated-mcap-partly-readable", ["track", "{I}/tail.mcap", "--out", "{O}/out"],
         ["{I}/tail.mcap", "truncated after", "chunk", "--allow-truncated"]),
    Case("track-garbage-mcap", ["track", "{I}/garbage.mcap", "--out", "{O}/out"],
         ["{I}/garbage.mcap", "not an MCAP file"]),
    Case("track-corrupt-chunk", ["track", "{I}/corrupt_mid.mcap", "--out", "{O}/out"],
         ["{I}/corrupt_mid.mcap", "corrupt"]),
    Case("track-truncated-existing-out", ["track", "{I}/half.mcap", "--out", "{O}/out"],
         ["{I}/half.mcap", "truncated"], setup={"out/joints.csv": "keep me\n", "out/notes.txt": "mine\n"}),
    # damage in the second chunk: found only while tracking, after the output was started
    Case("track-corrupt-2nd-chunk-existing-out", ["track", "{I}/corrupt_chunk2.mcap", "--out", "{O}/out"],
         ["{I}/corrupt_chunk2.mcap", "corrupt after"], setup={"out/joints.csv": "keep me\n"}),
    Case("track-corrupt-2nd-chunk-new-parents", ["track", "{I}/corrupt_chunk2.mcap", "--out", "{O}/a/b/out"],
         ["{I}/corrupt_chunk2.mcap", "corrupt after"]),
    Case("track-metadata-not-yaml", ["track", "{I}/brokenmeta", "--out", "{O}/out"],
         ["{I}/brokenmeta/metadata.yaml", "YAML"]),
    Case("track-metadata-missing-key", ["track", "{I}/nokeymeta", "--out", "{O}/out"],
         ["{I}/nokeymeta/metadata.yaml", "rosbag2_bagfile_information"]),
    Case("track-no-such-bag", ["track", "{I}/nothere.mcap", "--out", "{O}/out"], ["{I}/nothere.mcap"]),
    Case("track-out-is-a-file", ["track", "{I}/good.mcap", "--out", "{O}/out"], ["{O}/out", "not a directory"],
         setup={"out": "a file\n"}),
    Case("eval-truth-truncated", ["eval", "--truth", "{I}/half.mcap", "--pred", "{O}/pred.csv"],
         ["{I}/half.mcap", "truncated"], setup={"pred.csv": "frame,stamp,joint,x,y,z\n0,0,head,0,0,0\n"}),
    Case("eval-truth-garbage", ["eval", "--truth", "{I}/garbage.mcap", "--pred", "{O}/pred.csv"],
         ["{I}/garbage.mcap", "not an MCAP file"],
         setup={"pred.csv": "frame,stamp,joint,x,y,z\n0,0,head,0,0,0\n"}),
    Case("eval-truth-metadata-not-yaml", ["eval", "--truth", "{I}/brokenmeta", "--pred", "{O}/pred.csv"],
         ["{I}/brokenmeta/metadata.yaml", "YAML"], setup={"pred.csv": "frame,stamp,joint,x,y,z\n0,0,head,0,0,0\n"}),
    Case("overlay-truncated", ["overlay", "{I}/half.mcap", "--out", "{O}/o.png"], ["{I}/half.mcap", "truncated"]),
    Case("overlay-garbage", ["overlay", "{I}/garbage.mcap", "--out", "{O}/o.png"],
         ["{I}/garbage.mcap", "not an MCAP file"]),
    Case("overlay-metadata-missing-key", ["overlay", "{I}/nokeymeta", "--out", "{O}/o.mp4"],
         ["{I}/nokeymeta/metadata.yaml", "rosbag2_bagfile_information"]),
    # ---- 2. calibration missing a field (names file, camera and field)
    Case("calib-rig-no-K", ["track", "--videos", "{I}/a.mp4", "{I}/b.mp4", "--calib", "{I}/rig_noK.yaml",
                            "--out", "{O}/out"], ["{I}/rig_noK.yaml", "camera 'cam02'", "'K'"]),
    Case("calib-rig-no-dist", ["track", "--videos", "{I}/a.mp4", "{I}/b.mp4", "--calib", "{I}/rig_nodist.yaml",
                               "--out", "{O}/out"], ["{I}/rig_nodist.yaml", "camera 'cam01'", "'dist'"]),
    Case("calib-rig-no-R", ["track", "--videos", "{I}/a.mp4", "{I}/b.mp4", "--calib", "{I}/rig_noR.yaml",
                            "--out", "{O}/out"], ["{I}/rig_noR.yaml", "camera 'cam02'", "'R'"]),
    Case("calib-caminfo-no-matrix", ["track", "--videos", "{I}/a.mp4", "--calib", "{I}/info_nomatrix.yaml",
                                     "--out", "{O}/out"], ["{I}/info_nomatrix.yaml", "camera 'cam01'",
                                                           "'camera_matrix'"]),
    Case("calib-caminfo-no-dist", ["track", "--videos", "{I}/a.mp4", "--calib", "{I}/info_nodist.yaml",
                                   "--out", "{O}/out"], ["{I}/info_nodist.yaml", "camera 'cam01'",
                                                         "'distortion_coefficients'"]),
    Case("calib-toml-no-rotation", ["track", "--videos", "{I}/a.mp4", "{I}/b.mp4", "--calib",
                                    "{I}/norot.toml", "--out", "{O}/out"],
         ["{I}/norot.toml", "camera 'cam02'", "'rotation'"]),
    Case("calib-toml-no-matrix", ["track", "--videos", "{I}/a.mp4", "{I}/b.mp4", "--calib",
                                  "{I}/nomatrix.toml", "--out", "{O}/out"],
         ["{I}/nomatrix.toml", "camera 'cam01'", "'matrix'"]),
    Case("calib-qca-no-focal", ["track", "--videos", "{I}/a.mp4", "--calib", "{I}/nofocal.qca.txt",
                                "--out", "{O}/out"], ["{I}/nofocal.qca.txt", "camera 'camA'", "focalLengthU"]),
    Case("calib-qca-no-rotation", ["track", "--videos", "{I}/a.mp4", "--calib", "{I}/norot.qca.txt",
                                   "--out", "{O}/out"], ["{I}/norot.qca.txt", "camera 'camA'", "r11"]),
    Case("calib-qca-no-distortion", ["track", "--videos", "{I}/a.mp4", "--calib", "{I}/nodist.qca.txt",
                                     "--out", "{O}/out"], ["{I}/nodist.qca.txt", "camera 'camA'",
                                                           "radialDistortion1"]),
    Case("calib-missing-file", ["track", "--videos", "{I}/a.mp4", "--calib", "{I}/nothere.yaml",
                                "--out", "{O}/out"], ["{I}/nothere.yaml", "not found"]),
    # ---- 3. video frames whose size differs from the calibration
    Case("video-size-mp4", ["track", "--videos", "{I}/big_a.mp4", "{I}/b.mp4", "--calib", "{I}/rig.yaml",
                            "--out", "{O}/out"], ["{I}/big_a.mp4", "200x100", "camera 'cam01'", f"{W}x{H}"]),
    Case("video-size-avi", ["track", "--videos", "{I}/a.mp4", "{I}/big_b.avi", "--calib", "{I}/rig.yaml",
                            "--out", "{O}/out"], ["{I}/big_b.avi", "200x100", "camera 'cam02'", f"{W}x{H}"]),
    Case("video-size-scaled", ["track", "--videos", "{I}/big_a.mp4", "{I}/b.mp4", "--calib", "{I}/rig.yaml",
                               "--scale", "0.5", "--out", "{O}/out"], ["{I}/big_a.mp4", "camera 'cam01'"]),
    Case("video-not-a-video", ["track", "--videos", "{I}/notavideo.mp4", "{I}/b.mp4", "--calib",
                               "{I}/rig.yaml", "--out", "{O}/out"], ["{I}/notavideo.mp4", "cannot open video"]),
    Case("video-too-many", ["track", "--videos", "{I}/a.mp4", "{I}/b.mp4", "{I}/a.mp4", "--calib",
                            "{I}/rig.yaml", "--out", "{O}/out"], ["{I}/rig.yaml", "2 cameras for 3 videos"]),
    # ---- 4. unknown camera name
    Case("camera-name-bag", ["track", "{I}/good.mcap", "--camera-names", "cam01", "nosuchcam",
                             "--out", "{O}/out"], ["{I}/good.mcap", "no camera named 'nosuchcam'"]),
    Case("camera-name-calib", ["track", "--videos", "{I}/a.mp4", "--calib", "{I}/rig.yaml", "--camera-names",
                               "nosuchcam", "--out", "{O}/out"], ["{I}/rig.yaml", "no camera named 'nosuchcam'"]),
    # ---- 5. body model whose link has no parent
    Case("body-no-parent-track", ["track", "{I}/good.mcap", "--body-model", "{I}/body_noparent.yaml",
                                  "--out", "{O}/out"], ["{I}/body_noparent.yaml", "link 'l_forearm'",
                                                        "no parent"]),
    Case("body-unknown-parent-track", ["track", "{I}/good.mcap", "--body-model", "{I}/body_badparent.yaml",
                                       "--out", "{O}/out"], ["{I}/body_badparent.yaml", "link 'l_hand'",
                                                             "parent 'l_arm'"]),
    Case("body-no-parent-synth", ["synth", "--body-model", "{I}/body_noparent.yaml", "--duration", "0.1",
                                  "--width", "80", "--height", "60", "--out", "{O}/s.mcap", "--quiet"],
         ["{I}/body_noparent.yaml", "link 'l_forearm'", "no parent"]),
    Case("body-unknown-parent-synth", ["synth", "--body-model", "{I}/body_badparent.yaml", "--duration", "0.1",
                                       "--width", "80", "--height", "60", "--out", "{O}/s.mcap", "--quiet"],
         ["{I}/body_badparent.yaml", "link 'l_hand'", "parent 'l_arm'"]),
    Case("config-not-text", ["track", "{I}/good.mcap", "--blob-config", "{I}/binary.yaml", "--out", "{O}/out"],
         ["{I}/binary.yaml", "not a text file"]),
    # YAML syntax errors: one line with what is wrong and where (str(yaml error) spans several lines)
    Case("body-not-yaml", ["track", "{I}/good.mcap", "--body-model", "{O}/body.yaml", "--out", "{O}/out"],
         ["{O}/body.yaml", "not valid YAML", "at line 3"], setup={"body.yaml": "links: [\n  {name: a, joint: free\n"}),
    Case("config-not-yaml", ["track", "{I}/good.mcap", "--skeleton-config", "{O}/skeleton.yaml", "--out", "{O}/out"],
         ["{O}/skeleton.yaml", "not valid YAML", "at line 3"], setup={"skeleton.yaml": "fit:\n  a: [1, 2\n"}),
    Case("calib-not-yaml", ["track", "--videos", "{I}/a.mp4", "--calib", "{O}/rig.yaml", "--out", "{O}/out"],
         ["{O}/rig.yaml", "not valid YAML", "at line 3"], setup={"rig.yaml": "cameras:\n  - {name: a\n"}),
    Case("config-is-a-directory", ["track", "{I}/good.mcap", "--skeleton-config", "{I}/brokenmeta",
                                   "--out", "{O}/out"], ["{I}/brokenmeta", "is a directory"]),
    # ---- 6. synth output / arguments, eval predictions
    Case("synth-out-under-a-file", ["synth", "--duration", "0.1", "--width", "80", "--height", "60",
                                    "--out", "{O}/afile/s.mcap", "--quiet"],
         ["{O}/afile/s.mcap", "not a directory"], setup={"afile": "x\n"}),
    Case("synth-out-unwritable", ["synth", "--duration", "0.1", "--width", "80", "--height", "60",
                                  "--out", "/proc/artrack_test/s.mcap", "--quiet"], ["/proc/artrack_test/s.mcap"]),
    Case("synth-zero-cameras", ["synth", "--cameras", "0", "--duration", "0.1", "--out", "{O}/s.mcap", "--quiet"],
         ["--cameras", "0"]),
    Case("synth-zero-duration", ["synth", "--duration", "0", "--out", "{O}/s.mcap", "--quiet"], ["--duration"]),
    Case("synth-zero-width", ["synth", "--width", "0", "--duration", "0.1", "--out", "{O}/s.mcap", "--quiet"],
         ["--width"]),
    Case("synth-blackout-garbage", ["synth", "--blackout", "soon", "--duration", "0.1", "--out", "{O}/s.mcap",
                                    "--quiet"], ["--blackout soon", "START:SECONDS"]),
    Case("synth-blackout-after-the-end", ["synth", "--blackout", "5:1", "--duration", "0.1", "--out", "{O}/s.mcap",
                                          "--quiet"], ["--blackout 5:1"]),
    Case("overlay-out-under-a-file", ["overlay", "{I}/good.mcap", "--out", "{O}/afile/o.png"],
         ["{O}/afile/o.png", "not a directory"], setup={"afile": "x\n"}),
    Case("eval-pred-empty-folder", ["eval", "--truth", "{I}/good.mcap", "--pred", "{O}/pred"],
         ["{O}/pred", "joints.csv"], setup={"pred/.keep": ""}),
    Case("eval-pred-header-only", ["eval", "--truth", "{I}/good.mcap", "--pred", "{O}/pred"],
         ["{O}/pred/joints.csv", "no rows"], setup={"pred/joints.csv": "frame,stamp,joint,x,y,z\n"}),
    Case("eval-pred-empty-csv", ["eval", "--truth", "{I}/good.mcap", "--pred", "{O}/pred"],
         ["{O}/pred/joints.csv", "empty"], setup={"pred/joints.csv": ""}),
    Case("eval-pred-bag-without-body", ["eval", "--truth", "{I}/good.mcap", "--pred", "{I}/good.mcap"],
         ["{I}/good.mcap", "'/artrack/body'"]),
    Case("eval-truth-csv-bad-number", ["eval", "--truth", "{O}/truth.csv", "--pred", "{O}/truth.csv"],
         ["{O}/truth.csv", "line 2", "'x'"], setup={"truth.csv": "frame,stamp,joint,x,y,z\n0,0,head,abc,0,0\n"}),
]


# ------------------------------------------------------------------ inputs
def _qca(missing: str = "") -> str:
    M = Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix()
    attrs = {"r11": M[0, 0], "r12": M[0, 1], "r13": M[0, 2], "r21": M[1, 0], "r22": M[1, 1], "r23": M[1, 2],
             "r31": M[2, 0], "r32": M[2, 1], "r33": M[2, 2], "x": 1460.2, "y": -1909.2, "z": 1896.5}
    intr = {"focalLengthU": 9000.0, "focalLengthV": 9000.0, "centerPointU": 79.5 * 64, "centerPointV": 59.5 * 64,
            "radialDistortion1": 0.0, "radialDistortion2": 0.0, "radialDistortion3": 0.0,
            "tangentalDistortion1": 0.0, "tangentalDistortion2": 0.0, "skew": 0.0}
    attrs.pop(missing, None)
    intr.pop(missing, None)

    def fmt(d):
        return " ".join(f'{k}="{float(v)!r}"' for k, v in d.items())

    return ("<?xml version='1.0' encoding='ASCII'?>\n<calibration type=\"regular\"><cameras>\n"
            '<camera active="1" model="none" serial="camA" viewrotation="0">\n'
            f'<fov_video bottom="{H - 1}" left="0" right="{W - 1}" top="0"/>\n'
            f"<transform {fmt(attrs)}/>\n<intrinsic {fmt(intr)}/>\n</camera></cameras></calibration>\n")


def _toml(cameras, drop: tuple[str, str] | None = None) -> str:
    parts = []
    for c in cameras:
        fields = {
            "name": f'"{c.name}"',
            "size": f"[{float(c.width)}, {float(c.height)}]",
            "matrix": repr(c.K.tolist()),
            "distortions": repr(c.dist[:4].tolist()),
            "rotation": repr(c.rvec.tolist()),
            "translation": repr(c.t.tolist()),
            "fisheye": "false",
        }
        if drop and drop[0] == c.name:
            fields.pop(drop[1])
        parts.append(f"[{c.name}]\n" + "".join(f"{k} = {v}\n" for k, v in fields.items()))
    return "\n".join(parts) + "\n[metadata]\nadjusted = false\nerror = 0.0\n"


def _caminfo(cam, drop: str | None = None) -> str:
    data = {
        "image_width": cam.width,
        "image_height": cam.height,
        "camera_name": cam.name,
        "camera_matrix": {"rows": 3, "cols": 3, "data": cam.K.reshape(-1).tolist()},
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": cam.dist.tolist()},
    }
    if drop:
        data.pop(drop)
    return yaml.safe_dump(data, sort_keys=False)


def _corrupt_second_chunk(data: bytes) -> bytes:
    """The MCAP with the length of the first message record in its second chunk made absurd."""
    pos, chunks = 8, []
    while pos < len(data) and data[pos] != 0x02:  # top-level records up to the footer
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        if data[pos] == 0x06:
            chunks.append(pos)
        pos += 9 + length
    assert len(chunks) >= 2, "scene too small for two chunks"
    body = chunks[1] + 9
    (n,) = struct.unpack_from("<I", data, body + 28)  # compression string length
    rec = body + 28 + 4 + n + 8  # first record of the chunk
    while data[rec] != 0x05:  # message record
        rec += 9 + struct.unpack_from("<Q", data, rec + 1)[0]
    out = bytearray(data)
    struct.pack_into("<Q", out, rec + 1, 2**62)
    return bytes(out)


def _video(path: Path, w: int, h: int, fourcc: str, n: int = 4) -> None:
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 30.0, (w, h))
    assert vw.isOpened(), path
    rng = np.random.default_rng(0)
    for _ in range(n):
        vw.write(rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
    vw.release()


@pytest.fixture(scope="module")
def inputs(tmp_path_factory, env) -> Path:
    from artrack.bags import read_scene
    from artrack.cameras import save_rig_yaml

    d = tmp_path_factory.mktemp("bad_input")
    good = d / "good.mcap"
    run_artrack(env, "synth", "--seed", "1", "--duration", "0.5", "--width", str(W), "--height", str(H),
                "--cameras", "2", "--out", str(good), "--quiet")
    data = good.read_bytes()
    (d / "half.mcap").write_bytes(data[: len(data) // 2])
    (d / "tail.mcap").write_bytes(data[: int(len(data) * 0.85)])  # first chunk complete, second cut
    (d / "garbage.mcap").write_bytes(np.random.default_rng(0).integers(0, 256, 5000, np.uint8).tobytes())
    mid = bytearray(data)
    mid[len(data) // 3 : len(data) // 3 + 64] = b"\xff" * 64  # inside the first chunk's compressed data
    (d / "corrupt_mid.mcap").write_bytes(bytes(mid))
    (d / "corrupt_chunk2.mcap").write_bytes(_corrupt_second_chunk(data))
    for name, meta in [("brokenmeta", "rosbag2_bagfile_information: [unclosed\n  : :\n"),
                       ("nokeymeta", "something_else: 1\n")]:
        (d / name).mkdir()
        (d / name / "metadata.yaml").write_text(meta)
        shutil.copy(good, d / name / f"{name}_0.mcap")

    cams = read_scene(good).cameras
    assert [c.name for c in cams] == ["cam01", "cam02"] and (cams[0].width, cams[0].height) == (W, H)
    save_rig_yaml(cams, d / "rig.yaml")
    rig = yaml.safe_load((d / "rig.yaml").read_text())
    for name, cam_i, key in [("rig_noK", 1, "K"), ("rig_nodist", 0, "dist"), ("rig_noR", 1, "R")]:
        broken = yaml.safe_load(yaml.safe_dump(rig))
        del broken["cameras"][cam_i][key]
        (d / f"{name}.yaml").write_text(yaml.safe_dump(broken))
    (d / "info_nomatrix.yaml").write_text(_caminfo(cams[0], "camera_matrix"))
    (d / "info_nodist.yaml").write_text(_caminfo(cams[0], "distortion_coefficients"))
    (d / "norot.toml").write_text(_toml(cams, ("cam02", "rotation")))
    (d / "nomatrix.toml").write_text(_toml(cams, ("cam01", "matrix")))
    (d / "good.toml").write_text(_toml(cams))
    (d / "nofocal.qca.txt").write_text(_qca("focalLengthU"))
    (d / "norot.qca.txt").write_text(_qca("r11"))
    (d / "nodist.qca.txt").write_text(_qca("radialDistortion1"))
    (d / "good.qca.txt").write_text(_qca())

    _video(d / "a.mp4", W, H, "mp4v")
    _video(d / "b.mp4", W, H, "mp4v")
    _video(d / "big_a.mp4", 200, 100, "mp4v")
    _video(d / "big_b.avi", 200, 100, "MJPG")
    (d / "notavideo.mp4").write_bytes(b"this is not a video\n" * 50)
    (d / "binary.yaml").write_bytes(bytes(range(128, 256)) * 4)

    body = (REPO / "config" / "body_model.yaml").read_text()
    model = yaml.safe_load(body)
    for name, link, fn in [("body_noparent", "l_forearm", lambda lk: lk.pop("parent")),
                           ("body_badparent", "l_hand", lambda lk: lk.__setitem__("parent", "l_arm"))]:
        broken = yaml.safe_load(body)
        fn(next(lk for lk in broken["links"] if lk["name"] == link))
        (d / f"{name}.yaml").write_text(yaml.safe_dump(broken, sort_keys=False))
    assert model["links"][0]["parent"] is None
    return d


def _fill(s: str, inp: Path, case_dir: Path) -> str:
    return s.replace("{I}", str(inp)).replace("{O}", str(case_dir))


@pytest.fixture(scope="module")
def results(inputs, env, tmp_path_factory):
    """Run every case (a few processes at a time); case id -> (proc, case dir, before, after)."""
    root = tmp_path_factory.mktemp("bad_input_cases")
    before_inputs = snapshot(inputs)

    def run(case: Case):
        cdir = root / case.id
        cdir.mkdir()
        for rel, text in case.setup.items():
            (cdir / rel).parent.mkdir(parents=True, exist_ok=True)
            (cdir / rel).write_text(text)
        before = snapshot(cdir)
        proc = run_artrack(env, *[_fill(a, inputs, cdir) for a in case.args], timeout=120, check=False)
        return case.id, (proc, cdir, before, snapshot(cdir))

    with ThreadPoolExecutor(max_workers=max(2, min(4, os.cpu_count() or 2))) as pool:
        out = dict(pool.map(run, CASES))
    out["_inputs_unchanged"] = snapshot(inputs) == before_inputs
    return out


# ------------------------------------------------------------------ tests
@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_one_line_exit_1_nothing_written(case, results, inputs):
    proc, cdir, before, after = results[case.id]
    shown = f"artrack {' '.join(case.args)}\nexit {proc.returncode}\nstdout: {proc.stdout}\nstderr: {proc.stderr}"
    assert proc.returncode == 1, shown
    assert "Traceback" not in proc.stderr, shown
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, shown
    line = lines[0]
    assert line.startswith(f"artrack {case.args[0]}: "), shown
    for fragment in case.expect:
        assert _fill(fragment, inputs, cdir) in line, f"missing {fragment!r}\n{shown}"
    assert after == before, f"output left behind: {sorted(set(after) ^ set(before))}\n{shown}"


def test_inputs_unchanged(results):
    assert results["_inputs_unchanged"]


def test_allow_truncated_tracks_the_readable_part(inputs, env, tmp_path):
    """--allow-truncated: the frames before the damage are tracked, with one warning line."""
    out = tmp_path / "out"
    proc = run_artrack(env, "track", str(inputs / "tail.mcap"), "--allow-truncated", "--max-frames", "3",
                       "--out", str(out), "--quiet", check=False)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and str(inputs / "tail.mcap") in lines[0] and "truncated" in lines[0], proc.stderr
    assert sorted(p.name for p in out.iterdir()) == ["joints.csv", "track"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temp sibling left


def test_good_inputs_are_accepted(inputs, env, tmp_path):
    """The calibrations and videos the bad cases are derived from are themselves fine."""
    for calib, videos in [("rig.yaml", ["a.mp4", "b.mp4"]), ("good.toml", ["a.mp4", "b.mp4"]),
                          ("good.qca.txt", ["a.mp4"])]:
        out = tmp_path / calib
        proc = run_artrack(env, "track", "--videos", *[str(inputs / v) for v in videos], "--calib",
                           str(inputs / calib), "--max-frames", "1", "--out", str(out), "--quiet", check=False)
        assert proc.returncode == 0, proc.stderr
        assert (out / "joints.csv").is_file()
