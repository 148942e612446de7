"""Optimisation: motion-only pose refinement (OpenCV LM with ORB-SLAM's outlier rounds), bundle
adjustment and pose-graph optimisation (gtsam, Levenberg-Marquardt, Huber robust factors).

Conventions: poses enter and leave as w2c [4,4]; gtsam variables are camera-to-world Pose3 /
Similarity3 (gtsam's convention). Observation noise is isotropic with sigma = scale^octave pixels
(ORB-SLAM's information 1/sigma^2); chi-square thresholds 5.991 (2 dof) and 7.815 (3 dof).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import gtsam
import numpy as np

from segs.slam.geometry import inv_se3, orthonormalize, rt_to_w2c, transform
from segs.slam.native import kernels

# chi-square 95 % quantiles (statistics constants, not parameters): a reprojection error of 2 dof
# (u, v) and of 3 dof (u, v, right u), ORB-SLAM's outlier thresholds
CHI2_MONO = 5.991
CHI2_STEREO = 7.815


def reproj_chi2(w2c: np.ndarray, P: np.ndarray, uv: np.ndarray, ur: np.ndarray | None,
                inv_sigma2: np.ndarray, K: np.ndarray, bf: float,
                ur_sigma: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per observation chi2 [M], its threshold [M] (2 or 3 dof) and the camera depth [M].

    w2c: one pose [4,4] for all points P [M,3], or one per point [M,4,4].

    The third (stereo / RGB-D) residual is the disparity error bf/z - (u_meas - ur_meas), whose
    pixel sigma is ur_sigma (RGB-D: from the depth noise) or, when None, the keypoint's octave
    sigma (stereo). Equivalent to ORB-SLAM's (u, v, ur) residual with correlated u / ur noise.
    """
    pc = transform(w2c, P) if w2c.ndim == 2 else np.matmul(w2c[:, :3, :3], P[:, :, None])[:, :, 0] + w2c[:, :3, 3]
    z = pc[:, 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    u = K[0, 0] * pc[:, 0] / zs + K[0, 2]
    v = K[1, 1] * pc[:, 1] / zs + K[1, 2]
    chi2 = ((u - uv[:, 0]) ** 2 + (v - uv[:, 1]) ** 2) * inv_sigma2
    th = np.full(len(P), CHI2_MONO)
    if ur is not None:
        st = ur >= 0
        w_ur = inv_sigma2 if ur_sigma is None else 1.0 / ur_sigma ** 2
        chi2 = chi2 + np.where(st, (bf / zs - (uv[:, 0] - ur)) ** 2, 0.0) * w_ur
        th[st] = CHI2_STEREO
    return chi2, th, z


def _se3_exp(x: np.ndarray) -> np.ndarray:
    """[6] (rotation vector, translation) -> [4,4] (first-order translation, exact rotation)."""
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.ascontiguousarray(x[:3], np.float64).reshape(3, 1))[0]
    T[:3, 3] = x[3:]
    return T


def _pose_system(w2c: np.ndarray, P, uv, ur, w, K, bf, stereo, w_ur) -> tuple[np.ndarray, np.ndarray]:
    """Whitened reprojection residuals [R] (u rows [M], v rows [M], stereo rows [S]) and their
    Jacobian [R,6] wrt a left increment (rotation vector, translation) of w2c at zero.

    P [M,3] points, uv [M,2] keypoints, ur [M] right coordinates, w [M] / w_ur [M] weights,
    stereo [M] bool or None. The closed forms are ORB-SLAM's pose-only edges: with X = x/z,
    Y = y/z, du/d(omega) = fx (-XY, 1 + X^2, -Y), dv/d(omega) = fy (-(1 + Y^2), XY, X).
    """
    pc = P @ w2c[:3, :3].T + w2c[:3, 3]
    iz = 1.0 / np.maximum(pc[:, 2], 1e-6)
    X, Y = pc[:, 0] * iz, pc[:, 1] * iz
    n = len(P)
    ns = int(stereo.sum()) if stereo is not None else 0
    r = np.empty(2 * n + ns)
    J = np.zeros((2 * n + ns, 6))
    fw, gw, XY = K[0, 0] * w, K[1, 1] * w, X * Y
    r[:n] = (K[0, 0] * X + K[0, 2] - uv[:, 0]) * w
    r[n : 2 * n] = (K[1, 1] * Y + K[1, 2] - uv[:, 1]) * w
    Ju, Jv = J[:n], J[n : 2 * n]
    Ju[:, 0], Ju[:, 1], Ju[:, 2] = -fw * XY, fw * (1.0 + X * X), -fw * Y
    Ju[:, 3], Ju[:, 5] = fw * iz, -fw * X * iz
    Jv[:, 0], Jv[:, 1], Jv[:, 2] = -gw * (1.0 + Y * Y), gw * XY, gw * X
    Jv[:, 4], Jv[:, 5] = gw * iz, -gw * Y * iz
    if ns:  # disparity residual bf/z - (u - ur): d/d(pc) = (0, 0, -bf/z^2)
        s = stereo
        izs, ws = iz[s], w_ur[s]
        r[2 * n :] = (bf * izs - (uv[s, 0] - ur[s])) * ws
        b = bf * izs * ws
        Js = J[2 * n :]
        Js[:, 0], Js[:, 1], Js[:, 5] = -b * Y[s], b * X[s], -b * izs
    return r, J


