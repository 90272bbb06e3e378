"""Fitting the body model to back-projected depth points with known correspondences.

Two solvers minimise the same objective (fit.objective):

* 'fast' (default), in float64 numpy on the CPU (a few hundred targets and a few dozen
  bones: numpy's per-call overhead is a fraction of torch's at that size):
  1. targets: the points are aggregated per corresponded vertex (`aggregate_by_vertex`:
     robust median, weight = count x coherence), at most `max_points` of them;
  2. cold start: GM-reweighted Kabsch of the head+torso targets for the global rotation
     and translation, then a per-segment closed-form rotation for every fitted joint,
     parents first (in the spirit of smplfitter); a limb joint whose own segment is
     barely seen (a thigh behind the folded body, an upper arm behind the torso) is
     oriented from the targets of its whole limb below it in a second start
     (`cfg.limb_init`), solved too where the first leaves that limb's targets
     unexplained, and the lower energy kept;
  3. Levenberg-Marquardt / IRLS iterations with the analytic Jacobian of linear blend
     skinning for rotation increments (R_j <- exp(delta_j) R_j), translation and the
     exact local linearisation of the shape, with a graduated Geman-McClure scale; a
     180-degree flip restart when the cold fit leaves a large residual;
  4. cold fits, last: the joints no target moves (cfg.min_joint_support: an arm behind
     the body, a head out of frame), held at rest until then, take their conditional
     mean given the fitted joints under a pose Gaussian learned from the synthetic poses
     (fit.pose_prior).
  Tracking mode warm-starts from the previous frame, keeps its shape and runs a few
  iterations.
* 'lbfgs': the paper's reference - PyTorch L-BFGS, strong Wolfe, lr 0.6, 20 iterations on
  axis-angle parameters, from the same initialisation.

`fit_joints` is the Table II row-1 baseline: the same solver on 3D joint positions.

This module holds the public entry, `Fitter` (initialisation, the sequence of solver runs,
results) and `FitResult`; the targets are made in fit.targets, the kinematics live in
fit.rig, the solvers' iterations in fit.solver.
"""
from __future__ import annotations

import contextlib
import copy
import time
from dataclasses import dataclass

import numpy as np
import torch

from smpl_depth_ros.body.base import BodyModel
from smpl_depth_ros.config import FitConfig
from smpl_depth_ros.fit import objective
from smpl_depth_ros.fit.freespace import FreeSpace
from smpl_depth_ros.fit.pose_prior import PoseGaussian
from smpl_depth_ros.fit.rig import Rig, kabsch, log, rodrigues, vertex_normals
from smpl_depth_ros.fit.solver import FastSolver, lbfgs
from smpl_depth_ros.fit.targets import aggregate_by_vertex
from smpl_depth_ros.types import BodyParams

TORSO_PARTS = (1, 2)  # head + torso: the most rigid region, used for the rigid init
MAX_RAW_POINTS = 20000  # input points aggregated per fit (a random subset beyond that)
SPREAD_M = 0.02  # aggregate_by_vertex's coherence scale (widened for noisy sensors)
FREE_SQ_MIN = 0.02  # m^2: summed squared free-space distances that call for the refinement
                    # (exact fits to noisy val_s2 frames leave <= 0.005; 0.02 is e.g. 8
                    # vertices 5 cm out, or 2 at 10 cm)
SEGMENT_MIN_TARGETS = 20  # targets a segment needs to be oriented from its own
LIMB_MIN_TARGETS = 10  # targets a limb joint's whole limb needs to be oriented from them
LIMB_JOINTS = ('hip', 'knee', 'shoulder', 'elbow')  # name suffixes: the limb joints so
                                                   # oriented (not the spine, collars, wrists)
LIMB_EXPLAINED_M = 0.05  # median residual of those targets under which the first start
                         # has found the limb already: no second solve
REST_CACHE_SIZE = 4  # shapes whose rest linearisation is kept (tracking reuses one)
RNG_SEED = 0  # the random stream of the point subsets (`reseed` starts it again)


