"""Edge statistics per camera and their fusion into the body fit (ALGORITHMS.md §2 "Fusion")."""

from __future__ import annotations

import numpy as np
import pytest

from artrack.body_model import load_body_model
from artrack.edge_fusion import EdgeStage, LinkEdgeStatistics, combine
from artrack.lie import exp_se3, inverse_se3, log_se3
from artrack.motion import pose_at
from artrack.skeleton import LinkGoals, fit_pose
from artrack.synth import Renderer, default_rig


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


def test_edges_of_four_views_pull_a_shifted_body_back(scene):
    """The body rendered at the true pose, the statistics of four views taken about a reference
    whose root is moved 3.6 cm: one fit to the edge goals alone (one linearisation, as the
    skeleton does per frame) moves the joints back toward the truth."""
    body, cams, renderer = scene
    theta = pose_at("default", 0.8, body)
    images = dict(zip([c.name for c in cams], renderer.render(theta, noise_sigma=2.0)))
    T = body.forward_kinematics(theta)
    stages = {c.name: EdgeStage(c, body) for c in cams}
    for c in cams:  # polarity colours learnt at the true pose (as at a trusted start)
        stages[c.name].tracker.learn_appearance({c.name: images[c.name]}, T)
    ref_theta = theta.copy()
    ref_theta[:3] += [0.03, -0.02, 0.0]
    stats = combine([stages[c.name].step(images[c.name], body.forward_kinematics(ref_theta)) for c in cams])
    assert stats.cameras == tuple(c.name for c in cams)
    goals = LinkGoals.from_edges(stats, sigma_px=1.0, min_found=8)
    assert {"torso", "head", "l_thigh", "r_thigh"} <= {body.link_names[i] for i in goals.links}
    fitted, _, _ = fit_pose(body, ref_theta, [], previous=ref_theta, previous_sigma=2.0, link_goals=goals,
                            robust_scale=3.0)
    before = np.linalg.norm(body.joint_positions(ref_theta) - body.joint_positions(theta), axis=1).mean()
    after = np.linalg.norm(body.joint_positions(fitted) - body.joint_positions(theta), axis=1).mean()
    assert after < 0.85 * before, (before, after)  # measured: 36 mm -> 28 mm


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