def _solve_pose(w2c: np.ndarray, args: tuple, evaluations: int, native: bool = True) -> np.ndarray:
    """Levenberg-Marquardt (Marquardt's diagonal damping) on a w2c [4,4] with _pose_system(args);
    at most `evaluations` residual evaluations, stopping when the cost or the step stalls.
    native: the C++ kernel (segs.slam.native) where it is built, the same algorithm."""
    ext = kernels() if native else None
    if ext is not None:
        P, uv, ur, w, K, bf, stereo, w_ur = args
        none_f, none_b = np.zeros(0), np.zeros(0, bool)
        return ext.solve_pose(w2c, P, uv, none_f if ur is None else ur, w, K, float(bf),
                              none_b if stereo is None else stereo, none_f if w_ur is None else w_ur, int(evaluations))
    r, J = _pose_system(w2c, *args)
    cost, lam = float(r @ r), 1e-4
    for _ in range(evaluations - 1):
        H, g = J.T @ J, J.T @ r
        try:
            dx = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), -g)
        except np.linalg.LinAlgError:
            break
        T = _se3_exp(dx) @ w2c
        r2, J2 = _pose_system(T, *args)
        cost2 = float(r2 @ r2)
        if cost2 < cost:
            stalled = cost - cost2 <= 1e-8 * cost or float(dx @ dx) < 1e-20
            w2c, r, J, cost, lam = T, r2, J2, cost2, max(lam * 0.1, 1e-10)
            if stalled:
                break
        else:
            lam *= 10.0
            if lam > 1e6:
                break
    return w2c