@dataclass
class FitResult:
    """Outcome of one fit.

    Attributes:
        params: fitted BodyParams (numpy float32).
        vertices: (V, 3) full mesh, camera frame.
        joints: (J, 3).
        residuals: (N,) distance of every input point to its corresponding vertex (m).
        data_term: robust data-term value (weighted mean Geman-McClure, m^2) over the
            solver's targets: the per-vertex aggregates of the points (see
            `aggregate_by_vertex`), not the raw points.
        energy: total objective on the same targets.
        iterations: solver iterations run.
        time_ms: wall time of the fit.
        solver: 'fast' | 'lbfgs'; warm: warm-started.
    """

    params: BodyParams
    vertices: np.ndarray
    joints: np.ndarray
    residuals: np.ndarray
    data_term: float
    energy: float
    iterations: int
    time_ms: float
    solver: str
    warm: bool

    @property
    def median_residual(self) -> float:
        return float(np.median(self.residuals)) if len(self.residuals) else float('inf')


_BLAS = []  # [threadpoolctl.ThreadpoolController or None], made on first use


def _single_threaded_blas():
    """A context in which BLAS runs one thread: the fast solver makes many small BLAS calls
    between torch calls; OpenBLAS's worker threads then fight torch's OpenMP threads for
    the cores and every call waits (measured: 15x slower on 2 cores). One BLAS thread is
    the fastest at these sizes. Scoped to the fit: the rest of the process keeps its own
    BLAS settings."""
    if not _BLAS:
        try:
            from threadpoolctl import ThreadpoolController
            _BLAS.append(ThreadpoolController())
        except ImportError:  # optional: only speed depends on it
            _BLAS.append(None)
    if _BLAS[0] is None:
        return contextlib.nullcontext()
    return _BLAS[0].limit(limits=1, user_api='blas')


