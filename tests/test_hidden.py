"""Negative evidence (artrack.hidden): where a part that the silent cameras did not find can be."""

from __future__ import annotations

import numpy as np

from artrack.cameras import Camera
from artrack.hidden import hide
from artrack.projection import Capsule, project_priors, visible_points
from artrack.types import VISIBLE, Blob3D

K = np.array([[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]])
#: a trunk standing at the origin, 0.9-1.5 m high
TORSO = Capsule("torso", np.array([0.0, 0.0, 0.9]), np.array([0.0, 0.0, 1.5]), 0.15)
#: the one view that finds the hand looks along +y at x = -0.3 m, z = 1.2 m (behind the trunk's left)
SEEING = Camera.look_at("seeing", 1280, 720, K, [-0.3, -4.0, 1.2], [-0.3, 0.0, 1.2])
RAY = (SEEING.center, np.array([0.0, 1.0, 0.0]))
#: a view from +x that did not find it: the trunk hides the ray's points with |y| below ~0.16 m
SILENT = Camera.look_at("silent", 1280, 720, K, [4.0, 0.0, 1.2], [0.0, 0.0, 1.2])
COV = np.eye(3) * 0.2**2


def test_visible_points_agree_with_the_priors_visibility():
    rng = np.random.default_rng(4)
    points = np.vstack([rng.uniform([-6, -6, -1], [6, 6, 3], size=(300, 3)),
                        [[-0.3, 0.0, 1.2], [-0.3, 0.5, 1.2], [5.0, 0.0, 1.2]]])  # hidden, seen, behind
    for cam in (SEEING, SILENT):
        got = visible_points(cam, points, "r_hand", [TORSO])
        priors = project_priors([Blob3D("r_hand", p, np.eye(3) * 1e-4) for p in points], [cam], 0,
                                occluders=[TORSO], margin=0.0)[cam.name]
        np.testing.assert_array_equal(got, [p.visibility == VISIBLE for p in priors])
        assert 0 < got.sum() < len(points)
    assert visible_points(SILENT, points[-3:], "r_hand", [TORSO]).tolist() == [False, True, False]
    # a capsule of the part's own label never hides it; an inset border takes the image's edge away
    assert visible_points(SILENT, points[-3:-2], "torso", [TORSO]).tolist() == [True]
    edge = SILENT.rays(np.array([[2.0, 360.0]]))[1][0] * 4.0 + SILENT.center
    assert visible_points(SILENT, edge[None], "r_hand", []).tolist() == [True]
    assert visible_points(SILENT, edge[None], "r_hand", [], inset_px=10.0).tolist() == [False]


def test_a_one_view_prior_moves_along_its_ray_to_the_nearest_depth_the_silent_view_cannot_see():
    prior = np.array([-0.3, 0.5, 1.2])  # on the ray, in the silent view's sight
    x = hide("r_hand", prior, COV, [SILENT], [TORSO], ray=RAY)
    assert x is not None
    np.testing.assert_allclose(x[[0, 2]], [-0.3, 1.2], atol=1e-9)  # on the ray
    assert 0.05 < x[1] < 0.17  # the hidden stretch's near end (samples every 0.05 m)
    assert not visible_points(SILENT, x[None], "r_hand", [TORSO])[0]
    assert visible_points(SILENT, (x + [0.0, 0.05, 0.0])[None], "r_hand", [TORSO])[0]  # the next sample out
    # a prior off the ray is taken to its nearest point on the ray first
    np.testing.assert_allclose(hide("r_hand", prior + [0.0, 0.0, 0.2], COV, [SILENT], [TORSO], ray=RAY), x)


def test_the_prediction_is_kept_when_it_is_hidden_or_nothing_likelier_is():
    assert hide("r_hand", np.array([-0.3, 0.0, 1.2]), COV, [SILENT], [TORSO], ray=RAY) is None  # already hidden
    prior = np.array([-0.3, 0.5, 1.2])
    assert hide("r_hand", prior, COV, [SILENT], [], ray=RAY) is None  # nothing hides any point
    # a view that sees the whole ray (facing the seeing one): the point still hides from the other
    far = Camera.look_at("far", 1280, 720, K, [-0.3, 8.0, 1.2], [-0.3, 0.0, 1.2])
    np.testing.assert_allclose(hide("r_hand", prior, COV, [SILENT, far], [TORSO], ray=RAY),
                               hide("r_hand", prior, COV, [SILENT], [TORSO], ray=RAY))
    # a tracker that often misses a part in sight says little: the 1.75-sigma move to the hidden
    # stretch (-log density 1.5) is dearer than one view's -log 0.5 = 0.69, and not than -log 0.2
    assert hide("r_hand", prior, COV, [SILENT], [TORSO], ray=RAY, miss_probability=0.5) is None
    assert hide("r_hand", prior, COV, [SILENT], [TORSO], ray=RAY, miss_probability=0.2) is not None
    assert hide("r_hand", prior, COV, [], [TORSO], ray=RAY) is None  # no silent view
    assert hide("r_hand", prior, COV, [SILENT], [TORSO], ray=RAY, sigmas=1.0) is None  # out of 1 sigma (0.2 m)
    assert hide("r_hand", prior, COV, [SILENT], [TORSO], ray=RAY, reach=(prior, 0.2)) is None  # out of reach
    assert hide("r_hand", prior, COV, [SILENT], [TORSO], ray=RAY, reach=(prior, 0.4)) is not None


def test_a_part_no_view_found_moves_in_3d_to_a_point_no_silent_view_sees():
    prior = np.array([-0.3, 0.5, 1.2])
    x = hide("r_hand", prior, COV, [SILENT], [TORSO])
    assert x is not None and not visible_points(SILENT, x[None], "r_hand", [TORSO])[0]
    assert np.linalg.norm(x - prior) <= 0.6 + 1e-9  # within 3 sigma
    # the nearest hidden point lies at least as near as the ray's hidden stretch (0.35 m off)
    assert np.linalg.norm(x - prior) <= 0.35 + 0.15  # + the grid's step (6 sigma / 8)
    # two silent views on either side, whose shadows of the trunk do not meet outside it: a point
    # that one of them cannot see (the prediction is seen by both), never one inside the trunk
    other = Camera.look_at("other", 1280, 720, K, [-4.0, -1.0, 1.2], [0.0, 0.0, 1.2])
    x2 = hide("r_hand", prior, COV, [SILENT, other], [TORSO])
    assert x2 is not None and np.linalg.norm(x2[:2]) >= TORSO.radius
    assert sum(visible_points(c, x2[None], "r_hand", [TORSO])[0] for c in (SILENT, other)) == 1
    assert hide("r_hand", prior, COV, [SILENT, other], []) is None