def refine_pose(w2c0: np.ndarray, P: np.ndarray, uv: np.ndarray, ur: np.ndarray | None,
                inv_sigma2: np.ndarray, K: np.ndarray, bf: float, rounds: int = 4,
                min_inliers: int = 6, iterations: int = 20,
                ur_sigma: float | None = None, warm: bool = False, native: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Motion-only bundle adjustment of a w2c from map points P [M,3] and keypoints uv [M,2].

    ORB-SLAM's PoseOptimization: `rounds` optimisations (Levenberg-Marquardt on the 6-DOF
    increment, at most `iterations` residual evaluations each, Huber loss at sqrt(5.991) by
    reweighting, residuals whitened by the keypoint's octave sigma; stereo /
    RGB-D observations (ur >= 0) add the right-image coordinate); after each round every match
    is classified by its chi2 against 5.991 / 7.815 and only inliers enter the next.
    warm: the start pose is already refined (no gradual widening of the kernel in round one).
    native: the C++ kernel (segs.slam.native) where it is built, the same steps in one call.
    Returns (w2c [4,4], inlier mask [M]).
    """
    ext = kernels() if native else None
    if ext is not None:
        return ext.refine_pose(w2c0, P, uv, np.zeros(0) if ur is None else ur, inv_sigma2, K, float(bf), int(rounds),
                               int(min_inliers), int(iterations), 0.0 if ur_sigma is None else float(ur_sigma),
                               bool(warm))
    n = len(P)
    if n < min_inliers:
        return w2c0.copy(), np.zeros(n, bool)
    w = np.sqrt(inv_sigma2)
    w_ur = w if ur_sigma is None else np.full(n, 1.0 / ur_sigma)
    stereo = (ur >= 0) if ur is not None else None
    huber = np.sqrt(CHI2_MONO)
    inl = np.ones(n, bool)
    w2c = w2c0.copy()
    for r in range(rounds):
        if inl.sum() < min_inliers:
            return w2c, inl
        # Huber by iteratively reweighted least squares; the first round widens the kernel
        # gradually (the prediction may be far off), the last round is plain least squares.
        first = (1.0,) if warm else (10.0, 3.0, 1.0)
        scales = first if r == 0 else ((1.0,) if r < rounds - 1 else (None,))
        for sc in scales:
            if sc is None:
                hw = np.ones(int(inl.sum()))
            else:
                chi2, _, _ = reproj_chi2(w2c, P[inl], uv[inl], ur[inl] if ur is not None else None,
                                         inv_sigma2[inl], K, bf, ur_sigma)
                e = np.sqrt(chi2)
                hw = np.sqrt(np.where(e > sc * huber, sc * huber / np.maximum(e, 1e-12), 1.0))
            args = (P[inl], uv[inl], ur[inl] if ur is not None else None, w[inl] * hw, K, bf,
                    stereo[inl] if stereo is not None else None, w_ur[inl] * hw)
            w2c = orthonormalize(_solve_pose(w2c, args, iterations))
        chi2, th, z = reproj_chi2(w2c, P, uv, ur, inv_sigma2, K, bf, ur_sigma)
        new = (chi2 < th) & (z > 0)
        if r > 0 and np.array_equal(new, inl):
            return w2c, new
        inl = new
    return w2c, inl


def pnp_ransac(P: np.ndarray, uv: np.ndarray, K: np.ndarray, reproj: float = 4.0,
               iterations: int = 2000, seed: int = 0) -> tuple[np.ndarray | None, np.ndarray]:
    """Absolute pose from 3D-2D matches with RANSAC (cv2, deterministic seed) -> (w2c, inlier mask)."""
    if len(P) < 6:
        return None, np.zeros(len(P), bool)
    cv2.setRNGSeed(int(seed))
    ok, rvec, tvec, inl = cv2.solvePnPRansac(P.astype(np.float64), uv.astype(np.float64), K, None,
                                             iterationsCount=iterations, reprojectionError=reproj,
                                             confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
    mask = np.zeros(len(P), bool)
    if not ok or inl is None:
        return None, mask
    mask[inl.ravel()] = True
    return rt_to_w2c(rvec, tvec), mask


# --------------------------------------------------------------------------- bundle adjustment
@dataclass
class Observations:
    """Flattened observations: kf [O] kf id, pid [O] point id, uv [O,2], ur [O] (-1: mono), octave [O]."""

    kf: np.ndarray
    pid: np.ndarray
    uv: np.ndarray
    ur: np.ndarray
    octave: np.ndarray


@dataclass
class PointSet:
    """The points of a BA problem as two arrays (not one object per point: a local window holds
    thousands, and the child-process adjuster pickles them both ways): pid [N] int64 point ids in
    ascending order, xyz [N,3] float64 positions."""

    pid: np.ndarray
    xyz: np.ndarray

    def __post_init__(self) -> None:
        if self.xyz.shape != (len(self.pid), 3) or (len(self.pid) > 1 and not (np.diff(self.pid) > 0).all()):
            raise ValueError("PointSet: pid [N] ascending and unique, xyz [N,3] expected")


NO_FACTORS = (np.zeros(0, np.int64), np.zeros((0, 4)), np.empty(0, object))  # an empty factor cache
_X0, _L0 = gtsam.symbol("x", 0), gtsam.symbol("l", 0)  # keys: symbol(c, j) = symbol(c, 0) + j


def _pose3(w2c: np.ndarray) -> gtsam.Pose3:
    return gtsam.Pose3(inv_se3(w2c))


CONVERGED_GAIN = 1e-5  # LM stops after an iteration that lowers the cost by less than this fraction
# LM's initial damping lambda (absolute: added to the diagonal of the whitened normal equations).
# gtsam's default 1e-5 makes the first step an undamped Gauss-Newton step; in 5 of 30 real
# 7-Scenes RGB-D windows that step raised the cost by 30-140 %, nearly all of it from one to three
# points with few or no depth readings among their observations, thrown 3-63 m along their rays,
# and each rejected step costs a whole elimination until lambda has grown enough. 100 is small
# against a point's diagonal (about 3e5: a few observations at 525 px and 2 m) yet holds such
# points: same final cost, less time (bench/local_ba.py, docs/decisions/004-local-ba-lm-damping.md).
LAMBDA_INITIAL = 100.0


class BundleAdjuster:
    """Local / global BA over keyframe poses and points with gtsam (Huber, LM).

    K: intrinsics; bf: fx * baseline for stereo / RGB-D observations (ignored when ur < 0);
    sigma: per-octave pixel sigma [L]; huber: whether the robust kernel is used.
    """

    def __init__(self, K: np.ndarray, bf: float, scales: np.ndarray, huber: bool = True,
                 ur_sigma: float | None = None):
        self.K = K
        self.ur_sigma = ur_sigma
        self.bf = float(bf)
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        self.cal = gtsam.Cal3_S2(fx, fy, 0.0, cx, cy)
        self.cal_st = gtsam.Cal3_S2Stereo(fx, fy, 0.0, cx, cy, max(self.bf / fx, 1e-9))
        self.inv_sigma2 = 1.0 / np.asarray(scales, np.float64) ** 2

        def robust(dim, sigma, th):
            if dim == 3:  # (uL, uR, v) with uR = uL - disparity: correlated noise
                sd2 = (ur_sigma or sigma) ** 2
                s2 = sigma ** 2
                cov = np.array([[s2, s2, 0.0], [s2, s2 + sd2, 0.0], [0.0, 0.0, s2]])
                base = gtsam.noiseModel.Gaussian.Covariance(cov)
            else:
                base = gtsam.noiseModel.Isotropic.Sigma(dim, sigma)
            if not huber:
                return base
            return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(np.sqrt(th)), base)

        self.noise2 = [robust(2, s, CHI2_MONO) for s in scales]
        self.noise3 = [robust(3, s, CHI2_STEREO) for s in scales]
        self.prior = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
        # the last call's factors, see _factors: (keys [F] sorted, measurements [F,4], factors [F] object)
        self._factor_cache: tuple[np.ndarray, np.ndarray, np.ndarray] = NO_FACTORS

    def _factors(self, obs: Observations) -> np.ndarray:
        """One gtsam factor per observation (stereo / RGB-D when ur >= 0, else monocular) -> [O] object.

        Factors are immutable, and consecutive local BAs share most observations: a factor of
        the previous call is reused where keyframe, point and measurement are the same, and only
        this call's factors are kept for the next one (see bench/local_ba.py)."""
        keys = (obs.kf.astype(np.int64) << 32) | obs.pid.astype(np.int64)
        meas = np.column_stack([obs.uv, obs.ur, obs.octave]).astype(np.float64)
        prev_keys, prev_meas, prev_factors = self._factor_cache
        out = np.empty(len(keys), object)
        same = np.zeros(len(keys), bool)
        if len(prev_keys):
            pos = np.minimum(np.searchsorted(prev_keys, keys), len(prev_keys) - 1)
            same = (prev_keys[pos] == keys) & (prev_meas[pos] == meas).all(axis=1)
            out[same] = prev_factors[pos[same]]
        miss = np.flatnonzero(~same)
        if len(miss):
            stereo, mono = gtsam.GenericStereoFactor3D, gtsam.GenericProjectionFactorCal3_S2
            n3, n2, cal_st, cal = self.noise3, self.noise2, self.cal_st, self.cal
            xs = (np.uint64(_X0) + obs.kf[miss].astype(np.uint64)).tolist()
            ls = (np.uint64(_L0) + obs.pid[miss].astype(np.uint64)).tolist()
            for i, x, lm, (u, v), r, o in zip(miss.tolist(), xs, ls, obs.uv[miss].tolist(), obs.ur[miss].tolist(),
                                              obs.octave[miss].tolist()):
                if r >= 0:
                    out[i] = stereo(gtsam.StereoPoint2(u, r, v), n3[o], x, lm, cal_st)
                else:
                    out[i] = mono(np.array((u, v)), n2[o], x, lm, cal)
        order = np.argsort(keys, kind="stable")
        self._factor_cache = (keys[order], meas[order], out[order])
        return out

    def graph(self, poses, fixed, points: PointSet, factors) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The factor graph (observation factors + priors holding the fixed poses) and its
        initial values: poses kf_id -> w2c [4,4], points (PointSet)."""
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        for k, T in poses.items():
            values.insert(_X0 + int(k), _pose3(T))
            if k in fixed:
                graph.add(gtsam.PriorFactorPose3(_X0 + int(k), _pose3(T), self.prior))
        for key, x in zip((np.uint64(_L0) + points.pid.astype(np.uint64)).tolist(), points.xyz.astype(np.float64)):
            values.insert(key, x)
        for f in factors:
            graph.add(f)
        return graph, values

    @staticmethod
    def _lm(graph, values, order: gtsam.Ordering, iterations: int, min_gain: float = CONVERGED_GAIN):
        """gtsam LM from values -> optimised Values, or None for an indeterminate system."""
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(int(iterations))
        params.setRelativeErrorTol(float(min_gain))
        params.setlambdaInitial(LAMBDA_INITIAL)
        # points first, poses last: the elimination is the Schur complement of BA (a dense
        # reduced camera system); sequential Cholesky is 10-15 % faster than the multifrontal
        # default here, with the same steps (bench/local_ba.py)
        params.setOrdering(order)
        params.setLinearSolverType("SEQUENTIAL_CHOLESKY")
        try:
            return gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        except RuntimeError:  # indeterminate system (degenerate window)
            return None

    @staticmethod
    def _order(poses, pids: np.ndarray) -> gtsam.Ordering:
        """Elimination order: the points pids [N], then every pose."""
        return gtsam.Ordering((np.uint64(_L0) + pids.astype(np.uint64)).tolist() + [_X0 + int(k) for k in poses])

    @staticmethod
    def _read(values, poses) -> tuple[dict[int, np.ndarray], np.ndarray]:
        """-> (kf_id -> w2c [4,4] for every key of poses, every point of values [N,3] in id order)."""
        return ({k: inv_se3(values.atPose3(_X0 + int(k)).matrix()) for k in poses},
                gtsam.utilities.extractPoint3(values).reshape(-1, 3))

    def _optimize(self, poses, fixed, points: PointSet, factors, iterations, min_gain=CONVERGED_GAIN):
        graph, values = self.graph(poses, fixed, points, factors)
        result = self._lm(graph, values, self._order(poses, points.pid), iterations, min_gain)
        if result is None:  # keep the input
            return dict(poses), PointSet(points.pid, points.xyz.copy())
        new_poses, P = self._read(result, poses)
        return new_poses, PointSet(points.pid, P)

    def run(self, poses: dict[int, np.ndarray], fixed: set[int], points: PointSet,
            obs: Observations, iterations: int) -> tuple[dict[int, np.ndarray], PointSet]:
        """Optimise poses (w2c, kf_id -> [4,4]; those in `fixed` stay) and points."""
        return self._optimize(poses, fixed, points, self._factors(obs), iterations)

    def run_two_pass(self, poses: dict[int, np.ndarray], fixed: set[int], points: PointSet,
                     obs: Observations, iterations: tuple[int, int], min_gain: float = CONVERGED_GAIN):
        """ORB-SLAM's local BA: optimise, drop the observations that fail the chi2 test, optimise
        again without them. -> (poses, points, outlier mask [O] after the last pass). Each pass
        stops early after an iteration that lowered the cost by less than the fraction min_gain.
        The second pass starts from the first's gtsam Values and graph, minus the outliers'
        factors and the points left without observations (those keep the first pass's position)."""
        it1, it2 = (tuple(iterations) + (0,))[:2]
        factors = self._factors(obs)
        graph, values = self.graph(poses, fixed, points, factors)
        pids = points.pid  # ascending: extractPoint3's order
        at = np.searchsorted(pids, obs.pid)  # observation -> row of pids
        result = self._lm(graph, values, self._order(poses, pids), it1, min_gain)
        result = values if result is None else result
        new_poses, P = self._read(result, poses)
        bad = self.chi2(new_poses, P[at], obs)[0]
        if it2 > 0 and bad.any():
            first = graph.size() - len(factors)  # graph(): the priors, then the factors in order
            for i in np.flatnonzero(bad).tolist():
                graph.remove(first + i)
            kept = np.zeros(len(pids), bool)
            kept[at[~bad]] = True
            for p in pids[~kept].tolist():
                result.erase(_L0 + p)
            second = self._lm(graph, result, self._order(poses, pids[kept]), it2, min_gain)
            if second is not None:
                new_poses, P[kept] = self._read(second, poses)
                bad = self.chi2(new_poses, P[at], obs)[0]
        return new_poses, PointSet(pids, P), bad

    def chi2(self, poses: dict[int, np.ndarray], points: np.ndarray, obs: Observations) -> tuple[np.ndarray, np.ndarray]:
        """Outlier test per observation: (chi2 > threshold or behind the camera) [O] bool, chi2 [O].

        points: [O,3] position of each observation's point.
        """
        ks = np.sort(np.fromiter(poses, np.int64, len(poses)))
        w2c = np.stack([poses[k] for k in ks.tolist()])[np.searchsorted(ks, obs.kf)]  # [O,4,4]
        chi, th, z = reproj_chi2(w2c, points, obs.uv, obs.ur, self.inv_sigma2[obs.octave], self.K, self.bf,
                                 self.ur_sigma)
        bad = (chi > th) | (z <= 0)
        return bad, chi


# --------------------------------------------------------------------------- pose graph
def pose_graph(poses: dict[int, np.ndarray], edges: list[tuple[int, int, np.ndarray]], fixed: set[int],
               sim3: bool, iterations: int = 20,
               corrected: dict[int, np.ndarray] | None = None) -> dict[int, np.ndarray]:
    """Essential-graph optimisation.

    poses: kf_id -> initial similarity S_cw [4,4] (w2c; with scale for Sim3 after a correction);
    edges: (i, j, S_ij) with S_ij the measured relative transform S_iw @ S_wj (i.e. c_j -> c_i);
    fixed: kf ids held constant. Returns kf_id -> optimised S_cw [4,4] (a similarity if sim3).
    """
    X = lambda k: gtsam.symbol("x", int(k))
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    if sim3:
        to_var = lambda S: _sim3(np.linalg.inv(S))
        noise = gtsam.noiseModel.Isotropic.Sigma(7, 1.0)
        prior_noise = gtsam.noiseModel.Isotropic.Sigma(7, 1e-6)
    else:
        to_var = lambda T: gtsam.Pose3(inv_se3(T))
        noise = gtsam.noiseModel.Isotropic.Sigma(6, 1.0)
        prior_noise = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    for k, S in poses.items():
        values.insert(X(k), to_var(S))
        if k in fixed:
            graph.add((gtsam.PriorFactorSimilarity3 if sim3 else gtsam.PriorFactorPose3)(X(k), to_var(S), prior_noise))
    for i, j, Sij in edges:
        # between(x_i, x_j) = T_wi^-1 T_wj = T_ij (camera j expressed in camera i)
        meas = _sim3(Sij) if sim3 else gtsam.Pose3(Sij)
        graph.add((gtsam.BetweenFactorSimilarity3 if sim3 else gtsam.BetweenFactorPose3)(X(i), X(j), meas, noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(iterations))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    out = {}
    for k in poses:
        if sim3:
            out[k] = np.linalg.inv(_sim3_matrix(result.atSimilarity3(X(k))))
        else:
            out[k] = inv_se3(result.atPose3(X(k)).matrix())
    return out


def _sim3(S: np.ndarray) -> gtsam.Similarity3:
    """Our similarity [[sR, t],[0,1]] -> gtsam.Similarity3 (which acts as s (R p + t'))."""
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    R = S[:3, :3] / s
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    return gtsam.Similarity3(gtsam.Rot3(R), S[:3, 3] / s, s)


def _sim3_matrix(g: gtsam.Similarity3) -> np.ndarray:
    """gtsam.Similarity3 -> our [[sR, t],[0,1]]."""
    s = g.scale()
    S = np.eye(4)
    S[:3, :3] = s * g.rotation().matrix()
    S[:3, 3] = s * np.asarray(g.translation())
    return S
