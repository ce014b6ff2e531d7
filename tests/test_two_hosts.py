"""Two hosts of one DDS domain (issue item 7): scripts/two_hosts.sh runs the camera nodes (player,
blob_features per camera) and the tracker nodes (skeleton, feedback projection, body publisher,
recorder) in two network namespaces joined by a veth pair, DDS over UDP only. The closed loop
must close across the link on every frame (lockstep)."""

from __future__ import annotations

import re
import subprocess

import pytest
from conftest import REPO

from artrack.bags import open_bag
from artrack.messages import blobs_from_msg, body_from_msg

pytestmark = pytest.mark.graph
FRAMES = 20


def test_camera_nodes_and_skeleton_on_two_hosts(env, small_scene, tmp_path):
    out = tmp_path / "two_hosts"
    proc = subprocess.run(["bash", str(REPO / "scripts" / "two_hosts.sh"), str(small_scene), str(out),
                           f"max_frames={FRAMES}"], env=env, capture_output=True, text=True, timeout=240)
    if proc.returncode == 77:
        pytest.skip(proc.stderr.strip())
    logs = "\n".join(p.read_text(errors="replace")[-1500:] for p in sorted(out.glob("logs_*/*.log")))
    assert proc.returncode == 0, f"{proc.stdout}\n{proc.stderr}\n{logs}"
    assert f"done: {FRAMES} frames; {FRAMES} bodies" in logs, "every frame's body came back across the link"
    with open_bag(out / "graph") as reader:
        bodies, blobs = set(), {}
        for topic, _, msg in reader.messages():
            if topic == "/artrack/body":
                bodies.add(body_from_msg(msg).stamp_ns)
            elif topic.endswith("/blobs"):
                stamp, cam, _ = blobs_from_msg(msg)
                blobs.setdefault(cam, set()).add(stamp)
    assert len(bodies) == FRAMES
    assert {c: len(s) for c, s in blobs.items()} == {f"cam0{i}": FRAMES for i in range(1, 5)}, \
        "the blobs of every camera host node reached the tracker host"
    rx, tx = map(int, re.search(r"link bytes rx (\d+) tx (\d+)", proc.stdout).groups())
    assert rx > 10_000 and tx > 10_000, "the traffic went over the veth link"
