"""Where local bundle adjustment spends its time, on real frames (issue 13 item 1).

Tracks the first --frames frames of the shared 7-Scenes sequence with the frontend as
`segs.track +experiment=seven_scenes_{sensor}` builds it (defaults) and records every local BA
problem (poses, fixed keyframes, points, observations). Then, on the last --problems of them
(the map is warm there), it times with the machine otherwise unchanged:

- the parts: building the gtsam factors (from nothing, and after the previous problem's, whose
  factors BundleAdjuster reuses), one linearisation, one linearisation + elimination
  (with the elimination order BundleAdjuster uses and with gtsam's default COLAMD order), one
  error evaluation;
- whole optimisations: solver / order variants and iteration budgets, with the final cost
  (sum of robust squared whitened errors) relative to LM 5 iterations;
- BundleAdjuster.run_two_pass as the frontend calls it, each call after the previous problem's
  (the figure in fe.local_mapping.ba_times, minus reading / writing the map), with the configured and
  other iteration budgets / early stops (min_gain), with LM's initial damping as configured
  (optimize.LAMBDA_INITIAL) and gtsam's default 1e-5, and the final cost (every observation,
  robust) relative to the configured call's.

Medians (and means: a rejected LM step costs a whole elimination, so slow windows matter) over
problems, each timed --repeat times (the median of those). JSON: outputs/bench/local_ba.json.

    python bench/local_ba.py --frames 300 --problems 12
"""
from __future__ import annotations

import argparse
import statistics
import time

import _harness

_harness.apply_process_settings()  # before torch loads

import gtsam
import numpy as np

from segs.config import compose, instantiate, make_sequence
from segs.slam.estimation import optimize
from segs.slam.estimation.optimize import NO_FACTORS, BundleAdjuster

SEVEN_SCENES = _harness.SEVEN_SCENES


def record_problems(sensor: str, frames: int) -> tuple[list, BundleAdjuster, dict]:
    """Track the first `frames` frames; every local BA problem passed to run_two_pass."""
    cfg = compose([f"+experiment=seven_scenes_{sensor}", f"data.root={SEVEN_SCENES}", f"data.frames=[0,{frames}]"],
                  output_dir="/tmp/segs_bench_ba")  # fmt: skip
    seq = make_sequence(cfg.data)
    fe = instantiate(cfg.slam)(camera=seq.camera, sensor=seq.sensor)
    problems = []
    original = optimize.BundleAdjuster.run_two_pass

    def spy(self, poses, fixed, points, obs, iterations, min_gain=optimize.CONVERGED_GAIN):
        problems.append((dict(poses), set(fixed), points, obs, (tuple(iterations), min_gain)))
        return original(self, poses, fixed, points, obs, iterations, min_gain)

    optimize.BundleAdjuster.run_two_pass = spy
    try:
        for i in range(len(seq)):
            fe.process(seq[i])
    finally:
        optimize.BundleAdjuster.run_two_pass = original
    info = {"keyframes": len(fe.keyframe_frames()), "local_ba_ms_in_run": 1e3 * float(np.median(fe.local_mapping.ba_times))}
    return problems, fe.ba, info


def graph_of(ba: BundleAdjuster, poses, fixed, points, obs):
    """The graph BundleAdjuster optimises, with its factors built from obs."""
    return ba.graph(poses, fixed, points, ba._factors(obs))


def optimise(graph, values, order, iterations: int, solver: str, method: str = "LM"):
    """-> (seconds, final error, iterations run)."""
    params = gtsam.LevenbergMarquardtParams() if method == "LM" else gtsam.GaussNewtonParams()
    if method == "LM":
        params.setlambdaInitial(optimize.LAMBDA_INITIAL)
    params.setMaxIterations(iterations)
    params.setRelativeErrorTol(1e-5)
    params.setLinearSolverType(solver)
    if order is not None:
        params.setOrdering(order)
    cls = gtsam.LevenbergMarquardtOptimizer if method == "LM" else gtsam.GaussNewtonOptimizer
    t = time.perf_counter()
    opt = cls(graph, values, params)
    result = opt.optimize()
    return time.perf_counter() - t, graph.error(result), opt.iterations()


