"""bench/closed_loop.py's phases of a run: start-up frames, walk, after the walk; and the occlusion
claim without the start-up frames; its --body option refuses a bad or incompatible model with one
line and writes nothing."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from artrack.body_model import load_body_model
from artrack.motion import T_WALK_END
from artrack.synth import START_STAMP_NS


@pytest.fixture(scope="module")
def closed_loop():
    path = Path(__file__).resolve().parents[1] / "bench" / "closed_loop.py"
    spec = importlib.util.spec_from_file_location("bench_closed_loop", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _stamps(times_s):
    return [START_STAMP_NS + int(round(t * 1e9)) for t in times_s]


def test_phases_split_start_up_walk_and_after_the_walk(closed_loop):
    cl = closed_loop
    times = np.arange(1.7, 6.0, 1 / 30)  # tracked from 1.7 s, as the default scene
    n = len(times)
    err = np.full((n, 15), 0.030)
    err[: cl.STARTUP_FRAMES] = 0.300  # a start-up far off
    after = times >= T_WALK_END
    err[after] = 0.060  # worse once the arms go up
    head_hands = [2, 5, 8]
    err[cl.STARTUP_FRAMES:, head_hands] = 0.020
    err[after, 5] = 0.050
    p = cl.phases("default", _stamps(times), err, head_hands)
    assert p["startup_mm"] == pytest.approx(300.0)
    assert p["walk_mm"] == pytest.approx(1e3 * err[cl.STARTUP_FRAMES:][~after[cl.STARTUP_FRAMES:]].mean())
    assert p["after_walk_mm"] == pytest.approx(1e3 * err[after].mean())
    assert p["settled_mm"] == pytest.approx(1e3 * err[cl.STARTUP_FRAMES:].mean())
    hh = err[cl.STARTUP_FRAMES:][:, head_hands]
    assert p["head_hands_rms_settled_mm"] == pytest.approx(1e3 * np.sqrt(np.mean(hh**2)))
    # the line scene has no walk: no walk phases, the rest the same way
    q = cl.phases("line", _stamps(times), err, head_hands)
    assert "walk_mm" not in q and q["startup_mm"] == pytest.approx(300.0)


def test_occlusion_claim_without_the_start_up_frames(closed_loop):
    cl = closed_loop
    body = load_body_model()
    names = list(body.joint_names)
    n = 40
    truth = np.zeros((n, len(names), 3))
    est = truth.copy()
    est[: cl.STARTUP_FRAMES, names.index("l_wrist"), 0] = 0.300  # hands far off at start-up only
    est[25, names.index("r_wrist"), 1] = 0.100  # later, one frame within the limit
    stamps = _stamps(np.arange(n) / 30)
    c = cl.claim("occlusion", body, stamps, est, truth)
    assert c["frames_over_150mm"] == cl.STARTUP_FRAMES and c["hand_max_mm"] == pytest.approx(300.0)
    assert c["frames_over_150mm_settled"] == 0 and c["hand_max_settled_mm"] == pytest.approx(100.0)
    est[30, names.index("r_wrist"), 2] = 0.200  # a loss after the start-up counts in both
    c = cl.claim("occlusion", body, stamps, est, truth)
    assert c["frames_over_150mm_settled"] == 1 and c["frames_over_150mm"] == cl.STARTUP_FRAMES + 1


def test_distractor_claim_counts_jumps_on_the_other_person_apart(closed_loop):
    """A frame whose head or wrist lies nearer the second person's same joint than the true one is a
    jump frame; it is also on the other person only within ``JUMP_NEAR_M`` of that joint: a hand
    lost far from both people is nearer one of them, but on neither. The knees and ankles are counted
    the same way, apart from the claim."""
    cl = closed_loop
    from artrack.motion import pose_at

    body = load_body_model()
    names = list(body.joint_names)
    times = np.arange(20) / 30 + 1.0
    stamps = _stamps(times)
    other = np.array([body.joint_positions(pose_at("distractor", float(t), body))
                      for t in cl.motion_time("distractor", stamps)])
    truth = other + np.array([2.0, 0.0, 0.0])  # the tracked person 2 m away
    est = truth.copy()
    r = names.index("r_wrist")
    est[3, r] = other[3, r] + [0.05, 0.0, 0.0]  # on the other person's wrist
    est[7, r] = other[7, r] + [0.9, 0.0, 0.5]  # lost: nearer the other person, but far from both
    c = cl.claim("distractor", body, stamps, est, truth)
    assert c == {"jump_frames": 2, "jump_frames_near_other": 1, "leg_jump_frames": 0, "leg_jump_frames_near_other": 0}
    # the knees and ankles are counted apart (the claim is about head and hands only)
    ka = names.index("r_ankle")
    est[3, ka] = other[3, ka] + [0.1, 0.0, 0.0]  # an ankle on the other person in a frame with a jump already
    est[11, names.index("l_knee")] = other[11, names.index("l_knee")] + [0.6, 0.0, 0.3]  # lost, nearer them
    c = cl.claim("distractor", body, stamps, est, truth)
    assert c == {"jump_frames": 2, "jump_frames_near_other": 1, "leg_jump_frames": 2, "leg_jump_frames_near_other": 1}
    assert cl.claim_text(c) == "jumps 2, legs 2"


def test_smoothed_line_keeps_a_bow_and_drops_the_jitter(closed_loop):
    """The line claim's smoothed figure: frame-to-frame jitter goes, a slow bow of the path stays."""
    cl = closed_loop
    body = load_body_model()
    wr = list(body.joint_names).index("r_wrist")
    n = 120
    s = np.linspace(-0.2, 0.2, n)
    truth = np.zeros((n, len(body.joint_names), 3))
    truth[:, wr, 1] = s
    rng = np.random.default_rng(0)
    jitter = truth.copy()
    jitter[:, wr, 0] += rng.normal(0.0, 0.005, n)
    bow = truth.copy()
    bow[:, wr, 0] += 0.010 * np.sin(np.pi * (s + 0.2) / 0.4)
    stamps = _stamps(np.arange(n) / 30)
    cj = cl.claim("line", body, stamps, jitter, truth)
    cb = cl.claim("line", body, stamps, bow, truth)
    assert cj["line_rms_mm_smoothed"] < 0.6 * cj["line_rms_mm"]  # white noise: SG(9, 2) passes ~0.55 of it
    assert cb["line_rms_mm_smoothed"] == pytest.approx(cb["line_rms_mm"], rel=0.02)


