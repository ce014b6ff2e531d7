"""Tests of the loose-limbed body (ALGORITHMS.md §4): parts, potentials (EM, model file), BP, shouters,
likelihood and the annealed baseline. Seeded; small sizes so the module runs in seconds."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from artrack.annealed_filter import AnnealedParticleFilter, AnnealingConfig, _beta_for_survival
from artrack.body_model import load_body_model
from artrack.body_parts import PART_NAMES, SPATIAL_EDGES, joints_from_parts, part_geometry, parts_from_theta
from artrack.errors import InputError
from artrack.loose_limbed import (
    KernelMixture,
    LooseLimbedBP,
    LooseLimbedGraph,
    MapAssembler,
    MapConfig,
    NBPConfig,
    Particles,
    estimate_parts,
    message_from_particles,
    pairwise_rot_residual,
    product_sample,
)
from artrack.motion import pose_at
from artrack.part_likelihood import LikelihoodConfig, PartLikelihood, frame_evidence
from artrack.part_potentials import (
    compose,
    fit_pose_gmm,
    load_model,
    relative_pose,
    rot_residual,
    save_model,
    train_model,
)
from artrack.shouters import Shouter, hull_points
from artrack.synth import Renderer, default_rig


@pytest.fixture(scope="module")
def body():
    return load_body_model()


@pytest.fixture(scope="module")
def geo(body):
    return part_geometry(body)


@pytest.fixture(scope="module")
def model():
    return load_model()  # the committed config/loose_limbed_model.yaml


@pytest.fixture(scope="module")
def scene(body, geo):
    """One 320x240 4-view frame of the test motion, its evidence and true part poses."""
    cams = default_rig(4, 320, 240)
    r = Renderer(body, cams, seed=5)
    theta = pose_at("self_occlusion", 5.3, body)
    imgs = r.render(theta, noise_sigma=2.0, frame_index=0)
    views = frame_evidence(cams, {c.name: im for c, im in zip(cams, imgs)}, {c.name: r.background(c) for c in cams})
    pos, quat = parts_from_theta(body, geo, theta)
    return SimpleNamespace(views=views, theta=theta, pos=pos, quat=quat, joints=body.joint_positions(theta))


# ------------------------------------------------------------------ parts
def test_parts_geometry_and_joint_map(body, geo):
    assert geo.names == PART_NAMES and geo.n_parts == 10
    assert np.all(geo.r_end <= geo.r_start + 1e-12) and np.all(geo.r_end > 0)
    assert geo.length[PART_NAMES.index("l_thigh")] == pytest.approx(0.44)
    assert geo.length[PART_NAMES.index("torso")] == pytest.approx(0.52)
    thetas = np.stack([pose_at("default", t, body) for t in (0.5, 3.0, 6.0, 8.5)])
    pos, quat = parts_from_theta(body, geo, thetas)
    assert pos.shape == (4, 10, 3) and quat.shape == (4, 10, 4)
    err = np.linalg.norm(joints_from_parts(geo, pos, quat) - body.joint_positions(thetas), axis=-1)
    thorax = body.joint_names.index("thorax")
    assert np.all(np.delete(err, thorax, axis=1) < 1e-9)  # every joint but the thorax is exact
    assert np.all(err[:, thorax] < 0.05)  # the thorax: one torso cylinder for pelvis + torso links


# ------------------------------------------------------------------ potentials
def test_relative_pose_round_trip():
    rng = np.random.default_rng(0)
    pi, pj = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    qi, qj = Rotation.random(5, random_state=1).as_quat(), Rotation.random(5, random_state=2).as_quat()
    t, q = relative_pose(pi, qi, pj, qj)
    p2, q2 = compose(pi, qi, t, q)
    assert np.allclose(p2, pj)
    assert np.allclose(np.abs(np.sum(q2 * qj, axis=1)), 1.0)


def _two_cluster_data(n=600, seed=0):
    rng = np.random.default_rng(seed)
    half = n // 2
    t = np.vstack([rng.normal([0.0, 0.0, 0.3], 0.01, (half, 3)), rng.normal([0.2, 0.0, 0.1], 0.02, (half, 3))])
    rv = np.vstack([rng.normal([0.0, 0.0, 0.0], 0.05, (half, 3)), rng.normal([1.0, 0.0, 0.0], 0.1, (half, 3))])
    return t, Rotation.from_rotvec(rv).as_quat()


def test_em_recovers_two_clusters():
    t, q = _two_cluster_data()
    g, hist = fit_pose_gmm(t, q, n_components=2, var_floor=(1e-6, 1e-6), seed=0)
    assert all(b >= a - 1e-9 for a, b in zip(hist[1:], hist[2:]))  # EM never lowers the likelihood
    order = np.argsort(g.mean_t[:, 0])
    assert g.weights[order] == pytest.approx([0.5, 0.5], abs=0.02)
    assert g.mean_t[order] == pytest.approx(np.array([[0.0, 0.0, 0.3], [0.2, 0.0, 0.1]]), abs=0.005)
    rv = Rotation.from_quat(g.mean_q[order]).as_rotvec()
    assert rv == pytest.approx(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), abs=0.03)
    assert np.sqrt(g.var[order][:, 3]) == pytest.approx([0.05, 0.1], rel=0.2)
    # the learned density prefers held-in data to poses far away
    far_t, far_q = t + 0.3, q
    assert g.logpdf(t, q).mean() > g.logpdf(far_t, far_q).mean() + 10


def test_gmm_sample_matches_fit():
    t, q = _two_cluster_data(seed=1)
    g, _ = fit_pose_gmm(t, q, n_components=2, outlier_weight=0.0, var_floor=(1e-6, 1e-6), seed=0)
    ts, qs = g.sample(4000, np.random.default_rng(3))
    assert ts.mean(axis=0) == pytest.approx(t.mean(axis=0), abs=0.01)


def test_model_file_round_trip_and_errors(model, tmp_path):
    assert len(model.spatial) == 2 * len(SPATIAL_EDGES)
    assert set(model.next) == set(PART_NAMES) == set(model.prev)
    assert "self_occlusion" in model.provenance["not_in_training"]
    path = tmp_path / "m.yaml"
    save_model(model, path)
    again = load_model(path)
    g0, g1 = model.spatial[("torso", "head")], again.spatial[("torso", "head")]
    assert np.allclose(g0.mean_t, g1.mean_t, atol=1e-8) and np.allclose(g0.var, g1.var, atol=1e-8)
    path.write_text(path.read_text().replace("version: 1", "version: 7"))
    with pytest.raises(InputError, match="version"):
        load_model(path)
    with pytest.raises(InputError, match="cannot read"):
        load_model(tmp_path / "missing.yaml")


def test_learned_potentials_place_the_head_above_the_torso(model, body, geo):
    g = model.spatial[("torso", "head")]
    assert np.all(np.abs(g.mean_t[:, 2] - 0.52) < 0.03)  # neck at the top of the 0.52 m torso cylinder
    pos, quat = parts_from_theta(body, geo, pose_at("self_occlusion", 5.5, body))
    t, q = relative_pose(pos[:1], quat[:1], pos[1:2], quat[1:2])
    assert g.logpdf(t, q)[0] > g.logpdf(t + [0.0, 0.0, 0.2], q)[0] + 5


def test_spatial_only_sequences_widen_the_spatial_potentials_not_the_temporal_ones(body, geo):
    rest = body.rest_pose()
    still = np.tile(rest, (40, 1))  # arms hanging, a little sway
    still[:, 6:] += np.random.default_rng(0).normal(0.0, 0.02, (40, body.n_dof - 6))
    raised = still.copy()
    arm = body.link_names.index("l_upper_arm")
    start = 6 + sum(body.links[i].n_dof for i in range(1, arm))
    raised[:, start] = np.linspace(0.0, 2.5, 40)  # the left arm raised sideways, step by step
    base = train_model(body, geo, [still], 30.0)
    wide = train_model(body, geo, [still], 30.0, spatial_sequences=[raised])
    pos, quat = parts_from_theta(body, geo, raised[-1])
    t, q = relative_pose(pos[:1], quat[:1], pos[2:3], quat[2:3])  # the raised upper arm in the torso's frame
    ga, gb = base.spatial[("torso", "l_upper_arm")], wide.spatial[("torso", "l_upper_arm")]
    assert gb.logpdf(t, q)[0] > ga.logpdf(t, q)[0] + 5
    for part in PART_NAMES:  # the temporal potentials come from the motions alone
        assert np.allclose(base.next[part].mean_t, wide.next[part].mean_t)


# ------------------------------------------------------------------ BP machinery
def test_graph_sizes():
    g3 = LooseLimbedGraph(3)
    assert len(g3.nodes) == 30 and len(g3.edges) == 94
    assert len(LooseLimbedGraph(1).edges) == 18
    assert sorted(g3.in_nodes((1, 0))) == sorted([(1, 1), (1, 2), (1, 4), (1, 6), (1, 8), (0, 0), (2, 0)])


def test_pairwise_rot_residual_matches_scipy():
    a = Rotation.random(4, random_state=3).as_quat()
    b = Rotation.random(6, random_state=4).as_quat()
    ref = np.stack([rot_residual(a, np.tile(x, (4, 1))) for x in b])
    assert np.allclose(pairwise_rot_residual(a, b), ref, atol=1e-9)


def _single(pos, var, quat=(0.0, 0.0, 0.0, 1.0)):
    return KernelMixture(np.zeros(1), np.array([pos], float), np.array([quat], float), np.array([var], float))


def test_product_of_gaussians_by_gibbs():
    rng = np.random.default_rng(0)
    a = _single([0.0, 0.0, 0.0], [0.04] * 3 + [0.01] * 3)
    b = _single([0.2, 0.0, 0.0], [0.04] * 3 + [0.01] * 3, Rotation.from_rotvec([0.2, 0, 0]).as_quat())
    p, q = product_sample([a, b], 4000, rng)
    assert p.mean(axis=0) == pytest.approx([0.1, 0.0, 0.0], abs=0.01)
    assert p.var(axis=0) == pytest.approx([0.02] * 3, rel=0.1)
    assert Rotation.from_quat(q).as_rotvec().mean(axis=0) == pytest.approx([0.1, 0, 0], abs=0.01)


def test_gibbs_picks_the_agreeing_modes():
    rng = np.random.default_rng(1)
    var = [1e-3] * 3 + [1e-2] * 3
    m1 = KernelMixture(np.log([0.5, 0.5]), np.array([[0.0, 0, 0], [1.0, 0, 0]]), np.tile([0, 0, 0, 1.0], (2, 1)),
                       np.array([var, var]))
    m2 = KernelMixture(np.log([0.5, 0.5]), np.array([[1.0, 0, 0], [2.0, 0, 0]]), np.tile([0, 0, 0, 1.0], (2, 1)),
                       np.array([var, var]))
    m3 = KernelMixture(np.log([0.9, 0.1]), np.array([[-1.0, 0, 0], [1.0, 0, 0]]), np.tile([0, 0, 0, 1.0], (2, 1)),
                       np.array([[0.5] * 3 + [1e-2] * 3, var]))
    p, _ = product_sample([m1, m2, m3], 500, rng, n_sweeps=4)
    assert np.mean(np.abs(p[:, 0] - 1.0) < 0.1) > 0.9


def test_message_kernels_are_the_composed_components(model):
    rng = np.random.default_rng(0)
    parts = Particles.around(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.0, 1.0]), 5, 0.0, 0.0, rng)
    g = model.spatial[("torso", "head")]
    m = message_from_particles(parts, g, 5, rng)
    assert len(m) == 5 * (g.n_components + 1)
    assert np.allclose(m.pos[: g.n_components], np.array([0.0, 0.0, 1.0]) + g.mean_t)
    assert np.exp(m.logw).sum() == pytest.approx(1.0)


class _FakeLikelihood:
    """log φ = −|p − p_true|² / (2·0.03²) − |rotvec|² / (2·0.2²): evidence centred on the true parts."""

    def __init__(self, pos, quat):
        self.pos, self.quat = pos, quat

    def log_likelihood(self, part, pos, quat, views):
        d = np.sum((pos - self.pos[part]) ** 2, axis=1)
        r = rot_residual(np.tile(self.quat[part], (len(pos), 1)), quat)
        return -d / (2 * 0.03**2) - np.sum(r * r, axis=1) / (2 * 0.2**2)


def test_bp_initialises_from_noisy_shouters(model, body, geo):
    pos, quat = parts_from_theta(body, geo, pose_at("self_occlusion", 5.6, body))
    rng = np.random.default_rng(2)
    shouts = {}
    for p in (1, 3, 5, 7, 9):  # head, forearms, shins: the truth among 3 decoys 0.5 m away
        cand_p = np.vstack([pos[p], pos[p] + rng.normal(0, 0.5, (3, 3))])
        cand_q = np.vstack([quat[p], Rotation.random(3, random_state=p).as_quat()])
        shouts[p] = KernelMixture(np.full(4, -np.log(4)), cand_p, cand_q, np.tile([0.03**2] * 3 + [0.1] * 3, (4, 1)))
    bp = LooseLimbedBP(model, geo, _FakeLikelihood(pos, quat), NBPConfig(n_particles=60, n_exclusive=30,
                                                                          n_message=20), seed=0)
    errors = []

    def cb(it, beliefs):
        est, _ = estimate_parts(beliefs, 0)
        errors.append(np.nanmean(np.linalg.norm(est - pos, axis=1)))

    res = bp.run(LooseLimbedGraph(1), [[]], 5, [shouts], callback=cb)
    assert len(res.beliefs) == 10  # every part found, the unshouted ones through the messages
    assert errors[-1] < 0.06


class _MovingLikelihood(_FakeLikelihood):
    """Like _FakeLikelihood, the true parts moving +2 cm in x per frame; ``views`` = [frame index]."""

    def log_likelihood(self, part, pos, quat, views):
        shift = np.array([0.02 * views[0], 0.0, 0.0])
        return super().log_likelihood(part, pos - shift, quat, views)


def test_three_frame_window_finds_every_node_through_time(model, body, geo):
    pos, quat = parts_from_theta(body, geo, pose_at("self_occlusion", 5.6, body))
    shouts = [{}, {p: KernelMixture(np.zeros(1), pos[p:p + 1] + [0.02, 0, 0], quat[p:p + 1],
                                     np.array([[0.02**2] * 3 + [0.05] * 3])) for p in range(10)}, {}]
    bp = LooseLimbedBP(model, geo, _MovingLikelihood(pos, quat), NBPConfig(n_particles=40, n_exclusive=20,
                                                                            n_message=15), seed=1)
    res = bp.run(LooseLimbedGraph(3), [[0], [1], [2]], 3, shouts)
    assert len(res.beliefs) == 30  # frames 0 and 2 (no shouters) found through the temporal edges
    for f in range(3):
        est, _ = estimate_parts(res.beliefs, f)
        assert np.mean(np.linalg.norm(est - (pos + [0.02 * f, 0, 0]), axis=1)) < 0.06


def test_tracker_follows_a_moving_body_and_reports_the_map_estimate(model, body, geo):
    from artrack.loose_limbed import LooseLimbedTracker, TrackerConfig

    pos, quat = parts_from_theta(body, geo, pose_at("self_occlusion", 5.6, body))
    bp = LooseLimbedBP(model, geo, _MovingLikelihood(pos, quat), NBPConfig(n_particles=40, n_exclusive=20,
                                                                            n_message=15), seed=2)
    tracker = LooseLimbedTracker(bp, None, TrackerConfig(track_iterations=2, use_shouters=False))
    tracker.start_at(pos, quat)
    for k in range(1, 6):
        joints = tracker.step([k])
    est_p, est_q = tracker.parts  # the estimate reported is the joint MAP (TrackerConfig.map)
    assert np.allclose(joints, joints_from_parts(geo, est_p, est_q)) and tracker.map_seconds > 0
    truth = joints_from_parts(geo, pos + [0.1, 0, 0], quat)
    assert np.mean(np.linalg.norm(joints - truth, axis=1)) < 0.05


def _joint_score(bp, pos, quat):
    """Σ log φ + Σ log ψ (parent -> child) of one configuration, as MapAssembler maximises it."""
    idx = {n: k for k, n in enumerate(PART_NAMES)}
    total = sum(float(bp.unary(p, pos[p:p + 1], quat[p:p + 1], [])[0]) for p in range(10))
    for a, b in SPATIAL_EDGES:
        i, j = idx[a], idx[b]
        total += float(bp.spatial_log_potential(i, j, pos[i:i + 1], quat[i:i + 1], pos[j:j + 1], quat[j:j + 1])[0])
    return total


def test_map_assembly_is_the_exact_maximum_over_the_candidates(model, body, geo):
    """Two candidates per part (the truth and a decoy 8 cm / 0.4 rad off): the dynamic programme's body
    scores as the best of all 2^10 combinations, found by enumeration."""
    import itertools

    pos, quat = parts_from_theta(body, geo, pose_at("self_occlusion", 5.6, body))
    rng = np.random.default_rng(4)
    decoy_p = pos + rng.normal(0.0, 0.08, pos.shape)
    decoy_q = (Rotation.from_quat(quat) * Rotation.from_rotvec(rng.normal(0.0, 0.4, (10, 3)))).as_quat()
    # evidence on the decoys of half the parts: likelihood and potentials disagree, the choice is not trivial
    on_decoy = (np.arange(10) % 2 == 0)[:, None]

    class Sharp(_FakeLikelihood):  # 3x sharper evidence, so that it can outweigh a potential
        def log_likelihood(self, part, p, q, views):
            return 3.0 * super().log_likelihood(part, p, q, views)

    bp = LooseLimbedBP(model, geo, Sharp(np.where(on_decoy, decoy_p, pos), np.where(on_decoy, decoy_q, quat)),
                       NBPConfig(), seed=0)
    asm = MapAssembler(bp, MapConfig(refine_rounds=0))
    beliefs = {(0, p): Particles(np.stack([pos[p], decoy_p[p]]), np.stack([quat[p], decoy_q[p]]), np.log([0.5, 0.5]))
               for p in range(10)}
    asm.add(beliefs, 0, [])
    est_p, est_q, score = asm.estimate([])
    best = max(itertools.product((0, 1), repeat=10), key=lambda c: _joint_score(
        bp, np.where(np.array(c)[:, None] == 0, pos, decoy_p), np.where(np.array(c)[:, None] == 0, quat, decoy_q)))
    pick = np.array(best)[:, None] == 0
    assert np.allclose(est_p, np.where(pick, pos, decoy_p)) and np.allclose(est_q, np.where(pick, quat, decoy_q))
    assert score == pytest.approx(_joint_score(bp, est_p, est_q))
    assert 0 < int(np.sum(pick)) < 10  # both kinds of candidate were chosen somewhere


def test_map_refinement_raises_the_score_and_candidates_keep_the_best(model, body, geo):
    pos, quat = parts_from_theta(body, geo, pose_at("self_occlusion", 5.6, body))
    bp = LooseLimbedBP(model, geo, _FakeLikelihood(pos, quat), NBPConfig(), seed=1)
    rng = np.random.default_rng(5)
    beliefs = {(0, p): Particles.around(pos[p] + [0.04, 0.0, 0.0], quat[p], 30, 0.02, 0.1, rng) for p in range(10)}
    plain = MapAssembler(bp, MapConfig(refine_rounds=0, candidates=20))
    refined = MapAssembler(bp, MapConfig(refine_rounds=3, candidates=20))
    for asm in (plain, refined):
        asm.add(beliefs, 0, [])
        assert all(len(c) == 20 for c in asm.score)
        assert all(np.min(c) >= np.sort(bp.unary(p, beliefs[(0, p)].pos, beliefs[(0, p)].quat, []))[-20] - 1e-9
                   for p, c in enumerate(asm.score))  # the 20 best by log φ were kept
    p0, q0, s0 = plain.estimate([])
    p1, q1, s1 = refined.estimate([])
    assert s1 > s0 and s1 == pytest.approx(_joint_score(bp, p1, q1))
    assert np.mean(np.linalg.norm(p1 - pos, axis=1)) < np.mean(np.linalg.norm(p0 - pos, axis=1))
    again = refined.estimate([])  # a function of the candidates: the same answer on every call
    assert np.array_equal(again[0], p1) and again[2] == s1


# ------------------------------------------------------------------ images
def test_face_tells_a_person_facing_the_cameras_from_one_turned_away(geo, scene):
    """Silhouette and edges score a head turned about its axis the same; the face term (skin in front,
    hair behind) does not: the mirrored body (left and right swapped) fits the same outline."""
    head = PART_NAMES.index("head")
    turned = np.stack([scene.quat[head]] + [(Rotation.from_quat(scene.quat[head])
                                             * Rotation.from_rotvec([0.0, 0.0, a])).as_quat() for a in (np.pi, 1.5)])
    where = np.tile(scene.pos[head], (3, 1))
    with_face = PartLikelihood(geo).log_likelihood(head, where, turned, scene.views)
    without = PartLikelihood(geo, LikelihoodConfig(w_face=0.0)).log_likelihood(head, where, turned, scene.views)
    assert np.ptp(without) < 0.3
    assert with_face[0] > with_face[1] + 3.0 and with_face[0] > with_face[2] + 1.0
    assert all(v.skin is not None and v.skin.min() >= 0.0 and v.skin.max() <= 1.0 for v in scene.views)


def test_likelihood_prefers_the_true_pose(geo, scene):
    """Shifts across a part's axis (10 cm) lower its likelihood; the torso is also held along its axis."""
    lik = PartLikelihood(geo)
    wins = 0
    for p in range(10):
        lt = lik.log_likelihood(p, scene.pos[p:p + 1], scene.quat[p:p + 1], scene.views)[0]
        axis = Rotation.from_quat(scene.quat[p]).apply(geo.axis[p])
        a = np.cross(axis, [1.0, 0.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(axis, a)
        shifted = scene.pos[p] + 0.1 * np.array([a, -a, b, -b])
        ls = lik.log_likelihood(p, shifted, np.tile(scene.quat[p], (4, 1)), scene.views)
        wins += int(lt > ls.max())
    assert wins >= 8
    torso = [scene.pos[0] + [0.0, 0.0, dz] for dz in (-0.2, 0.2)]
    lt = lik.log_likelihood(0, scene.pos[:1], scene.quat[:1], scene.views)[0]
    assert np.all(lik.log_likelihood(0, np.array(torso), np.tile(scene.quat[0], (2, 1)), scene.views) < lt - 3)
    for v in scene.views:
        assert v.fg.min() >= 0 and v.fg.max() <= 1 and v.edge.max() <= 1


def test_hull_points_lie_on_the_body(scene):
    hull = hull_points(scene.views, np.random.default_rng(0))
    assert len(hull) > 100
    d = np.min(np.linalg.norm(hull[:, None] - scene.joints[None], axis=2), axis=1)
    assert np.median(d) < 0.2


def test_shouter_finds_the_head(geo, scene):
    sh = Shouter(geo, PartLikelihood(geo), seed=0)
    shouts = sh.shout(scene.views)
    head = PART_NAMES.index("head")
    assert head in shouts and np.min(np.linalg.norm(shouts[head].pos - scene.pos[head], axis=1)) < 0.15
    assert shouts[PART_NAMES.index("l_shin")] is shouts[PART_NAMES.index("r_shin")]  # no left/right


# ------------------------------------------------------------------ annealed baseline
def test_beta_for_survival():
    ll = np.random.default_rng(0).normal(0, 5, 200)
    beta = _beta_for_survival(ll, 0.5)
    w = np.exp(beta * ll - np.max(beta * ll))
    w /= w.sum()
    assert 1.0 / np.sum(w**2) == pytest.approx(100, rel=0.05)


def test_annealed_filter_moves_towards_the_evidence(body, geo):
    target = body.rest_pose()
    target[:3] += [0.1, -0.05, 0.0]

    class Fake(AnnealedParticleFilter):
        def log_likelihood(self, theta, views):
            return -np.sum((theta[:, :6] - target[:6]) ** 2, axis=1) / (2 * 0.02**2)

    apf = Fake(body, geo, PartLikelihood(geo, LikelihoodConfig()), AnnealingConfig(n_layers=5, n_particles=100), 0)
    apf.start_at(body.rest_pose())
    for _ in range(3):
        est = apf.step([])
    assert np.linalg.norm(est[:3] - target[:3]) < 0.03


def test_stage_seeds_the_background_then_finds_the_body(body, model):
    from artrack.loose_limbed_stage import LooseLimbedStage, StageConfig
    from artrack.types import STATUS_INITIALIZING, STATUS_TRACKING

    cams = default_rig(4, 320, 240)
    r = Renderer(body, cams, seed=7)
    stage = LooseLimbedStage(body, cams, model, StageConfig(init_iterations=3, track_iterations=1, n_particles=30,
                                                            background_seed_frames=3, background_seed_stride=1))
    empty = r.render(None, noise_sigma=2.0)
    for k in range(3):  # seeding, then (k = 2) an empty room: nothing found
        assert stage.step(k, {c.name: im for c, im in zip(cams, empty)}) is None
    theta = pose_at("self_occlusion", 5.2, body)
    frame = {c.name: im for c, im in zip(cams, r.render(theta, noise_sigma=2.0, frame_index=3))}
    est = stage.step(3, frame)
    assert est.status == STATUS_INITIALIZING and est.joints.shape == (15, 3) and len(est.links) == 10
    assert np.all(np.isfinite(est.joints))
    # the body is found in the room, near the truth (the tight figure is the bench's job)
    assert np.linalg.norm(est.joints[0] - body.joint_positions(theta)[0]) < 0.5
    assert stage.step(4, frame).status == STATUS_TRACKING
    stage.reinitialise()
    assert stage.step(5, frame).status == STATUS_INITIALIZING
    with pytest.raises(InputError, match="cam02"):
        stage.step(6, {"cam01": frame["cam01"]})


class _PolicyStage:
    """Records what an InitialiserPolicy asks of the stage; finds nothing on frame 1."""

    ready = True

    def __init__(self):
        self.calls = []

    def reinitialise(self):
        self.calls.append("reinit")

    def step(self, stamp, images):
        self.calls.append(stamp)
        return None if stamp == 1 else stamp

    def step_background(self, images):
        self.calls.append("bg")


@pytest.mark.parametrize("start", [False, True])
def test_initialiser_policy_infers_at_start_and_while_the_skeleton_is_lost(start):
    """InitialiserPolicy (the loose_limbed node's mode=initialiser): infers until its first estimate,
    then only after the skeleton's last body was LOST, re-initialising on the first such frame; with
    ``start`` also while the skeleton has not started (tracking the body found: a TRACKING body is what
    starts the skeleton)."""
    from artrack.loose_limbed_stage import InitialiserPolicy
    from artrack.types import STATUS_INITIALIZING, STATUS_LOST, STATUS_TRACKING

    stage, policy = _PolicyStage(), InitialiserPolicy(start=start)
    assert policy.infer() and policy.step(stage, 1, {}) is None  # nothing found yet: still initialising
    policy.skeleton(STATUS_INITIALIZING)
    assert policy.step(stage, 2, {}) == 2 and stage.calls == ["reinit", 1, "reinit", 2]
    assert not policy.skeleton(STATUS_INITIALIZING)
    if start:  # the skeleton has not started: track on, no re-initialisation
        assert policy.infer() and policy.step(stage, 3, {}) == 3 and stage.calls[-2:] == [2, 3]
    else:  # the skeleton starts from its own blobs
        assert not policy.infer() and policy.step(stage, 3, {}) is None and stage.calls[-1] == 2
    assert not policy.skeleton(STATUS_TRACKING) and not policy.infer() and policy.step(stage, 4, {}) is None
    assert policy.skeleton(STATUS_LOST)  # newly lost: say so once
    assert policy.infer() and policy.step(stage, 5, {}) == 5 and stage.calls[-2:] == ["reinit", 5]
    assert not policy.skeleton(STATUS_LOST) and policy.step(stage, 6, {}) == 6 and stage.calls[-1] == 6  # tracks on
    policy.skeleton(STATUS_TRACKING)
    assert not policy.infer()
    assert InitialiserPolicy(estimator=True).infer()


def test_tracker_detects_loss_and_recovers_from_the_shouters(model, body, geo):
    from artrack.loose_limbed import LooseLimbedTracker, TrackerConfig

    pos, quat = parts_from_theta(body, geo, pose_at("self_occlusion", 5.6, body))

    class FakeShouter:  # proposes the moving truth (and a decoy) for the shouted parts
        def shout(self, views):
            shift = np.array([0.02 * views[0], 0.0, 0.0])
            return {p: KernelMixture(np.log([0.7, 0.3]), np.vstack([pos[p] + shift, pos[p] + [0.0, 0.8, 0.0]]),
                                     np.vstack([quat[p], quat[p]]), np.tile([0.02**2] * 3 + [0.05] * 3, (2, 1)))
                    for p in (0, 1, 3, 5, 7, 9)}

    bp = LooseLimbedBP(model, geo, _MovingLikelihood(pos, quat), NBPConfig(n_particles=40, n_exclusive=20,
                                                                            n_message=15), seed=3)
    tracker = LooseLimbedTracker(bp, FakeShouter(), TrackerConfig(init_iterations=4, track_iterations=2,
                                                                  use_shouters=False, lost_score=-50.0))
    tracker.start_at(pos, quat)
    tracker.step([1])
    assert not tracker.lost
    for b in tracker.previous.values():  # corrupt the belief: 0.6 m off
        b.pos = b.pos + [0.6, 0.0, 0.0]
    tracker.step([2])
    assert tracker.lost and tracker.previous is None  # the likelihood of the estimate gave it away
    joints = tracker.step([3])  # found again from no prior pose
    truth = joints_from_parts(geo, pos + [0.06, 0, 0], quat)
    assert np.mean(np.linalg.norm(joints - truth, axis=1)) < 0.08 and not tracker.lost
