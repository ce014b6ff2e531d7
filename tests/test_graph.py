"""Process-level tests: the real node executables over real DDS (ALGORITHMS.md §1 loop).

The graph replays a synthetic bag in lockstep, its output is recorded by the
bag_recorder node, and the recorded joints must equal `artrack track` on the
same bag to 1e-9; the recorded blob messages must show the priors flowing
back into blob_features and being used.
"""

from __future__ import annotations

import subprocess
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import NODE_BIN, REPO, run_artrack

from artrack.bags import open_bag
from artrack.messages import blobs_from_msg, body_from_msg

pytestmark = pytest.mark.graph
FRAMES = 75  # conftest.small_scene: 2.5 s at 30 fps
# Launches that compare the skeleton's bodies only leave the body_publisher out (one process less to start;
# the default graph_run and tests/test_ros_user.py run it)
NO_REP155 = "rep155=false"


def _launch(out: Path, scene: Path, env, *sets: str, timeout_s: int = 240, graph: str = "config/graph.yaml") -> Path:
    """Run ``graph`` on ``scene`` (extra ``--set`` values), return the recorded bag."""
    rec = out / "graph"
    extra = [a for s in sets for a in ("--set", s)]
    proc = subprocess.run(
        [str(NODE_BIN / "artrack"), "launch", graph, "--set", f"bag={scene}",
         "--set", f"out={rec}", *extra, "--log-dir", str(out / "logs"), "--timeout", str(timeout_s)],
        env=env, cwd=REPO, capture_output=True, text=True, timeout=timeout_s + 60,
    )
    logs = "\n".join(p.read_text(errors="replace")[-3000:] for p in sorted((out / "logs").glob("*.log")))
    assert proc.returncode == 0, f"launch failed ({proc.returncode}):\n{proc.stderr}\n{logs}"
    assert rec.exists(), f"recorder wrote nothing:\n{logs}"
    return rec


def _launch_beside(out: Path, scene: Path, env, offline: list[str], *sets: str, **kw) -> Path:
    """:func:`_launch`, with ``artrack track <offline> --out <out>/offline --quiet`` run beside it (the
    lockstep graph leaves a core idle while one node works; a thread waits on each process).
    Returns the recorded bag; the offline run's is ``<out>/offline/track``."""
    with ThreadPoolExecutor(1) as pool:
        job = pool.submit(run_artrack, env, "track", *offline, "--out", str(out / "offline"), "--quiet")
        rec = _launch(out, scene, env, *sets, **kw)
        job.result()
    return rec


@pytest.fixture(scope="module")
def graph_run(tmp_path_factory, env, small_scene) -> Path:
    """The default graph on the small scene; beside it `artrack track` on the same bag
    (``<graph_run>/../offline/track``)."""
    return _launch_beside(tmp_path_factory.mktemp("graph"), small_scene, env, [str(small_scene)])


def _bodies(bag: Path) -> dict[int, np.ndarray]:
    with open_bag(bag) as reader:
        return {body.stamp_ns: body.joints for body in
                (body_from_msg(m) for _, _, m in reader.messages(["/artrack/body"]))}


def _assert_same_bodies(live_bag: Path, offline_bag: Path, what: str) -> tuple[dict[int, np.ndarray], list[int]]:
    """The graph's recorded bodies equal the offline run's: every frame of the bag estimated exactly
    once, NaN joints (frames before start-up) in the same frames, the tracked joints to 1e-9.
    Returns (the offline bodies, the stamps of their tracked frames)."""
    live, offline = _bodies(live_bag), _bodies(offline_bag)
    assert len(offline) == FRAMES
    assert sorted(live) == sorted(offline), f"{what}: the graph must estimate every frame of the bag exactly once"
    for s in offline:
        assert np.array_equal(np.isnan(live[s]), np.isnan(offline[s])), f"{what}: NaN joints differ at stamp {s}"
    tracked = [s for s in offline if not np.isnan(offline[s]).all()]
    assert len(tracked) >= 15, f"{what}: the tracker should be running after the background seed"
    worst = max(float(np.nanmax(np.abs(live[s] - offline[s]))) for s in tracked)
    assert worst <= 1e-9, f"{what}: live graph and offline pipeline differ by {worst:.3g} m"
    return offline, tracked


def test_graph_equals_offline_track(graph_run):
    _assert_same_bodies(graph_run, graph_run.parent / "offline" / "track", "blobs")


