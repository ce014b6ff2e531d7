"""Edge statistics per camera and their fusion into the body fit (ALGORITHMS.md §2 "Fusion")."""

from __future__ import annotations

import numpy as np
import pytest

from artrack.body_fit import LinkGoals, fit_pose
from artrack.body_model import load_body_model
from artrack.edge_fusion import EdgeStage, LinkEdgeStatistics, combine
from artrack.edge_tracker import EdgeTrackerConfig
from artrack.errors import InputError
from artrack.lie import exp_se3, inverse_se3, log_se3
from artrack.motion import pose_at
from artrack.pipeline import ClosedLoopPipeline, load_pipeline_config
from artrack.synth import Renderer, default_rig
from artrack.types import STATUS_LOST, STATUS_TRACKING


@pytest.fixture(scope="module")
def scene():
    body = load_body_model()
    cams = default_rig(4, 320, 240)
    return body, cams, Renderer(body, cams, seed=1)


def _stats(n: int, seed: int, ref: np.ndarray) -> LinkEdgeStatistics:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, 6, 6))
    C = A @ np.swapaxes(A, 1, 2)
    return LinkEdgeStatistics(ref, C, rng.normal(size=(n, 6)), rng.integers(0, 50, n), (f"c{seed}",))


def test_combine_sums_information_and_refuses_different_references():
    ref = np.tile(np.eye(4), (3, 1, 1))
    a, b = _stats(3, 1, ref), _stats(3, 2, ref)
    c = combine([a, None, b])
    np.testing.assert_allclose(c.information, a.information + b.information)
    np.testing.assert_allclose(c.information_vector, a.information_vector + b.information_vector)
    assert c.cameras == ("c1", "c2") and combine([]) is None
    moved = ref.copy()
    moved[0, 0, 3] = 0.1
    with pytest.raises(ValueError, match="different reference"):
        combine([a, _stats(3, 3, moved)])


def test_fit_to_link_goals_alone_recovers_the_pose():
    """Exact link poses as goals (identity information, no blobs): the fit returns the pose."""
    body = load_body_model()
    theta = pose_at("default", 1.2, body)
    T = body.forward_kinematics(theta)
    links = np.arange(len(body.links))
    ref = T @ exp_se3(np.tile([0.01, -0.02, 0.0, 0.0, 0.05, 0.0], (len(links), 1)))  # a nearby reference
    xi = log_se3(inverse_se3(ref) @ T)
    goals = LinkGoals(links, inverse_se3(ref), xi, np.tile(np.eye(6) * 100.0, (len(links), 1, 1)))
    start = pose_at("default", 1.0, body)
    fitted, _, _ = fit_pose(body, start, [], max_nfev=100, link_goals=goals)
    err = np.linalg.norm(body.joint_positions(fitted) - body.joint_positions(theta), axis=1).max()
    assert err < 2e-3, err


def _four_view_fit(scene, shift_m, config=None) -> tuple[float, float]:
    """The body rendered at the true pose, the statistics of four views taken about a reference
    whose root is moved by ``shift_m``, then one fit to the edge goals alone (as the skeleton does
    per frame): the mean joint error (m) before and after."""
    body, cams, renderer = scene
    theta = pose_at("default", 0.8, body)
    images = dict(zip([c.name for c in cams], renderer.render(theta, noise_sigma=2.0)))
    T = body.forward_kinematics(theta)
    stages = {c.name: EdgeStage(c, body, config) for c in cams}
    for c in cams:  # polarity colours learnt at the true pose (as at a trusted start)
        stages[c.name].tracker.learn_appearance({c.name: images[c.name]}, T)
    ref_theta = theta.copy()
    ref_theta[:3] += shift_m
    stats = combine([stages[c.name].step(images[c.name], body.forward_kinematics(ref_theta)) for c in cams])
    assert stats.cameras == tuple(c.name for c in cams)
    goals = LinkGoals.from_edges(stats, sigma_px=1.0, min_found=8)
    assert {"torso", "head", "l_thigh", "r_thigh"} <= {body.link_names[i] for i in goals.links}
    fitted, _, _ = fit_pose(body, ref_theta, [], previous=ref_theta, previous_sigma=2.0, link_goals=goals,
                            robust_scale=3.0)
    before = np.linalg.norm(body.joint_positions(ref_theta) - body.joint_positions(theta), axis=1).mean()
    after = np.linalg.norm(body.joint_positions(fitted) - body.joint_positions(theta), axis=1).mean()
    return before, after


def test_edges_of_four_views_pull_a_shifted_body_back(scene):
    """A 3.6 cm shift: the edges move the joints back toward the truth."""
    before, after = _four_view_fit(scene, [0.03, -0.02, 0.0])
    assert after < 0.85 * before, (before, after)  # measured: 36 mm -> 26 mm


def test_iterated_statistics_follow_a_larger_motion_than_one_linearisation(scene):
    """A 9.4 cm shift, about the search range: the stage's statistics from three cycles of the
    edge tracker in each view (the default) take the fit much nearer the truth than those after
    one cycle."""
    shift = [0.08, -0.05, 0.0]
    before, one = _four_view_fit(scene, shift, EdgeTrackerConfig(iterations=1))
    _, three = _four_view_fit(scene, shift, EdgeTrackerConfig(iterations=3))
    assert three < 0.7 * one < 0.7 * before, (before, one, three)  # measured: 94 -> 83 (1), 42 mm (3)