def _run_closed_loop(*args):
    bench = Path(__file__).resolve().parents[1] / "bench" / "closed_loop.py"
    return subprocess.run([sys.executable, str(bench), *args], capture_output=True, text=True, timeout=120)


def test_blob_points_are_the_blob_centres_on_the_link_poses(closed_loop):
    """Head and hands at their blob centres: zero error for the true link poses (the default
    scene's motion replayed at the frame's stamp), the hand's offset turned with its link for a
    turned hand; None for a recorded truth the replay does not match, or a missing link."""
    cl = closed_loop
    from artrack.motion import pose_at
    from artrack.types import LinkEstimate

    body = load_body_model()
    stamp = _stamps([2.0])[0]
    theta = pose_at("default", 2.0, body)
    T = body.forward_kinematics(theta)
    joints = body.joint_positions(theta, T)
    links = [LinkEstimate(n, T[i, :3, 3].copy(), T[i, :3, :3].copy()) for i, n in enumerate(body.link_names)]
    est, tru = cl.blob_points("default", body, stamp, links, joints)
    np.testing.assert_allclose(est, tru, atol=1e-12)
    hand = next(lk for lk in links if lk.name == "r_hand")
    hand.rotation = hand.rotation @ np.diag([1.0, -1.0, -1.0])  # turned half round its own x axis
    est, tru = cl.blob_points("default", body, stamp, links, joints)
    c = body.link("r_hand").blob.centre
    assert np.linalg.norm(est[2] - tru[2]) == pytest.approx(2 * np.hypot(c[1], c[2]), abs=1e-12)
    assert np.linalg.norm(est[2] - tru[2]) > 0.1
    np.testing.assert_allclose(est[:2], tru[:2], atol=1e-12)
    assert cl.blob_points("default", body, stamp, links, joints + 0.01) is None
    assert cl.blob_points("default", body, stamp, [lk for lk in links if lk.name != "head"], joints) is None


def test_body_option_refuses_a_bad_model_before_rendering(tmp_path):
    bad = tmp_path / "bad_body.yaml"
    bad.write_text("links: 3\n")
    res = _run_closed_loop("--body", str(bad), "--cache", str(tmp_path / "cache"))
    assert res.returncode == 2
    last = res.stderr.strip().splitlines()[-1]
    assert "--body" in last and str(bad) in last and "links" in last
    assert not (tmp_path / "cache").exists()  # nothing rendered or written


def test_body_option_refuses_a_model_with_other_joints(tmp_path):
    default = Path(__file__).resolve().parents[1] / "config" / "body_model.yaml"
    other = tmp_path / "other_joints.yaml"
    other.write_text(f"extends: {default}\nname: other\n"
                     "joints:\n  - {name: pelvis, link: pelvis, point: [0.0, 0.0, 0.0]}\n")
    res = _run_closed_loop("--body", str(other), "--cache", str(tmp_path / "cache"))
    assert res.returncode == 2
    assert "joints differ" in res.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "cache").exists()


def test_live_graph_bench_reads_the_players_closing_line():
    """bench/live_graph.py parses bag_player's closing line (its format: bag_player._throughput)."""
    path = Path(__file__).resolve().parents[1] / "bench" / "live_graph.py"
    spec = importlib.util.spec_from_file_location("bench_live_graph", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    line = ("[INFO] [1.2] [bag_player]: done: 100 frames; 47 bodies in 6.8 s: 6.92 frames per second (closed loop); "
            "47 of 100 frames got a body, 190 ms (median) and 377 ms (max) after they were sent")
    assert bench.parse_player_log(line) == {"frames_sent": 100, "bodies": 47, "bodies_per_s": 6.92,
                                            "latency_median_ms": 190, "latency_max_ms": 377}
    assert bench.parse_player_log("done: 75 frames; no body came back")["bodies"] == 0
    with pytest.raises(ValueError, match="bag_player.log"):
        bench.parse_player_log("playing bags/x.mcap")