def cost_at(graph, poses, new_poses, new_points) -> float:
    """The graph's error (every observation, robust) at a run_two_pass result."""
    values = gtsam.Values()
    for k in poses:
        values.insert(optimize._X0 + int(k), optimize._pose3(new_poses[k]))
    for p, x in zip(new_points.pid.tolist(), new_points.xyz):
        values.insert(optimize._L0 + int(p), np.asarray(x, np.float64))
    return graph.error(values)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sensor", default="rgbd", choices=("rgbd", "mono"))
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--problems", type=int, default=12)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    if not (SEVEN_SCENES / "seq").is_dir():
        raise SystemExit(f"bench/local_ba.py: the 7-Scenes frames are not at {SEVEN_SCENES}")
    record = _harness.record()
    problems, ba, info = record_problems(args.sensor, args.frames)
    problems = problems[-args.problems:]
    rows: dict[str, list[float]] = {}
    failed: dict[str, int] = {}  # variant -> problems it could not solve

    def add(name, value):
        rows.setdefault(name, []).append(value)

    tol, lam, gtsam_lam = optimize.CONVERGED_GAIN, optimize.LAMBDA_INITIAL, 1e-5
    # run_two_pass variants: (iterations, min_gain, initial lambda), None = as configured; the
    # first one is the reference of the final costs
    variants = [("BundleAdjuster.run_two_pass, the configured iterations, min_gain", (None, None, lam)),
                ("BundleAdjuster.run_two_pass, LM 5 + 10 (the former default)", ((5, 10), tol, gtsam_lam)),
                ("BundleAdjuster.run_two_pass, the configured iterations, min_gain", (None, None, gtsam_lam)),
                ("BundleAdjuster.run_two_pass, LM, min_gain", ((4, 4), tol, lam)),
                ("BundleAdjuster.run_two_pass, LM, min_gain", ((4, 1), 0.01, lam)),
                ("BundleAdjuster.run_two_pass, LM, min_gain", ((2, 1), tol, lam)),
                ("BundleAdjuster.run_two_pass, LM, min_gain", ((2, 1), tol, gtsam_lam)),
                ("BundleAdjuster.run_two_pass, LM, min_gain", ((1, 1), tol, lam)),
                ("BundleAdjuster.run_two_pass, LM, min_gain", ((1, 1), tol, gtsam_lam))] + [
        (f"{m} {it} it, {solver.split('_')[0].lower()} Cholesky, {'points-first' if schur else 'COLAMD'}", (m, it, solver, schur))
        for m, it, solver, schur in [("LM", 5, "MULTIFRONTAL_CHOLESKY", False), ("LM", 5, "SEQUENTIAL_CHOLESKY", True),
                                     ("LM", 10, "SEQUENTIAL_CHOLESKY", True), ("LM", 3, "SEQUENTIAL_CHOLESKY", True),
                                     ("GN", 3, "SEQUENTIAL_CHOLESKY", True)]]  # fmt: skip
    previous = problems[0][3]
    for poses, fixed, points, obs, iterations in problems[1:]:
        # BundleAdjuster reuses the factors of its previous call: time each call after the
        # previous problem's, as in a run
        def after_previous(previous=previous):
            ba._factors(previous)

        add("observations", len(obs.kf))
        add("points", len(points.pid))
        add("keyframes (optimised + fixed)", len(poses))
        add("build factors + values (ms)", 1e3 * _harness.median_seconds(lambda: graph_of(ba, poses, fixed, points, obs), args.repeat,
                                                                         setup=lambda: setattr(ba, "_factor_cache", NO_FACTORS)))
        add("build factors + values after the previous problem's (ms)",
            1e3 * _harness.median_seconds(lambda: graph_of(ba, poses, fixed, points, obs), args.repeat, setup=after_previous))
        graph, values = graph_of(ba, poses, fixed, points, obs)
        order = BundleAdjuster._order(poses, points.pid)
        add("one linearisation (ms)", 1e3 * _harness.median_seconds(lambda: graph.linearize(values), args.repeat))
        add("one error evaluation (ms)", 1e3 * _harness.median_seconds(lambda: graph.error(values), args.repeat))
        lin = graph.linearize(values)
        add("one elimination, COLAMD multifrontal (ms)", 1e3 * _harness.median_seconds(lin.eliminateMultifrontal, args.repeat))
        add("one elimination, points first, sequential (ms)",
            1e3 * _harness.median_seconds(lambda: lin.eliminateSequential(order), args.repeat))
        ref_error = ref_cost = None
        for name, v in variants:
            if len(v) == 3:
                its, gain = iterations if v[0] is None else v[:2]
                optimize.LAMBDA_INITIAL = v[2]
                ms = 1e3 * _harness.median_seconds(lambda: ba.run_two_pass(poses, fixed, points, obs, its, gain), args.repeat,
                                                   setup=after_previous)
                new_poses, new_points, _ = ba.run_two_pass(poses, fixed, points, obs, its, gain)
                optimize.LAMBDA_INITIAL = lam
                label = f"{name} {its} {gain:g}, initial lambda {v[2]:g}"
                add(label + " (ms)", ms)
                cost = cost_at(graph, poses, new_poses, new_points)
                if ref_cost is None:
                    ref_cost = cost
                else:
                    add(label + ": final cost / configured's", cost / ref_cost)
                continue
            m, it, solver, schur = v
            try:
                secs, err, its = zip(*[optimise(graph, values, order if schur else None, it, solver, m)
                                       for _ in range(args.repeat)])
            except RuntimeError:  # gtsam: indeterminate system (this variant cannot solve this window)
                failed[name] = failed.get(name, 0) + 1
                continue
            add(name + " (ms)", 1e3 * statistics.median(secs))
            if ref_error is None:
                ref_error = optimise(graph, values, order, 5, "SEQUENTIAL_CHOLESKY")[1]
            add(name + ": final cost / LM-5 cost", err[0] / ref_error)
            add(name + ": iterations", its[0])
        previous = obs
    table = {k: statistics.median(v) for k, v in rows.items()}
    means = {k: statistics.fmean(v) for k, v in rows.items()}
    print(f"local BA on {len(problems)} problems of 7-Scenes {args.sensor} frames 0-{args.frames} "
          f"(load {record['machine']['load_avg'][0]:.2f} -> {_harness.load_average()[0]:.2f}); median, mean over problems:")
    for k, v in table.items():
        print(f"  {k:90s} {v:12.5f} {means[k]:12.5f}")
    for k, n in failed.items():
        print(f"  {k}: indeterminate system (gtsam) on {n} of {len(problems)} problems, left out of its rows")
    print(f"  {'local BA in the tracking run (fe.local_mapping.ba_times, median, ms)':72s} {info['local_ba_ms_in_run']:12.1f}")
    record["machine"]["load_avg_end"] = _harness.load_average()
    _harness.write_json(_harness.OUTPUTS / "local_ba.json", {"args": vars(args), **record, "info": info, "medians": table, "means": means,
                                                             "indeterminate": failed})  # fmt: skip


if __name__ == "__main__":
    main()