class Fitter(FastSolver):
    """Fits a BodyModel to points with correspondences. Stateless apart from caches.

    Args:
        body: the body model (anny or SMPL backend).
        cfg: objective weights and solver settings.
    """

    def __init__(self, body: BodyModel, cfg: FitConfig = FitConfig()):
        self.body = body
        self.cfg = cfg
        self.rig = Rig(body)
        self._rest_cache: dict[bytes, tuple] = {}
        self._rng = np.random.default_rng(RNG_SEED)
        # Rest vertices at the mean shape: the template for the target consistency check.
        self._template = self._rest(self.rig.shape_mean)[1]
        self._rest_normals = vertex_normals(self._template, body.faces_numpy())
        self._weak = objective.weak_joint_mask(body).astype(np.float64)
        self._limb = np.array([n.split('_')[-1] in LIMB_JOINTS for n in body.joint_names])
        # Built here, not on the first frame (0.3 s, once per process and body model).
        self._pose_gaussian = PoseGaussian.for_body(body) if cfg.complete_hidden else None
        self.spread_m = SPREAD_M
        self._noisy: dict[int, 'Fitter'] = {}

    def reseed(self) -> None:
        """Restart the random stream (the subsets of large point sets) from its start, as
        in a new Fitter; the noise-widened copies (`for_noise`) share it."""
        self._rng.bit_generator.state = np.random.default_rng(RNG_SEED).bit_generator.state

    def for_noise(self, excess: float) -> 'Fitter':
        """This fitter with its noise-dependent thresholds widened for an excess sensor
        noise (metres, sensor_noise.scaled_fit_config / scaled_spread); itself for 0.
        Shares the rig, caches and random stream."""
        from smpl_depth_ros.sensor_noise import scaled_fit_config, scaled_spread
        cfg = scaled_fit_config(self.cfg, excess)
        spread = scaled_spread(SPREAD_M, excess)
        if cfg == self.cfg and spread == self.spread_m:
            return self
        key = int(round(float(excess) * 1e4))  # 0.1 mm steps
        if key not in self._noisy:
            f = copy.copy(self)
            f.cfg, f.spread_m, f._noisy = cfg, spread, {}
            self._noisy[key] = f
        return self._noisy[key]

    def vertices(self, params: BodyParams) -> np.ndarray:
        """The posed mesh (V, 3) of `params`, float32, as a fit's `FitResult.vertices`."""
        rot = rodrigues(np.concatenate([np.asarray(params.global_orient, np.float64)[None],
                                        np.asarray(params.pose, np.float64)]))
        state = (rot, np.asarray(params.transl, np.float64), np.asarray(params.shape, np.float64))
        return self._vertices(state)[0].astype(np.float32)

    def moved(self, params: BodyParams, R: np.ndarray, t: np.ndarray) -> BodyParams:
        """The parameters of the same posed body moved rigidly, x -> R x + t (the root
        turns about its rest head)."""
        pivot = self._rest(np.asarray(params.shape))[3][self.rig.levels[0][0]]
        g = log(R @ rodrigues(np.asarray(params.global_orient, np.float64)))
        transl = R @ (pivot + np.asarray(params.transl, np.float64)) + t - pivot
        return BodyParams(pose=params.pose, shape=params.shape,
                          global_orient=g.astype(np.float32), transl=transl.astype(np.float32))

    def joint_frames(self, params: BodyParams) -> tuple[np.ndarray, np.ndarray]:
        """World rotations (J, 3, 3) and positions (J, 3) of the fitted joints (root
        first, the order of `FitResult.joints`) for `params`: the joints' frames for TF."""
        rig = self.rig
        rot = rodrigues(np.concatenate([np.asarray(params.global_orient, np.float64)[None],
                                        np.asarray(params.pose, np.float64).reshape(-1, 3)]))
        h0 = self._rest(params.shape)[3]
        G, x = rig.fk(rot, h0)
        return G[rig.jb], x[rig.jb] + np.asarray(params.transl, np.float64)

    def _pose_l2_weights(self) -> np.ndarray:
        """(P,) weight per pose joint of its pull towards rest (per rad^2):
        cfg.lambda_pose_l2, plus cfg.lambda_pose_weak for the weakly observed joints."""
        return self.cfg.lambda_pose_l2 + self.cfg.lambda_pose_weak * self._weak

    # ------------------------------------------------------------------ helpers
    def _rest(self, shape: np.ndarray):
        """Exact first-order rest geometry of the whole mesh at `shape` (cached):
        rest vertices (V, 3), their shape Jacobian (V, 3, S), rest heads (Jb, 3) and their
        Jacobian (Jb, 3, S)."""
        # Keyed at float32 precision: a warm start's shape comes back through BodyParams.
        shape = np.asarray(shape, np.float32).astype(np.float64)
        key = shape.tobytes()
        hit = self._rest_cache.get(key)
        if hit is None:
            body = self.body
            s = torch.as_tensor(shape, dtype=body.dtype, device=body.device)[None]
            with torch.no_grad():
                hit = tuple(t.detach().cpu().double().numpy()
                            for t in body.rest_linear(s, None))
            hit = (shape,) + hit
            if len(self._rest_cache) >= REST_CACHE_SIZE:  # ~210 kB each (anny)
                self._rest_cache.pop(next(iter(self._rest_cache)))
            self._rest_cache[key] = hit
        return hit

    def _pose_offsets(self, rot: np.ndarray, ids: np.ndarray | None):
        """SMPL's pose-corrective offsets (0 for anny). Their derivative is left out of
        the Jacobian (a small, standard Gauss-Newton approximation)."""
        body = self.body
        if not hasattr(body, 'pose_offsets'):
            return 0.0
        r = torch.as_tensor(rot, dtype=body.dtype, device=body.device)[None]
        i = None if ids is None else torch.as_tensor(ids, device=body.device)
        with torch.no_grad():
            return body.pose_offsets(r, i)[0].cpu().double().numpy()

    def _problem(self, shape, ids, joints: bool):
        """Rest points, their shape Jacobian and skinning weights of the targets."""
        s0, r0, A, h0, B = self._rest(shape)
        rig = self.rig
        if joints:
            b = rig.jb[ids]
            return s0, h0[b], B[b], h0, B, rig.joint_weights[ids]
        return s0, r0[ids], A[ids], h0, B, rig.weights[ids]

    def _initial_rigid(self, pts, ids, wts, joints: bool, shape):
        """Weighted Kabsch (GM-reweighted) from the rest model to the points: rotation
        about the root's rest position and translation, from the head+torso points."""
        rig = self.rig
        _, rp, _, h0, _, _ = self._problem(shape, ids, joints)
        sel = np.ones(len(pts), bool)
        if not joints:
            torso = np.isin(rig.part_labels[ids], TORSO_PARTS)
            if torso.sum() >= 30:
                sel = torso
        s, d = rp[sel], pts[sel]
        w0 = np.ones(len(s)) if wts is None else wts[sel]
        w = w0
        for sig in (0.3, 0.2, 0.12, 0.08, 0.05, 0.05):
            # Reweighted Kabsch with a shrinking Geman-McClure scale: robust to wrong
            # correspondences, and to the non-rigid (posed) part of the torso region.
            R, t = kabsch(s, d, w)
            r2 = ((s @ R.T + t - d) ** 2).sum(-1)
            w = w0 * objective.gm_weights(r2, sig)
        root = h0[rig.jb[0]]
        return R, t + R @ root - root

    def _initial_segments(self, state, pts, ids, wts, limbs: dict | None = None):
        """Per-segment closed-form initialisation (in the spirit of smplfitter): parents
        first, each fitted joint's world rotation is the GM-reweighted rotation-only
        Kabsch of its segment's rest points about the joint onto the observed points
        (the joint position follows from the parents). Segments with too few points
        keep their rest rotation; the solver refines everything afterwards.

        The second start: given `limbs` (the masks this pass returned) and its `state`,
        each of those limb joints (LIMB_JOINTS), short of targets of its own, is
        oriented from the targets of its segment and every segment below it, taken rigid
        at rest, and the joints below it again from theirs (the others keep theirs): a
        thigh hidden behind the folded body then swings its seen shin and foot towards
        their points instead of leaving the leg hanging at rest, out of the robust
        kernel's reach (measured with true correspondences on the broad-pose validation
        frames: 39.4 -> 32.8 mm, EXPERIMENTS.md).

        Returns:
            (state, masks): masks, {joint: (N,) bool} for each limb joint short of
            targets of its own with enough below it (left at rest without `limbs`),
            selects those targets.
        """
        rig = self.rig
        rot, transl, shape = state
        _, rp, _, h0, _, _ = self._problem(shape, ids, False)
        seg = rig.segment_of_vertex[ids]
        rot = rot.copy()
        masks = {}
        for j in rig.joint_order:
            if limbs is not None:  # the second start: the limbs' joints only
                if j in limbs:
                    m = masks[j] = limbs[j]
                elif not any(rig.desc[k, rig.jb[j]] for k in limbs):
                    continue
                elif (m := seg == j).sum() < SEGMENT_MIN_TARGETS:
                    continue
            elif (m := seg == j).sum() < SEGMENT_MIN_TARGETS:
                if self._limb[j]:
                    limb = rig.desc[j, rig.jb[seg]] > 0  # the targets of the limb below j
                    if limb.sum() >= LIMB_MIN_TARGETS:
                        masks[j] = limb
                continue
            G, x = rig.fk(rot, h0)
            b = rig.jb[j]
            src, dst = rp[m] - h0[b], pts[m] - transl - x[b]
            if np.linalg.norm(src - src.mean(0), axis=1).mean() < 0.03:
                continue  # too small to orient
            w0 = np.ones(len(src)) if wts is None else wts[m]
            w = w0
            for sig in (0.15, 0.08, 0.05):
                Hm = (src * w[:, None]).T @ dst
                U, _, Vt = np.linalg.svd(Hm)
                R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
                w = w0 * objective.gm_weights(((src @ R.T - dst) ** 2).sum(-1), sig)
            Gp = G[rig.jparent[j]]
            rot[j] = Gp.T @ R
        return (rot, transl, shape), masks

    # ------------------------------------------------------------------ API
    def fit(self, points, vertex_ids, init: BodyParams | None = None, **kw) -> FitResult:
        """Fit to points with correspondences (see `_fit`; BLAS single-threaded inside)."""
        with _single_threaded_blas():
            return self._fit(points, vertex_ids, init, **kw)

    def _fit(self, points, vertex_ids, init: BodyParams | None = None, *,
             solver: str | None = None, iterations: int | None = None,
             fix_shape: bool | None = None, weights=None,
             targets_are_joints: bool = False, free_space: FreeSpace | None = None,
             temporal_weight: float = 0.0, tangent_weight: float | None = None,
             give_up_m: float | None = None) -> FitResult:
        """Fit to points with correspondences.

        Args:
            points: (N, 3) camera-frame points (numpy or torch), metres.
            vertex_ids: (N,) template vertex per point (joint index if targets_are_joints).
            init: warm start (tracking); None = cold start from the data.
            solver: 'fast' | 'lbfgs' (default cfg.solver), or 'none': the initialisation
                alone (the warm start, or the data-driven cold start), for reference.
            iterations: override the solver's iteration count.
            fix_shape: keep init's shape (default: True when warm-started).
            weights: optional (N,) per-point confidence.
            free_space: the frame's free space (fit.freespace): vertices the sensor
                would have seen are pulled to where they could hide
                (cfg.free_space_weight; the fast solver only).
            temporal_weight: with a warm start, weight (per rad^2) of every joint's
                rotation away from init's (the fast solver only): tracking's temporal
                prior (FitConfig.lambda_temporal).
            tangent_weight: override cfg.tangent_weight for this fit (the pipeline's
                refit to nearest-vertex correspondences uses cfg.icp_tangent_weight).
            give_up_m: a cold fit (the fast solver) whose first run leaves a median target
                residual above this is returned as it is: no turned restart, no free
                space, no completion (a blob no body explains, not worth the rest); with
                it, no second start for the limbs either.

        Returns:
            FitResult.
        """
        t0 = time.perf_counter()
        cfg, body = self.cfg, self.body
        solver = solver or cfg.solver
        tw = cfg.tangent_weight if tangent_weight is None else float(tangent_weight)
        pts_all = np.asarray(points.cpu() if torch.is_tensor(points) else points, np.float64)
        ids_all = np.asarray(vertex_ids.cpu() if torch.is_tensor(vertex_ids) else vertex_ids,
                             np.int64)
        if pts_all.ndim != 2 or pts_all.shape[1] != 3 or ids_all.shape != pts_all.shape[:1]:
            raise ValueError('points must be (N, 3) and vertex_ids (N,)')
        if len(ids_all) < 10:
            raise ValueError(f'too few correspondences to fit ({len(ids_all)})')
        wts_all = None if weights is None else np.asarray(weights, np.float64)
        if targets_are_joints:
            pts, ids, wts = pts_all, ids_all, wts_all
        else:
            sel = slice(None)
            if len(ids_all) > MAX_RAW_POINTS:  # a few dozen pixels per vertex are plenty
                sel = self._rng.choice(len(ids_all), MAX_RAW_POINTS, replace=False)
            pts, ids, wts = aggregate_by_vertex(pts_all[sel], ids_all[sel],
                                                None if wts_all is None else wts_all[sel],
                                                spread_m=self.spread_m,
                                                min_points=cfg.min_cell_points,
                                                template=self._template)
            if len(ids) > cfg.max_points:
                sel = self._rng.permutation(len(ids))[:cfg.max_points]
                pts, ids, wts = pts[sel], ids[sel], wts[sel]
        warm = init is not None
        fix_shape = warm if fix_shape is None else fix_shape
        limb_start = None  # cold fits: the second start, limbs oriented from below
        if warm:
            rot = rodrigues(np.concatenate([np.asarray(init.global_orient, np.float64)[None],
                                            np.asarray(init.pose, np.float64)]))
            transl = np.asarray(init.transl, np.float64).copy()
            shape = np.asarray(init.shape, np.float64).copy()
        else:
            shape = self.rig.shape_mean.copy()
            rot = np.repeat(np.eye(3)[None], body.num_pose_joints + 1, 0)
            rot[0], transl = self._initial_rigid(pts, ids, wts, targets_are_joints, shape)
            if self.cfg.segment_init and not targets_are_joints:
                (rot, transl, shape), short = self._initial_segments((rot, transl, shape),
                                                                     pts, ids, wts)
                if self.cfg.limb_init and short and give_up_m is None and solver == 'fast':
                    # (Not for a blob the caller gives up on early, one beside a person
                    # found: a second start lets a piece of the scene pass as a person.)
                    limb_start = self._initial_segments((rot, transl, shape), pts, ids,
                                                        wts, limbs=short)
        state, sq = (rot, transl, shape), None
        if solver == 'none':  # the initialisation alone (a benchmark reference)
            iters = 0
        elif solver == 'lbfgs':
            state, iters = lbfgs(body, cfg, state, pts, ids, wts, targets_are_joints,
                                  iterations or cfg.lbfgs_iterations, fix_shape)
        elif solver == 'fast':
            n = iterations or (cfg.tracking_iterations if warm else cfg.iterations)
            s0 = None if warm else cfg.gm_sigma_start
            start = state
            anchor = (rot.copy(), float(temporal_weight)) if warm and temporal_weight > 0 \
                else None
            state, en, iters, sq = self._levenberg_marquardt(
                state, pts, ids, wts, targets_are_joints, n, fix_shape, s0, anchor=anchor,
                tangent_weight=tw)
            if give_up_m is not None and not warm and np.sqrt(np.median(sq)) > give_up_m:
                return self._result(state, (pts, ids, wts, sq), pts_all, ids_all,
                                    targets_are_joints, iters, t0, solver, warm)
            if limb_start is not None and max(
                    np.median(sq[m]) for m in limb_start[1].values()) > LIMB_EXPLAINED_M ** 2:
                # A limb's targets the first start left unexplained: solve from the
                # second start too, and keep the lower energy (as the turned restart).
                alt, en2, it2, sq2 = self._levenberg_marquardt(
                    limb_start[0], pts, ids, wts, False, n, fix_shape, s0, tangent_weight=tw)
                iters += it2
                if en2 < en:
                    state, en, sq, start = alt, en2, sq2, limb_start[0]
            if not warm and cfg.flip_restart and not targets_are_joints:
                # Depth-only correspondences can confuse front and back: when the fit
                # leaves a large residual, also try the init turned 180 deg about the
                # body's vertical axis and keep the lower energy.
                if np.sqrt(np.median(sq)) > cfg.flip_residual_m:
                    alt, en2, it2, sq2 = self._levenberg_marquardt(
                        self._flipped(start, pts), pts, ids, wts, False, n, fix_shape, s0,
                        tangent_weight=tw)
                    if en2 < en:
                        state, sq = alt, sq2
                    iters += it2
            if (free_space is not None and cfg.free_space_weight > 0 and not targets_are_joints
                    and self._free_sq(state, free_space) >= FREE_SQ_MIN):
                # Then the free space: parts the sensor would have seen are moved to where
                # they can hide (a refinement: from a cold start, most of the body is
                # "in free space" and the pulls would only scramble the pose).
                state, _, it2, sq = self._levenberg_marquardt(
                    state, pts, ids, wts, False, cfg.free_space_iterations, True, None,
                    free_space, anchor=anchor, tangent_weight=tw)
                iters += it2
            if not warm and cfg.complete_hidden and not targets_are_joints:
                # Last, the joints nothing moved (held at rest so far) take their likeliest
                # pose given the fitted ones (after the free space: measured less
                # sensitive to the prior's draw, val_s2 30.8 / 30.8 mm for two seeds
                # against 30.9 / 31.3 before it).
                done = self._complete_hidden(state, ids, wts)
                if done is not state:
                    state, sq = done, None  # the held joints may move a few targets
        else:
            raise ValueError(f"unknown solver {solver!r} (expected 'fast', 'lbfgs' or 'none')")
        return self._result(state, (pts, ids, wts, sq), pts_all, ids_all, targets_are_joints,
                            iters, t0, solver, warm)

    def fit_joints(self, joints, init: BodyParams | None = None, **kw) -> FitResult:
        """Baseline (paper Table II row 1): fit to 3D joint positions (J, 3), model order."""
        joints = np.asarray(joints)
        return self.fit(joints, np.arange(len(joints)), init, targets_are_joints=True, **kw)

    def _vertices(self, state):
        """The whole posed mesh (V, 3), exact at the state's shape, and the posed bone
        heads without translation (Jb, 3)."""
        rig = self.rig
        rot, transl, shape = state
        _, r0, _, h0, _ = self._rest(shape)
        G, x = rig.fk(rot, h0)
        verts = rig.skin_points(rig.weights, G, x, h0, r0 + self._pose_offsets(rot, None))
        return verts + transl, x

    def _free_sq(self, state, free: FreeSpace) -> float:
        """Sum of the squared distances of the vertices in free space to their targets."""
        v = self._vertices(state)[0]
        i, t = free.targets(v)
        return float(((v[i] - t) ** 2).sum())

    def _complete_hidden(self, state, ids, wts):
        """The state with its unsupported joints (cfg.min_joint_support) set to their
        conditional mean given the others under the learned pose Gaussian."""
        rig = self.rig
        prob = self._problem(state[2], ids, False)
        hidden = self._joint_support(prob[5], wts) < self.cfg.min_joint_support
        if not hidden.any() or hidden.all():
            return state
        rot = state[0].copy()
        canon = log(rot[1:]) @ rig.C.T
        new = self._pose_gaussian.complete(canon, hidden)
        rot[1:][hidden] = rodrigues(new[hidden] @ rig.C)
        return rot, state[1], state[2]

    def _flipped(self, state, pts):
        """The state turned 180 deg about the body's up axis, through the points' centroid."""
        rot, transl, shape = state
        rig = self.rig
        up = rot[0] @ rig.C.T @ np.array([0.0, 1.0, 0.0])
        F = rodrigues(up * np.pi)
        root = self._rest(shape)[3][rig.jb[0]]
        c = pts.mean(0)
        rot = rot.copy()
        rot[0] = F @ rot[0]
        # New root position: rotate the current root position about the centroid.
        return rot, F @ (root + transl - c) + c - root, shape
    # ------------------------------------------------------------------ result
    def _result(self, state, targets, pts_all, ids_all, joints, iters, t0, solver,
                warm) -> FitResult:
        """FitResult: energy on the solver's targets, residuals of every input point."""
        rig = self.rig
        rot, transl, shape = state
        pts, ids, wts, sq = targets
        if sq is None:
            sq = self._evaluate(state, pts, ids, joints)[0]
        en, data, aa, _ = self._energy_terms(state, sq, wts, self.cfg.gm_sigma)
        verts, x = self._vertices(state)
        model = (x[rig.jb] + transl)[ids_all] if joints else verts[ids_all]
        sq = ((model - pts_all) ** 2).sum(-1)
        f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
        bp = BodyParams(pose=f32(aa), shape=f32(shape), global_orient=f32(log(rot[0])),
                        transl=f32(transl))
        return FitResult(params=bp, vertices=f32(verts), joints=f32(x[rig.jb] + transl),
                         residuals=f32(np.sqrt(sq)), data_term=data, energy=en,
                         iterations=iters, time_ms=(time.perf_counter() - t0) * 1e3,
                         solver=solver, warm=warm)