def test_stage_learns_its_colours_again_when_a_new_track_starts(scene):
    """The appearance is learnt again at the first reference after the body's status becomes
    TRACKING from another status (the skeleton was re-initialised), and after relearn()."""
    body, cams, renderer = scene
    theta = pose_at("default", 0.8, body)
    img = renderer.render(theta, noise_sigma=2.0)[0]
    T = body.forward_kinematics(theta)
    stage = EdgeStage(cams[0], body, EdgeTrackerConfig(warmup_frames=0))
    stage.step(img, T, STATUS_TRACKING)
    first = stage.tracker.appearance
    stage.step(img, T, STATUS_TRACKING)
    assert stage.tracker.appearance is first  # same track: kept
    stage.step(img, T, STATUS_LOST)
    assert stage.tracker.appearance is first
    stage.step(img, T, STATUS_TRACKING)
    second = stage.tracker.appearance
    assert second is not None and second is not first
    stage.relearn()
    stage.step(img, T)
    assert stage.tracker.appearance is not None and stage.tracker.appearance is not second


def test_stage_waits_out_a_new_tracks_warm_up(scene):
    """warmup_frames = 3: the first three TRACKING references of a track give no statistics and
    learn no colours; the fourth learns them there and is measured. A reference of a body not
    TRACKING gives none, and the next track waits again; after relearn() (a trusted pose) the
    next reference is used at once."""
    body, cams, renderer = scene
    theta = pose_at("default", 0.8, body)
    img = renderer.render(theta, noise_sigma=2.0)[0]
    T = body.forward_kinematics(theta)
    stage = EdgeStage(cams[0], body, EdgeTrackerConfig(warmup_frames=3))
    for _ in range(3):
        assert stage.step(img, T, STATUS_TRACKING) is None
        assert stage.tracker.appearance is None
    stats = stage.step(img, T, STATUS_TRACKING)
    assert stats is not None and stats.measured.any() and stage.tracker.appearance is not None
    assert stage.step(img, T, STATUS_LOST) is None and stage.tracker.appearance is None
    assert [stage.step(img, T, STATUS_TRACKING) is None for _ in range(4)] == [True, True, True, False]
    stage.step(img, T, STATUS_LOST)
    stage.relearn()
    assert stage.step(img, T, STATUS_TRACKING) is not None and stage.tracker.appearance is not None
    with pytest.raises(ValueError, match="warmup_frames"):
        EdgeTrackerConfig(warmup_frames=-1)


def test_single_view_stage_learns_colours_with_unseen_links(scene):
    """One camera: links it cannot see get no colour model (no crash); their information is zero."""
    body, cams, renderer = scene
    theta = pose_at("default", 0.8, body)
    img = renderer.render(theta, noise_sigma=2.0)[0]
    T = body.forward_kinematics(theta)
    stage = EdgeStage(cams[0], body)
    stats = stage.step(img, T)
    assert stats.measured.any()
    assert np.all(stats.information[~stats.measured] == 0)
    assert np.all(np.isfinite(stats.information)) and np.all(np.isfinite(stats.information_vector))


def test_pipeline_restart_starts_a_track_from_the_given_body(scene):
    """ClosedLoopPipeline.restart (the benches' correct-start protocol): from the true joints,
    before any frame, the loop tracks from its first frame with blobs + edges, the edge stages
    having learnt their appearance at the restart's prediction, and predicts the next frame near
    it; bad joints change nothing."""
    body, cams, renderer = scene
    pipe = ClosedLoopPipeline(body, cams, load_pipeline_config(edges=True))
    stamp0, dt = 1_000_000_000, 1e9 / 30
    pipe.restart(stamp0, body.joint_positions(pose_at("default", 1.0, body)))
    assert pipe.reference is not None and pipe.reference_status == STATUS_TRACKING
    assert all(len(p) > 0 for p in pipe.priors.values())
    theta = pose_at("default", 1.0, body)
    images = dict(zip([c.name for c in cams], renderer.render(theta, noise_sigma=2.0)))
    res = pipe.step(stamp0, images)
    assert res.estimate.status == STATUS_TRACKING
    assert all(st.tracker.appearance is not None for st in pipe.edge_stages.values())
    error = np.linalg.norm(res.estimate.joints - body.joint_positions(theta), axis=1).mean()
    assert error < 0.04, error  # measured: 3 mm (19 mm before stop 71; the blob stages have no background yet)
    # the track starts at the frame's own stamp, so the frame's update follows no time step: at
    # stamp - 1 (before stop 71) the 1-ns step made the joint velocities ~1e8 rad/s and the
    # prediction for the next frame flew to the joint limits
    following = body.joint_positions(pose_at("default", 1.0 + dt * 1e-9, body))
    moved = np.linalg.norm(res.prediction.joints - following, axis=1).mean()
    assert moved < 0.05, moved  # measured: 35 mm (the walk moves the joints ~40 mm a frame); 14.9 m before
    before = pipe.skeleton.estimator.theta.copy()
    with pytest.raises(InputError, match="reseed joints"):
        pipe.restart(stamp0 + round(5 * dt), np.zeros((3, 3)))
    np.testing.assert_array_equal(pipe.skeleton.estimator.theta, before)  # nothing reset
