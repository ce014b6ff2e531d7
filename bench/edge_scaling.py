#!/usr/bin/env python3
"""Scaling of the O(N) articulated propagation (ALGORITHMS.md §2, Algorithm 1) against a dense KKT solve.

For chains and random trees of 10, 100, 1000 and 5000 components (half ball, half hinge
joints, random poses, random positive-definite statistics) it times
``artrack.propagation.propagate`` (median over interleaved rounds; the tree schedule is computed once per
topology, as a tracker would, and the joint matrices ``D12``/``D21`` are built beforehand —
their build time is shown in its own column; "cpu ms" is the thread's CPU time, which other
processes on a shared machine do not inflate) and ``dense_kkt_solve`` (one dense LU solve
of the same constrained least-squares problem; only up to 1000 components — at 5000 the
KKT matrix would be ~50 000 x 50 000, 20 GB — and skipped there), prints a table and ends
with one JSON line:

    {"t_ratio_5000_1000": worst t(5000)/t(1000) over the topologies,
     "speedup_vs_dense_1000": smallest dense/propagate time ratio at 1000,
     "max_abs_diff_vs_dense": largest |xi_propagated - xi_dense| over every dense comparison,
     plus the per-topology wall-clock and CPU-time ratios}

All times are medians; speedups compare wall-clock times.

Run from the repository root: ``.venv/bin/python bench/edge_scaling.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src" / "artrack_nodes"))

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from artrack.lie import make_se3  # noqa: E402
from artrack.propagation import (  # noqa: E402
    Joint,
    constraint_matrices,
    dense_kkt_solve,
    propagate,
    tree_schedule,
)


def make_problem(n: int, topology: str, seed: int):
    """Random articulated problem: parents (N,), E (N,4,4), joints, xi_hat (N,6), C (N,6,6)."""
    rng = np.random.default_rng(seed)
    if topology == "chain":
        parents = np.r_[-1, np.arange(n - 1)]
    else:  # random recursive tree: each component hangs from a uniformly chosen earlier one
        parents = np.r_[-1, (rng.random(n - 1) * np.arange(1, n)).astype(np.int64)]
    E = make_se3(Rotation.random(n, random_state=rng).as_matrix(), rng.normal(size=(n, 3)))
    kinds = rng.random(n) < 0.5
    points = rng.normal(size=(n, 3)) * 0.2
    axes = rng.normal(size=(n, 3))
    joints = [
        None if parents[i] < 0 else Joint("hinge" if kinds[i] else "ball", points[i], axes[i])
        for i in range(n)
    ]
    L = rng.normal(size=(n, 6, 6))
    C = L @ np.swapaxes(L, 1, 2) + 0.05 * np.eye(6)
    xi_hat = rng.normal(size=(n, 6)) * 0.05
    return parents, E, joints, xi_hat, C


def timed(fn, min_repeats: int, min_seconds: float, max_repeats: int) -> tuple[float, object]:
    """Median wall time (s) of ``fn()`` over repeats, and its last result."""
    times = []
    out = None
    while len(times) < max_repeats and (len(times) < min_repeats or sum(times) < min_seconds):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def bench_topology(topology: str, sizes: list[int], args: argparse.Namespace) -> list[dict]:
    """Time every N of one topology: propagation, joint-matrix build, dense KKT solve (N <= --dense-max).

    Propagation timings are interleaved across the sizes (round r times every N once, each as a
    batch of calls lasting >= ~10 ms) and the per-call median over the rounds is reported, so that
    load from other processes affects every size alike and the ratios stay meaningful.
    """
    cases = []
    for n in sizes:
        parents, E, joints, xi_hat, C = make_problem(n, topology, args.seed + n)
        sched = tree_schedule(parents)
        build = (E, parents, joints)
        t_d, (D12, D21, mask) = timed(lambda b=build: constraint_matrices(*b), 3, 0.2, 20)
        t0 = time.perf_counter()
        xi = propagate(xi_hat, C, sched, D12, D21, mask)  # warm-up and calibration
        batch = max(1, int(0.01 / max(time.perf_counter() - t0, 1e-6)))
        cases.append(
            dict(
                n=n,
                parents=parents,
                sched=sched,
                xi_hat=xi_hat,
                C=C,
                D=(D12, D21, mask),
                t_d=t_d,
                xi=xi,
                batch=batch,
                times=[],
                cpu=[],
            )
        )
    for _ in range(args.rounds):
        for case in cases:
            args_p = (case["xi_hat"], case["C"], case["sched"], *case["D"])
            t0, c0 = time.perf_counter(), time.thread_time()
            for _ in range(case["batch"]):
                propagate(*args_p)
            case["times"].append((time.perf_counter() - t0) / case["batch"])
            case["cpu"].append((time.thread_time() - c0) / case["batch"])
    rows = []
    for case in cases:
        t_p = float(np.median(case["times"]))
        row = {
            "topology": topology,
            "n": case["n"],
            "depth": len(case["sched"].levels),
            "propagate_ms": 1e3 * t_p,
            "propagate_cpu_ms": 1e3 * float(np.median(case["cpu"])),
            "dbuild_ms": 1e3 * case["t_d"],
            "dense_ms": None,
            "speedup": None,
            "max_abs_diff": None,
        }
        if case["n"] <= args.dense_max:
            reps = 3 if case["n"] <= 100 else 1
            dense_args = (case["xi_hat"], case["C"], case["parents"], *case["D"])
            t_k, dense = timed(lambda a=dense_args: dense_kkt_solve(*a), reps, 0.0, reps)
            diff = float(np.abs(case["xi"] - dense).max())
            row.update(dense_ms=1e3 * t_k, speedup=t_k / t_p, max_abs_diff=diff)
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    doc = (__doc__ or "").split("\n\n")[0]
    ap = argparse.ArgumentParser(description=doc, epilog="Ends with one JSON line on stdout.")
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 100, 1000, 5000], help="component counts")
    ap.add_argument("--topologies", nargs="+", default=["chain", "tree"], choices=["chain", "tree"])
    ap.add_argument("--dense-max", type=int, default=1000, help="largest N solved densely (default 1000)")
    ap.add_argument("--rounds", type=int, default=21, help="interleaved timing rounds (median reported)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    rows = []
    header = (
        f"{'topology':8s} {'N':>5s} {'depth':>5s} {'propagate ms':>12s} {'(cpu ms)':>9s} {'D build ms':>10s} "
        f"{'dense ms':>10s} {'speedup':>8s} {'max|diff|':>10s}"
    )
    print(header)
    print("-" * len(header))
    for topology in args.topologies:
        for row in bench_topology(topology, args.sizes, args):
            rows.append(row)
            n = row["n"]
            dense_s = f"{row['dense_ms']:10.1f}" if row["dense_ms"] is not None else f"{'skipped':>10s}"
            sp = f"{row['speedup']:7.0f}x" if row["speedup"] is not None else f"{'-':>8s}"
            diff = f"{row['max_abs_diff']:10.1e}" if row["max_abs_diff"] is not None else f"{'-':>10s}"
            print(
                f"{topology:8s} {n:5d} {row['depth']:5d} {row['propagate_ms']:12.3f} "
                f"{row['propagate_cpu_ms']:9.3f} {row['dbuild_ms']:10.2f} {dense_s} {sp} {diff}",
                flush=True,
            )
    skipped = [r["n"] for r in rows if r["dense_ms"] is None]
    if skipped:
        print(
            f"dense KKT skipped for N = {sorted(set(skipped))} (> --dense-max {args.dense_max}; "
            f"its matrix would be about {10 * max(skipped)} squared, {800 * max(skipped) ** 2 / 1e9:.1f} GB)"
        )

    def pick(topology: str, n: int) -> dict | None:
        return next((r for r in rows if r["topology"] == topology and r["n"] == n), None)

    big = [(t, pick(t, 5000), pick(t, 1000)) for t in args.topologies]
    ratios = {t: r5["propagate_ms"] / r1["propagate_ms"] for t, r5, r1 in big if r5 and r1}
    ratios_cpu = {t: r5["propagate_cpu_ms"] / r1["propagate_cpu_ms"] for t, r5, r1 in big if r5 and r1}
    speedups = [r1["speedup"] for _, _, r1 in big if r1 and r1["speedup"] is not None]
    diffs = [r["max_abs_diff"] for r in rows if r["max_abs_diff"] is not None]
    summary = {
        "t_ratio_5000_1000": max(ratios.values()) if ratios else None,
        "speedup_vs_dense_1000": min(speedups) if speedups else None,
        "max_abs_diff_vs_dense": max(diffs) if diffs else None,
        "t_ratio_5000_1000_by_topology": ratios,
        "t_ratio_5000_1000_cpu_by_topology": ratios_cpu,
    }
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