def test_graph_with_refinement_equals_offline_track_with_refinement(tmp_path_factory, small_scene, env, graph_run):
    """``refine_passes`` over DDS (skeleton -> /artrack/refinement -> feedback_projection -> the
    blob_features nodes, which label the frame again from their state before it): with every tracked
    frame refined twice (``refine_min_interval_s`` 0) the graph equals `artrack track --refine-passes 2`,
    and both differ from the plain loop."""
    out = tmp_path_factory.mktemp("graph_refine")
    live = _launch_beside(out, small_scene, env,
                          [str(small_scene), "--refine-passes", "2", "--refine-min-interval", "0"],
                          NO_REP155, "refine_passes=2", "refine_min_interval_s=0.0")
    offline, tracked = _assert_same_bodies(live, out / "offline" / "track", "refined")
    plain = _bodies(graph_run)  # (= the plain offline loop: test_graph_equals_offline_track)
    moved = max(float(np.nanmax(np.abs(plain[s] - offline[s]))) for s in tracked)
    assert moved > 1e-3, "the refined frames should differ from the plain loop's"
    with open_bag(live) as reader:
        refined = [body_from_msg(m).stamp_ns for _, _, m in reader.messages(["/artrack/refinement"])]
    assert sorted(refined) == sorted(2 * tracked), "every tracked frame goes round twice more"


def _silent_graph(out: Path, feature_node: str) -> Path:
    """config/graph.yaml with ``feature_node`` (e.g. ``blob_features_{camera}``) run without
    ``answer_refinements`` and the skeleton's ``refine_timeout_s`` at 1 s, written to ``out``."""
    graph = yaml.safe_load((REPO / "config" / "graph.yaml").read_text())
    for node in graph["nodes"]:
        if node["name"] == feature_node:
            node["parameters"]["answer_refinements"] = False
        if node["name"] == "skeleton":
            node["parameters"]["refine_timeout_s"] = 1.0
    path = out / "graph.yaml"
    path.write_text(yaml.safe_dump(graph))
    return path


def test_refinement_unanswered_by_the_blob_nodes_is_given_up(tmp_path_factory, small_scene, env):
    """The skeleton refines but the blob_features nodes do not answer (``answer_refinements`` false,
    as a node restarted since the frame would not): they log that they do not label the frame again,
    the skeleton abandons that pass after its ``refine_timeout_s``, publishes the frame's first pass
    and switches refinement off with one warning, so the run goes on and equals the loop without
    refinement (before: no body for that frame, and each later frame waited for the player's 30-s
    timeout)."""
    out = tmp_path_factory.mktemp("graph_refine_unanswered")
    path = _silent_graph(out, "blob_features_{camera}")
    live = _launch_beside(out, small_scene, env, [str(small_scene), "--startup-refine-frames", "0"],
                          NO_REP155, "refine_passes=2", "refine_min_interval_s=0.0", graph=str(path))
    plain, tracked = _assert_same_bodies(live, out / "offline" / "track", "unanswered refinement")
    with open_bag(live) as reader:
        refined = [body_from_msg(m).stamp_ns for _, _, m in reader.messages(["/artrack/refinement"])]
    assert refined == [min(tracked)], "one refinement asked for (the first tracked frame's), then none"
    skeleton_log = (out / "logs" / "skeleton.log").read_text(errors="replace")
    warnings = [line for line in skeleton_log.splitlines() if "refinement off" in line]
    assert len(warnings) == 1 and "answer_refinements" in warnings[0], skeleton_log[-2000:]
    blob_log = (out / "logs" / "blob_features_cam01.log").read_text(errors="replace")
    assert sum("not labelled again" in line for line in blob_log.splitlines()) == 1, blob_log[-2000:]


def test_priors_flow_back_and_are_used(graph_run):
    bodies = _bodies(graph_run)
    first = min(s for s, j in bodies.items() if not np.isnan(j).all())  # first estimated frame
    after = sum(s > first for s in bodies)
    used, total, cameras = 0, 0, set()
    with open_bag(graph_run) as reader:
        for topic, _, msg in reader.messages():
            if topic.endswith("/blobs"):
                stamp, cam, _ = blobs_from_msg(msg)
                cameras.add(cam)
                total += 1
                used += bool(msg.prior_used)
                assert bool(msg.prior_used) == (stamp > first), "priors are used exactly once there are some"
                if msg.prior_used:
                    assert abs(msg.prior_staleness) < 1.0 / 60, "lockstep priors predict the very frame"
    with open_bag(graph_run) as reader:
        refined = sorted(body_from_msg(m).stamp_ns for _, _, m in reader.messages(["/artrack/refinement"]))
    # the start-up refinement (startup_refine_frames 10, startup_refine_passes 2): the ten frames after
    # the first estimate go round twice more, each pass labelled again by every camera
    assert refined == sorted(2 * sorted(s for s in bodies if s > first)[:10])
    assert cameras == {"cam01", "cam02", "cam03", "cam04"}
    assert total == 4 * (FRAMES + len(refined))
    assert after >= 15 and used == 4 * (after + len(refined)), \
        "every frame after the first estimate is classified with its prior, every refinement pass too"


