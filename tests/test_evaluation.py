"""Evaluation: stamp matching, MPJPE, joints CSV, truth loading, report, plot."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from artrack.bags import write_scene_bag
from artrack.cameras import Camera
from artrack.errors import BagError, InputError
from artrack.evaluation import (
    compare_paired,
    evaluate,
    format_report,
    label_confusion,
    load_truth,
    match_by_stamp,
    mpjpe,
    plot_error_over_time,
    read_joints_csv,
    write_joints_csv,
)

NAMES = ["pelvis", "thorax", "head"]
T0 = 1_700_000_000_000_000_000


def test_match_by_stamp():
    truth = np.array([T0, T0 + 100, T0 + 200, T0 + 300])
    pred = np.array([T0 + 201, T0 + 2, T0 + 98, T0 + 104, T0 + 500])
    pi, ti = match_by_stamp(pred, truth, tol_ns=5)
    # T0+98 and T0+104 both want T0+100: the nearer (98) wins; T0+500 is out of tolerance
    assert ti.tolist() == [0, 1, 2]
    assert pi.tolist() == [1, 2, 0]
    pi, ti = match_by_stamp(pred, truth[::-1], tol_ns=5)  # unsorted truth: indices into the input
    assert truth[::-1][ti].tolist() == [T0, T0 + 100, T0 + 200]
    assert match_by_stamp([], truth, 5)[0].size == 0


def test_mpjpe_known_values():
    truth = np.zeros((2, 3, 3))
    pred = truth.copy()
    pred[0, 0] = [0.003, 0.004, 0.0]  # 5 mm
    pred[1, 2] = [0.0, 0.0, 0.012]  # 12 mm
    overall, per_joint, per_frame = mpjpe(pred, truth)
    assert overall == pytest.approx(17 / 6)
    np.testing.assert_allclose(per_joint, [2.5, 0.0, 6.0])
    np.testing.assert_allclose(per_frame, [5 / 3, 4.0])
    pred[1, 1] = np.nan  # a missing joint is left out
    overall, per_joint, per_frame = mpjpe(pred, truth)
    np.testing.assert_allclose(per_frame, [5 / 3, 6.0])
    assert per_joint[1] == 0.0 and overall == pytest.approx(17 / 5)
    with pytest.raises(ValueError, match=r"\(T, J, 3\)"):
        mpjpe(pred[:, :2], truth)


def test_evaluate_and_report():
    rng = np.random.default_rng(0)
    stamps = T0 + np.arange(10) * 33_333_333
    truth_j = rng.normal(size=(10, 3, 3))
    # prediction: joints in another order plus an extra one, stamps jittered by 1 ms, one frame missing
    order = [2, 0, 1]
    pred_j = np.concatenate([truth_j[:, order], np.zeros((10, 1, 3))], axis=1) + 0.010 / np.sqrt(3)
    keep = np.arange(10) != 4
    pred = (stamps[keep] + 1_000_000, [NAMES[i] for i in order] + ["extra"], pred_j[keep])
    res = evaluate(pred, (stamps, NAMES, truth_j), tolerance_ns=5_000_000)
    assert res.n_matched == 9 and res.n_pred == 9 and res.n_truth == 10
    assert res.overall_mm == pytest.approx(10.0)
    np.testing.assert_allclose(res.per_joint_mm, 10.0)
    np.testing.assert_array_equal(res.stamps_ns, stamps[keep])
    text = format_report(res)
    lines = text.splitlines()
    assert lines[-1] == "MPJPE 10.0 mm"
    assert lines[0].split() == ["joint", "MPJPE", "(mm)"]
    assert [ln.split()[0] for ln in lines[1:4]] == NAMES
    assert "frames matched: 9" in text
    with pytest.raises(InputError, match="no predicted frame is within 0.5 ms"):
        evaluate(pred, (stamps, NAMES, truth_j), tolerance_ns=500_000)
    with pytest.raises(InputError, match="prediction has no joint 'head'"):
        evaluate((stamps, NAMES[:2], truth_j[:, :2]), (stamps, NAMES, truth_j))


def test_joints_csv_round_trip_and_errors(tmp_path):
    rng = np.random.default_rng(1)
    stamps = T0 + np.arange(4) * 16_666_667
    joints = rng.normal(size=(4, 3, 3))
    joints[2, 1] = np.nan
    path = tmp_path / "out" / "joints.csv"
    write_joints_csv(path, stamps, NAMES, joints)
    text = path.read_text().splitlines()
    assert text[0] == "frame,stamp,joint,x,y,z"
    assert text[1].startswith(f"0,{T0},pelvis,")
    back = read_joints_csv(path)
    np.testing.assert_array_equal(back.stamps, stamps)
    assert back.joint_names == NAMES
    np.testing.assert_array_equal(back.joints, joints)  # exact, NaN included
    assert load_truth(path).joint_names == NAMES
    assert [p.name for p in path.parent.iterdir()] == ["joints.csv"]

    def bad(body: str, match: str) -> None:
        f = tmp_path / "bad.csv"
        f.write_text(body)
        with pytest.raises(InputError, match=match):
            read_joints_csv(f)

    bad("frame,stamp,joint,x,y\n", r"bad.csv: no column 'z'")
    bad("frame,stamp,joint,x,y,z\n0,5,pelvis,1,2,oops\n", r"bad.csv: line 2 column 'z' is not a number")
    bad("frame,stamp,joint,x,y,z\n0,5,pelvis,1,2,3\n0,6,head,1,2,3\n", r"line 3 column 'stamp'")
    bad("frame,stamp,joint,x,y,z\n0,5,a,1,2,3\n0,5,b,1,2,3\n1,6,a,1,2,3\n", "frame 1 has no row for joint")
    bad("", "bad.csv: empty file")
    bad("frame,stamp,joint,x,y,z\n", "bad.csv: no rows")
    with pytest.raises(InputError, match="not found"):
        read_joints_csv(tmp_path / "none.csv")
    f = tmp_path / "sci.csv"
    f.write_text("frame,stamp,joint,x,y,z\n0,1.7e18,a,1,2,3\n")
    assert read_joints_csv(f).stamps[0] == 1_700_000_000_000_000_000


def test_load_truth_from_bag(tmp_path):
    K = np.array([[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]])
    cam = Camera.look_at("cam01", 32, 24, K, [3, 0, 1], [0, 0, 1])
    rng = np.random.default_rng(2)
    frames = [
        SimpleNamespace(stamp_ns=T0 + i, images={"cam01": np.zeros((24, 32, 3), np.uint8)},
                        joints=rng.normal(size=(3, 3)))
        for i in range(3)
    ]
    write_scene_bag(tmp_path / "s.mcap", [cam], frames, joint_names=NAMES)
    truth = load_truth(tmp_path / "s.mcap")
    assert truth.joint_names == NAMES
    np.testing.assert_array_equal(truth.stamps, T0 + np.arange(3))
    np.testing.assert_array_equal(truth.joints, np.stack([f.joints for f in frames]))
    write_scene_bag(tmp_path / "nt.mcap", [cam], frames, truth=False)
    with pytest.raises(BagError, match=r"nt.mcap: no topic '/artrack/ground_truth'"):
        load_truth(tmp_path / "nt.mcap")


def test_plot_error_over_time(tmp_path):
    stamps = T0 + np.arange(120) * 33_333_333
    err = 20 + 5 * np.sin(np.arange(120) / 10.0)
    err[50:55] = np.nan
    out = plot_error_over_time(err, stamps, tmp_path / "plots" / "err.png", title="MPJPE over time")
    img = cv2.imread(str(out))
    assert img.shape == (420, 960, 3)
    blue = (img[..., 0] > 150) & (img[..., 2] < 80)
    assert blue.sum() > 500  # the curve is drawn
    dark = img.min(axis=2) < 60
    assert dark[:, :70].any() and dark[-50:].any()  # tick labels on both axes
    plot_error_over_time([], [], tmp_path / "empty.png")  # no data: still a valid image
    assert cv2.imread(str(tmp_path / "empty.png")) is not None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.png", "plots"]


def test_label_confusion_names_the_nearest_true_part():
    truth = {"l_hand": np.array([0.0, 0.3, 1.0]), "r_hand": np.array([0.0, -0.3, 1.0]),
             "head": np.array([0.0, 0.0, 1.6])}
    # l_hand right, r_hand swapped onto the left hand, an unknown label ignored
    observed = {"l_hand": np.array([0.01, 0.3, 1.0]), "r_hand": np.array([0.0, 0.28, 1.0]),
                "ghost": np.zeros(3)}
    out = label_confusion(observed, truth)
    assert set(out) == {"l_hand", "r_hand"}
    assert out["l_hand"][0] == "l_hand" and out["l_hand"][1] == pytest.approx(0.01)
    assert out["r_hand"][0] == "l_hand" and out["r_hand"][1] == pytest.approx(np.hypot(0.0, 0.58))
    assert label_confusion(observed, {}) == {}


def test_compare_paired_counts_seeds_and_sign_tests_them():
    """compare_paired (bench/closed_loop.py --compare): pairs only the keys with finite values in
    both runs, counts better / worse beyond tie_mm, and gives the exact two-sided sign test and
    the Wilcoxon signed-rank test."""
    before = {1: 100.0, 2: 200.0, 3: 150.0, 4: 120.0, 5: float("nan"), 6: 90.0}
    after = {1: 80.0, 2: 150.0, 3: 150.5, 4: 160.0, 5: 10.0, 7: 1.0}
    c = compare_paired(before, after)
    assert c["n"] == 4 and (c["better"], c["worse"], c["ties"]) == (2, 1, 1)
    assert c["mean_before"] == pytest.approx(142.5) and c["mean_after"] == pytest.approx(135.125)
    assert c["median_before"] == pytest.approx(135.0) and c["median_after"] == pytest.approx(150.25)
    assert c["sign_test_p"] == pytest.approx(1.0)  # 2 of 3: P(|X - 1.5| >= 0.5) under Bin(3, 1/2)
    # signed ranks of -20, -50, +40 (the tie dropped): W+ = 2; of the 8 equally likely sign
    # patterns of ranks 1, 2, 3, three give W+ <= 2: two-sided p = 2 x 3/8
    assert c["wilcoxon_p"] == pytest.approx(0.75)
    ten = compare_paired({k: 100.0 for k in range(10)}, {k: 50.0 for k in range(10)})
    assert ten["better"] == 10 and ten["sign_test_p"] == pytest.approx(2 * 0.5**10)
    # ten better by different amounts: every signed rank negative, the exact p = 2 / 2^10 again;
    # nine small gains and one large loss: the sign test sees 9 / 1, the signed ranks less
    spread = compare_paired({k: 100.0 for k in range(10)}, {k: 100.0 - 5 * (k + 1) for k in range(10)})
    assert spread["wilcoxon_p"] == pytest.approx(2 * 0.5**10)
    mixed = compare_paired({k: 100.0 for k in range(10)}, {k: 98.0 - k * 0.1 if k else 400.0 for k in range(10)})
    assert mixed["better"] == 9 and mixed["sign_test_p"] < 0.03 < mixed["wilcoxon_p"]
    all_ties = compare_paired({1: 5.0}, {1: 5.5})
    assert all_ties["sign_test_p"] == 1.0 and all_ties["wilcoxon_p"] == 1.0
    with pytest.raises(InputError, match="no key"):
        compare_paired({1: 1.0}, {2: 1.0})
    with pytest.raises(InputError, match="tie_mm"):
        compare_paired({1: 1.0}, {1: 1.0}, tie_mm=-1.0)