def test_recorded_bag_readable_by_mcap(graph_run):
    from mcap.reader import make_reader

    files = sorted(Path(graph_run).glob("*.mcap"))
    assert files, "no .mcap inside the recorded bag"
    with open(files[0], "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        schemas = {s.name: s.data.decode() for s in summary.schemas.values()}
        topics = {c.topic for c in summary.channels.values()}
        counts = summary.statistics.channel_message_counts
    assert "artrack_msgs/msg/TrackedBody" in schemas
    assert "LinkState[] links" in schemas["artrack_msgs/msg/TrackedBody"]
    assert {"/artrack/body", "/artrack/prediction", "/cameras/cam01/blob_priors"} <= topics
    body_channel = next(cid for cid, c in summary.channels.items() if c.topic == "/artrack/body")
    assert counts[body_channel] == FRAMES


def _frame_ids(msg, path: str = ""):
    """(where, frame id) of every header in a message and in the messages of its arrays."""
    if hasattr(getattr(msg, "header", None), "frame_id"):
        yield path + "header", msg.header.frame_id
    for name in getattr(msg, "__dataclass_fields__", {}):
        value = getattr(msg, name)
        if isinstance(value, list):
            for i, item in enumerate(value):
                if hasattr(item, "__dataclass_fields__"):
                    yield from _frame_ids(item, f"{path}{name}[{i}].")


def test_every_recorded_header_names_its_frame(graph_run):
    """Frame ids on every header (REP 103 frames): the bodies, predictions, link poses and markers in
    the world frame, each camera's blobs and priors in its optical frame."""
    seen: dict[str, set[str]] = {}
    with open_bag(graph_run) as reader:
        for topic, _, msg in reader.messages():
            for where, frame in _frame_ids(msg):
                assert frame, f"{topic}: {where}.frame_id is empty"
                seen.setdefault(topic, set()).add(frame)
    assert {"/artrack/body", "/artrack/prediction", "/artrack/markers", "/cameras/cam01/blobs"} <= set(seen)
    for topic, frames in seen.items():
        camera = topic.split("/")[2] if topic.startswith("/cameras/") else None
        assert frames == ({f"{camera}_optical_frame"} if camera else {"world"}), (topic, frames)


@pytest.fixture(scope="module")
def edge_config(tmp_path_factory) -> Path:
    """config/edge_features.yaml with a 5-frame warm-up: the small scene tracks ~20 frames, fewer
    than the default warm-up (30), so with it the edges would never be used."""
    from artrack.config import read_yaml

    data = read_yaml(REPO / "config" / "edge_features.yaml")
    data["edge_tracker"]["warmup_frames"] = 5
    path = tmp_path_factory.mktemp("edge_config") / "edge_features.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def graph_run_edges(tmp_path_factory, env, small_scene, edge_config) -> Path:
    """The graph with edges; beside it `artrack track --edges` (``<graph_run_edges>/../offline/track``)."""
    return _launch_beside(tmp_path_factory.mktemp("graph_edges"), small_scene, env,
                          [str(small_scene), "--edges", "--edge-config", str(edge_config)],
                          NO_REP155, "edges=true", f"edge_config={edge_config}", timeout_s=300)


def test_graph_with_edges_equals_offline_track_with_edges(graph_run_edges, graph_run):
    """edge_features nodes (one per camera) measure about the prediction; the skeleton fuses their
    statistics with the blobs: the same joints as `artrack track --edges`, and different from
    blobs alone (the edges are really used, after their warm-up). The start-up refinement runs with
    the edges (stop 63): each refinement body on /artrack/refinement gets a second measurement of
    its frame from every camera's edge_features node, as offline."""
    offline, tracked = _assert_same_bodies(graph_run_edges, graph_run_edges.parent / "offline" / "track", "with edges")
    blobs_only = _bodies(graph_run)  # (= `artrack track` without edges: test_graph_equals_offline_track)
    assert max(float(np.nanmax(np.abs(blobs_only[s] - offline[s]))) for s in tracked) > 1e-3
    with open_bag(graph_run_edges) as reader:
        counts = {}
        for topic, _, _ in reader.messages():
            counts[topic] = counts.get(topic, 0) + 1
    refined = counts.get("/artrack/refinement", 0)
    assert refined == 20, "the 10 frames after the start-up frame, 2 more passes each"
    assert all(counts.get(f"/cameras/{c}/edge_statistics", 0) == FRAMES + refined
               for c in ("cam01", "cam02", "cam03", "cam04"))


def test_refinement_unanswered_by_the_edge_nodes_switches_it_off(tmp_path_factory, small_scene, env, edge_config):
    """With edges, the blob_features nodes answer the skeleton's refinement but the edge_features nodes
    do not (``answer_refinements`` false): the skeleton gives the first pass up after its
    ``refine_timeout_s`` and switches refinement off with one warning naming the edge statistics, so
    the later start-up frames do not each wait as long (before, each of the 10 was asked for and given
    up in turn); every frame gets one body, and an edge node says once that it does not measure again."""
    out = tmp_path_factory.mktemp("graph_refine_edges_unanswered")
    path = _silent_graph(out, "edge_features_{camera}")
    live = _launch(out, small_scene, env, NO_REP155, "edges=true", f"edge_config={edge_config}", graph=str(path),
                   timeout_s=300)
    bodies = _bodies(live)
    assert len(bodies) == FRAMES, "every frame gets one body"
    tracked = sorted(s for s, joints in bodies.items() if not np.isnan(joints).all())
    assert len(tracked) >= 15, "the graph goes on tracking"
    with open_bag(live) as reader:
        refined = [body_from_msg(m).stamp_ns for _, _, m in reader.messages(["/artrack/refinement"])]
    assert len(refined) == 1 and refined[0] in tracked[:2], "one refinement asked for (at the track's start), then none"
    skeleton_log = (out / "logs" / "skeleton.log").read_text(errors="replace")
    warnings = [line for line in skeleton_log.splitlines() if "refine_timeout_s" in line]
    assert len(warnings) == 1, skeleton_log[-2000:]
    assert "edge statistics from cam01, cam02, cam03, cam04" in warnings[0], warnings[0]
    assert "refinement off" in warnings[0] and "blobs from" not in warnings[0], warnings[0]  # (the blob nodes answered)
    edge_log = (out / "logs" / "edge_features_cam01.log").read_text(errors="replace")
    assert sum("not measured again" in line for line in edge_log.splitlines()) == 1, edge_log[-2000:]


@pytest.fixture(scope="module")
def one_camera_scene(tmp_path_factory, env) -> Path:
    """The small scene seen by one camera (cam01 of the ring)."""
    out = tmp_path_factory.mktemp("scene1") / "small_c1.mcap"
    run_artrack(env, "synth", "--seed", "3", "--cameras", "1", "--out", str(out), "--duration", "2.5",
                "--width", "320", "--height", "240", "--quiet")
    return out


def test_graph_with_one_camera_equals_offline_track(one_camera_scene, env, tmp_path):
    """A graph of one camera (one blob_features node): the skeleton node starts from that view alone
    and tracks (config/skeleton.yaml few_cameras, applied because it knows one camera), with the same
    joints as `artrack track` on the same bag."""
    rec = _launch_beside(tmp_path, one_camera_scene, env, [str(one_camera_scene)], NO_REP155, "cameras=[cam01]")
    _assert_same_bodies(rec, tmp_path / "offline" / "track", "one camera")


def test_graph_with_full_dynamics_equals_offline_track(small_scene, env, tmp_path):
    """The full-dynamics skeleton (``estimator: dynamic``: the raw tracker beside the dynamics, whose
    springs pull toward its fit, stop 47) in the live graph, with the same joints as `artrack track
    --estimator dynamic`. A 5-frame warm-up, so that the dynamics' own estimate, not the raw tracker's,
    is the output for most of the scene's ~25 tracked frames."""
    cfg = yaml.safe_load((REPO / "config" / "skeleton.yaml").read_text())
    cfg["kinematic"]["warmup_frames"] = 5
    path = tmp_path / "skeleton.yaml"
    path.write_text(yaml.safe_dump(cfg))
    rec = _launch_beside(tmp_path, small_scene, env, [str(small_scene), "--estimator", "dynamic",
                                                      "--skeleton-config", str(path)],
                         NO_REP155, "estimator=dynamic", f"skeleton_config={path}")
    _assert_same_bodies(rec, tmp_path / "offline" / "track", "full dynamics")
