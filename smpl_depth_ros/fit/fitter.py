"""Fitting the body model to back-projected depth points with known correspondences.

Two solvers minimise the same objective (fit.objective):

* 'fast' (default), in float64 numpy on the CPU (a few hundred targets and a few dozen
  bones: numpy's per-call overhead is a fraction of torch's at that size):
  1. targets: the points are aggregated per corresponded vertex (`aggregate_by_vertex`:
     robust median, weight = count x coherence), at most `max_points` of them;
  2. cold start: GM-reweighted Kabsch of the head+torso targets for the global rotation
     and translation, then a per-segment closed-form rotation for every fitted joint,
     parents first (in the spirit of smplfitter);
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
"""
from __future__ import annotations

import contextlib
import copy
import time
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from smpl_depth_ros.body.base import BodyModel
from smpl_depth_ros.config import FitConfig
from smpl_depth_ros.fit import objective
from smpl_depth_ros.fit.freespace import FreeSpace
from smpl_depth_ros.fit.pose_prior import PoseGaussian
from smpl_depth_ros.types import BodyParams

TORSO_PARTS = (1, 2)  # head + torso: the most rigid region, used for the rigid init
MAX_RAW_POINTS = 20000  # input points aggregated per fit (a random subset beyond that)
SPREAD_M = 0.02  # aggregate_by_vertex's coherence scale (widened for noisy sensors)
RELIN_TOL = 0.03  # shape change that triggers a re-linearisation of the rest geometry
FREE_SQ_MIN = 0.02  # m^2: summed squared free-space distances that call for the refinement
                    # (exact fits to noisy val_s2 frames leave <= 0.005; 0.02 is e.g. 8
                    # vertices 5 cm out, or 2 at 10 cm)
REST_CACHE_SIZE = 4  # shapes whose rest linearisation is kept (tracking reuses one)
FREEZE = 1e3  # Hessian diagonal that holds an unsupported joint (data terms are O(1))


def backproject(depth: np.ndarray, K: np.ndarray, mask: np.ndarray | None = None):
    """Pixels to 3D points (paper: p_i from the intrinsic matrix).

    Args:
        depth: (H, W) float32 metres, 0/NaN invalid.
        K: (3, 3) intrinsics.
        mask: optional (H, W) bool, pixels to keep.

    Returns:
        points (N, 3) float32 camera frame, pixels (N, 2) int (row, col).
    """
    valid = np.isfinite(depth) & (depth > 0)
    if mask is not None:
        valid &= mask
    r, c = np.nonzero(valid)
    z = depth[r, c].astype(np.float64)
    x = (c - K[0, 2]) * z / K[0, 0]
    y = (r - K[1, 2]) * z / K[1, 1]
    return np.stack([x, y, z], 1).astype(np.float32), np.stack([r, c], 1)


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


def _kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray):
    """Weighted rigid transform (R, t) minimising sum w |R src + t - dst|^2."""
    w = w / w.sum()
    cs, cd = w @ src, w @ dst
    H = ((src - cs) * w[:, None]).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs


def _group_median(values: np.ndarray, grp: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Median of `values` within contiguous groups `grp` (sorted), group bounds lo/hi."""
    span = max(float(values.max() - values.min()), 1e-9)
    # Sort by (group, value) with one argsort: the values map into [0, 1).
    xs = values[np.argsort(grp + (values - values.min()) / (span * (1 + 1e-6)), kind='stable')]
    return 0.5 * (xs[lo] + xs[hi])


def aggregate_by_vertex(points: np.ndarray, ids: np.ndarray, weights: np.ndarray | None = None,
                        spread_m: float = 0.02, min_points: int = 2,
                        template: np.ndarray | None = None, tolerance_m: float = 0.05):
    """One robust target per corresponded vertex.

    Many pixels share a vertex (a 1,229-vertex template spans ~3 cm between vertices):
    the median of its cell of points sits near the vertex itself, whereas single pixels
    scatter by the vertex spacing plus sensor noise. The target is the coordinate-wise
    median of the vertex's points; its weight is their number (or summed weights) times
    1 / (1 + (d / spread_m)^2), d = the median distance of the points to the target, and
    0 beyond d > 3 spread_m: a coherent cell keeps its weight, a cell made of scattered
    wrong correspondences (e.g. a hidden vertex that only wrong pixels name) is dropped -
    a small weight would still drag a limb that nothing else constrains.

    A cell also needs `min_points` points once the typical cell (the count-weighted
    median) holds twice that: a visible vertex collects a patch of pixels, whereas
    isolated wrong correspondences scatter over hundreds of otherwise empty cells, each a
    perfectly "coherent" singleton. With 30 % wrong correspondences those singletons
    carried 15-55 % of the total weight. Given the `template` (rest vertex positions), a
    small cell is kept when it agrees with its nearest full cell instead: their vertices
    are at most their observed distance + `tolerance_m` apart on the template (a genuine
    sparse cell, e.g. a limb edge, sits beside its template neighbours).

    Returns:
        targets (M, 3), vertex ids (M,), weights (M,).
    """
    ids = np.asarray(ids, np.int64)
    order = np.argsort(ids, kind='stable')
    uniq, start, counts = np.unique(ids[order], return_index=True, return_counts=True)
    lo, hi = start + (counts - 1) // 2, start + counts // 2
    grp = np.repeat(np.arange(len(uniq)), counts)
    p = np.asarray(points, np.float64)[order]
    out = np.stack([_group_median(p[:, c], grp, lo, hi) for c in range(3)], 1)
    spread = _group_median(np.linalg.norm(p - out[grp], axis=1), grp, lo, hi)
    w = counts.astype(np.float64) if weights is None else \
        np.bincount(grp, np.asarray(weights, np.float64)[order], len(uniq))
    w = w / (1.0 + (spread / spread_m) ** 2)
    keep = spread <= 3 * spread_m
    cs = np.sort(counts)
    typical = cs[np.searchsorted(np.cumsum(cs), 0.5 * cs.sum())]
    small = counts < min_points
    if typical >= 2 * min_points and small.any():
        full = keep & ~small
        if template is not None and full.sum() >= 3:
            d, nn = cKDTree(out[full]).query(out[small])
            far = np.linalg.norm(template[uniq[small]] - template[uniq[full][nn]], axis=1)
            keep[small] &= far <= d + tolerance_m
        else:
            keep &= ~small
    return out[keep], uniq[keep], w[keep]


def _rodrigues(v: np.ndarray) -> np.ndarray:
    """(..., 3) axis-angle -> (..., 3, 3)."""
    return Rotation.from_rotvec(v.reshape(-1, 3)).as_matrix().reshape(v.shape[:-1] + (3, 3))


def _log(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 3) axis-angle."""
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-2] + (3,))


def _anchor_energy(rot: np.ndarray, anchor) -> float:
    """Temporal prior: weight * sum of the squared angles between `rot` (P + 1, 3, 3) and
    the anchor's rotations; anchor = (rotations, weight)."""
    return anchor[1] * float((_log(rot @ anchor[0].transpose(0, 2, 1)) ** 2).sum())


# Levi-Civita: (a x b)_c = eps[c, b_, d] a_b b_d.
_EPS = np.zeros((3, 3, 3))
for _c, _b, _d in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _EPS[_c, _b, _d], _EPS[_c, _d, _b] = 1.0, -1.0


class _Rig:
    """The body model's kinematic structure as float64 numpy arrays (fast solver).

    The fast solver works on a few hundred points and a few dozen bones: numpy on the CPU
    has a fraction of torch's per-call overhead at that size, so the solver runs in numpy
    whatever device the network uses.
    """

    def __init__(self, body: BodyModel):
        f = lambda t: t.detach().cpu().double().numpy()  # noqa: E731
        self.parents = body.bone_parents.cpu().numpy()
        self.levels = [lv.cpu().numpy() for lv in body._levels]
        self.jb = body.joint_bones.cpu().numpy()
        nb = len(self.parents)
        # Parent bone of each fitted joint's bone; -1 for the root (its parent frame is I).
        self.jparent = np.array([self.parents[b] if b != 0 else -1 for b in self.jb])
        # Descendant-or-self mask: fitted joint -> bones its rotation moves.
        desc = np.zeros((len(self.jb), nb))
        for j, b in enumerate(self.jb):
            for k in range(nb):
                a = k
                while True:
                    if a == b:
                        desc[j, k] = 1
                        break
                    if a == 0:
                        break
                    a = self.parents[a]
        self.desc = desc
        w = f(body.skin_weights)
        if body.skin_indices is None:
            self.weights = w
        else:  # sparse (V, K) -> dense (V, bones)
            self.weights = np.zeros((len(w), nb))
            np.add.at(self.weights, (np.arange(len(w))[:, None],
                                     body.skin_indices.cpu().numpy()), w)
        # Joint targets (baseline): a bone head moves rigidly with its parent bone.
        self.joint_weights = np.eye(nb)[[self.parents[b] if b != 0 else 0 for b in self.jb]]
        self.C = f(body.canonical_rotation)
        self.limits = f(body.limits_canonical())
        self.shape_mean, self.shape_std = f(body.shape_mean), f(body.shape_std)
        self.bounds = body.shape_bounds
        self.part_labels = body.part_labels.cpu().numpy()
        # Segment of every bone: the nearest fitted joint at or above it (unfitted bones
        # stay at rest, so a segment moves rigidly with its joint); fitted joints in
        # kinematic order (parents first) for the per-segment initialisation.
        owner = {int(b): j for j, b in enumerate(self.jb)}
        seg = np.zeros(nb, np.int64)
        depth = np.zeros(nb, np.int64)
        for lv_depth, lv in enumerate(self.levels):
            depth[lv] = lv_depth
        for b in range(nb):
            a = b
            while a not in owner and a != 0:
                a = self.parents[a]
            seg[b] = owner.get(a, 0)
        self.segment_of_vertex = seg[self.weights.argmax(1)]
        self.joint_order = [int(j) for j in np.argsort(depth[self.jb], kind='stable') if j]

    def fk(self, rot: np.ndarray, heads: np.ndarray):
        """Fitted-joint rotations (J, 3, 3) and rest heads (Jb, 3) -> world rotations
        G (Jb, 3, 3) and posed heads x (Jb, 3) (lbs.forward_kinematics in numpy)."""
        G = np.empty((len(self.parents), 3, 3))
        G[:] = np.eye(3)
        G[self.jb] = rot
        x = np.empty_like(heads)
        r0 = self.levels[0]
        x[r0] = heads[r0]
        for lv in self.levels[1:]:
            p = self.parents[lv]
            x[lv] = x[p] + np.einsum('nij,nj->ni', G[p], heads[lv] - heads[p])
            G[lv] = G[p] @ G[lv]
        return G, x

    def fk_tangent(self, G: np.ndarray, dheads: np.ndarray) -> np.ndarray:
        """d(posed heads)/d(rest heads) for (Jb, 3, S) tangents (rotations fixed)."""
        dx = np.empty_like(dheads)
        dx[self.levels[0]] = dheads[self.levels[0]]
        for lv in self.levels[1:]:
            p = self.parents[lv]
            dx[lv] = dx[p] + G[p] @ (dheads[lv] - dheads[p])
        return dx

    @staticmethod
    def skin_points(W, G, x, heads, rest_pts):
        """Posed points only (no per-bone terms): the blended transforms sum_b W_nb [G_b|t_b]
        applied to each point, ~5x cheaper than `skin` for a whole mesh."""
        tb = x - np.einsum('bij,bj->bi', G, heads)
        M = W @ np.concatenate([G, tb[:, :, None]], 2).reshape(len(G), 12)
        M = M.reshape(len(rest_pts), 3, 4)
        return np.einsum('nij,nj->ni', M[:, :, :3], rest_pts) + M[:, :, 3]

    @staticmethod
    def skin(W, G, x, heads, rest_pts):
        """Posed points v_n = sum_b WQ_nb, with the weighted per-bone terms
        WQ_nb = W_nb (G_b r_n + x_b - G_b h_b) (N, Jb, 3) that the Jacobian reuses."""
        tb = x - np.einsum('bij,bj->bi', G, heads)
        WQ = (rest_pts @ G.reshape(-1, 3).T).reshape(len(rest_pts), -1, 3)
        WQ += tb
        WQ *= W[:, :, None]
        return WQ.sum(1), WQ


def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3)."""
    fn = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    n = np.zeros_like(verts)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


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


class Fitter:
    """Fits a BodyModel to points with correspondences. Stateless apart from caches.

    Args:
        body: the body model (anny or SMPL backend).
        cfg: objective weights and solver settings.
    """

    def __init__(self, body: BodyModel, cfg: FitConfig = FitConfig()):
        self.body = body
        self.cfg = cfg
        self.rig = _Rig(body)
        self._rest_cache: dict[bytes, tuple] = {}
        self._rng = np.random.default_rng(0)
        # Rest vertices at the mean shape: the template for the target consistency check.
        self._template = self._rest(self.rig.shape_mean)[1]
        self._rest_normals = vertex_normals(self._template, body.faces_numpy())
        self._weak = objective.weak_joint_mask(body).astype(np.float64)
        # Built here, not on the first frame (0.3 s, once per process and body model).
        self._pose_gaussian = PoseGaussian.for_body(body) if cfg.complete_hidden else None
        self.spread_m = SPREAD_M
        self._noisy: dict[int, 'Fitter'] = {}

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

    def joint_frames(self, params: BodyParams) -> tuple[np.ndarray, np.ndarray]:
        """World rotations (J, 3, 3) and positions (J, 3) of the fitted joints (root
        first, the order of `FitResult.joints`) for `params`: the joints' frames for TF."""
        rig = self.rig
        rot = _rodrigues(np.concatenate([np.asarray(params.global_orient, np.float64)[None],
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
            R, t = _kabsch(s, d, w)
            r2 = ((s @ R.T + t - d) ** 2).sum(-1)
            w = w0 * objective.gm_weights(r2, sig)
        root = h0[rig.jb[0]]
        return R, t + R @ root - root

    def _initial_segments(self, state, pts, ids, wts):
        """Per-segment closed-form initialisation (in the spirit of smplfitter): parents
        first, each fitted joint's world rotation is the GM-reweighted rotation-only
        Kabsch of its segment's rest points about the joint onto the observed points
        (the joint position follows from the parents). Segments with too few points
        keep their rest rotation; the solver refines everything afterwards."""
        rig = self.rig
        rot, transl, shape = state
        _, rp, _, h0, _, _ = self._problem(shape, ids, False)
        seg = rig.segment_of_vertex[ids]
        rot = rot.copy()
        for j in rig.joint_order:
            m = seg == j
            if m.sum() < 20:
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
        return rot, transl, shape

    # ------------------------------------------------------------------ API
    def fit(self, points, vertex_ids, init: BodyParams | None = None, **kw) -> FitResult:
        """Fit to points with correspondences (see `_fit`; BLAS single-threaded inside)."""
        with _single_threaded_blas():
            return self._fit(points, vertex_ids, init, **kw)

    def _fit(self, points, vertex_ids, init: BodyParams | None = None, *,
             solver: str | None = None, iterations: int | None = None,
             fix_shape: bool | None = None, weights=None,
             targets_are_joints: bool = False, free_space: FreeSpace | None = None,
             temporal_weight: float = 0.0, tangent_weight: float | None = None) -> FitResult:
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
        if warm:
            rot = _rodrigues(np.concatenate([np.asarray(init.global_orient, np.float64)[None],
                                             np.asarray(init.pose, np.float64)]))
            transl = np.asarray(init.transl, np.float64).copy()
            shape = np.asarray(init.shape, np.float64).copy()
        else:
            shape = self.rig.shape_mean.copy()
            rot = np.repeat(np.eye(3)[None], body.num_pose_joints + 1, 0)
            rot[0], transl = self._initial_rigid(pts, ids, wts, targets_are_joints, shape)
            if self.cfg.segment_init and not targets_are_joints:
                rot, transl, shape = self._initial_segments((rot, transl, shape), pts, ids,
                                                            wts)
        state, sq = (rot, transl, shape), None
        if solver == 'none':  # the initialisation alone (a benchmark reference)
            iters = 0
        elif solver == 'lbfgs':
            state, iters = self._lbfgs(state, pts, ids, wts, targets_are_joints,
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

    # ------------------------------------------------------------------ fast solver
    def _evaluate(self, state, pts, ids, joints: bool, prob=None):
        """Squared residuals (N,) and everything the Jacobian needs at one state."""
        rot, transl, shape = state
        s0, rp, A, h0, B, W = prob or self._problem(shape, ids, joints)
        ds = shape - s0
        rest = rp + A @ ds
        if not joints:
            rest = rest + self._pose_offsets(rot, ids)
        heads = h0 + B @ ds
        G, x = self.rig.fk(rot, heads)
        v, WQ = self.rig.skin(W, G, x, heads, rest)
        e = v + transl - pts
        return (e * e).sum(-1), e, G, x, WQ

    def _energy_terms(self, state, sq, wts, sigma):
        """Objective (Eq. 3-4) from squared residuals; also the pose-prior pieces."""
        cfg, rig = self.cfg, self.rig
        rot, _, shape = state
        aa = _log(rot[1:])
        viol = objective.limit_violation(aa @ rig.C.T, rig.limits)
        rho = objective.geman_mcclure(sq, sigma)
        data = rho.mean() if wts is None else (rho * wts).sum() / wts.sum()
        en = (cfg.lambda_data * data + cfg.lambda_pose * (viol ** 2).sum()
              + (self._pose_l2_weights()[:, None] * aa ** 2).sum()
              + cfg.lambda_shape * (((shape - rig.shape_mean) / rig.shape_std) ** 2).sum())
        return float(en), float(data), aa, viol

    def _jacobian(self, state, prob, G, x, WQ, free_shape: bool) -> np.ndarray:
        """Jacobian of the residuals v + t - p at `state` (G, x, WQ from `_evaluate`):
        (N, 3, n) over the rotation increments R_j <- exp(delta_j) R_j of every joint
        (root first), the translation, and with `free_shape` the shape (through the local
        linearisation `prob`). Pose-dependent offsets (SMPL pose blend shapes) are left out.
        """
        rig = self.rig
        P = len(rig.jb) - 1
        S = len(rig.shape_mean)
        n_rot = 3 * (P + 1)
        n = n_rot + 3 + (S if free_shape else 0)
        _, _, A, _, B, W = prob
        N = W.shape[0]
        # Rotation columns: d v / d delta_j = (Gp_j delta) x u_j,
        # u_j = sum over bones moved by joint j of W (G_b r + t_b - x_j).
        U = (rig.desc @ WQ.transpose(1, 0, 2).reshape(W.shape[1], -1)).reshape(
            P + 1, N, 3) - (W @ rig.desc.T).T[:, :, None] * x[rig.jb][:, None, :]
        Gp = np.where(rig.jparent[:, None, None] >= 0, G[rig.jparent], np.eye(3))
        # cross(Gp_j e_a, u)_c = sum_d T[j, d, (c, a)] u_d.
        T = np.einsum('cbd,jba->jdca', _EPS, Gp).reshape(P + 1, 3, 9)
        Jr = (U @ T).reshape(P + 1, N, 3, 3).transpose(1, 2, 0, 3).reshape(N, 3, n_rot)
        Jd = np.empty((N, 3, n))
        Jd[:, :, :n_rot] = Jr
        Jd[:, :, n_rot:n_rot + 3] = np.eye(3)
        if free_shape:
            # d v / d s = sum_b W (G_b (A - B_b) + dx_b), dx from tangent FK.
            dx = rig.fk_tangent(G, B)
            Cb = dx - G @ B  # (Jb, 3, S)
            M = (W @ G.reshape(len(G), 9)).reshape(N, 3, 3)
            Jd[:, :, n_rot + 3:] = M @ A + (W @ Cb.reshape(len(G), -1)).reshape(N, 3, S)
        return Jd

    def _levenberg_marquardt(self, state, pts, ids, wts, joints: bool, iterations: int,
                             fix_shape: bool, sigma_start: float | None = None,
                             free: FreeSpace | None = None, anchor=None,
                             tangent_weight: float | None = None):
        """IRLS / Levenberg-Marquardt on the robust objective.

        Rotations are updated multiplicatively (R_j <- exp(delta_j) R_j) with the analytic
        LBS Jacobian; translation additively; shape through the exact local linearisation
        of the rest geometry (re-linearised when it moves: anny's phenotype mapping is
        piecewise linear). With `free`, vertices in free space are pulled (L2,
        cfg.free_space_weight per mesh vertex) to their nearest hiding place, found again
        at every evaluated state (ICP-style). With `anchor` = (rotations (P + 1, 3, 3),
        weight), every joint's rotation away from the anchor's costs weight * angle^2 (the
        temporal prior of tracking). `tangent_weight`: cfg.tangent_weight unless given.
        Returns (state, energy at the final scale,
        iterations, squared residuals at that state).
        """
        cfg, rig = self.cfg, self.rig
        s_end = cfg.gm_sigma
        s_start = max(sigma_start or s_end, s_end)

        def sigma_at(it):
            # Graduated non-convexity: a wide robust kernel first (big basin), then the
            # final scale, reached half-way through the iterations.
            f = min(1.0, (it - 1) / max(iterations / 2, 1))
            return s_start * (s_end / s_start) ** f
        P = len(rig.jb) - 1
        S = len(rig.shape_mean)
        n_rot = 3 * (P + 1)
        lam_p, lam_s = cfg.lambda_pose, cfg.lambda_shape
        lam_l2 = self._pose_l2_weights()  # (P,)
        N = len(pts)
        wsum = float(N) if wts is None else float(wts.sum())
        prob = self._problem(state[2], ids, joints)
        # Cold fits to surface points hold the shape for the first third (pose first:
        # shape steps taken while the pose is far off are noise, and each shape move
        # costs a re-linearisation); joint targets fix bone lengths from the start.
        hold = 0 if sigma_start is None or joints else iterations // 3
        # Joints whose rotation moves (almost) no target are held where they are: with no
        # data, a few wrong correspondences (or none) would swing an unseen limb anywhere.
        # Free-space targets (when given) count as support too: they do constrain a limb.
        support = self._joint_support(prob[5], wts) if not joints else None
        mu, prev, prev_sigma, it = 1e-3, None, None, 0
        tw = cfg.tangent_weight if tangent_weight is None else tangent_weight
        aniso = tw < 1 and not joints
        for it in range(1, iterations + 1):
            free_shape = not fix_shape and it > hold
            n = n_rot + 3 + (S if free_shape else 0)
            if free_shape and np.abs(state[2] - prob[0]).max() > RELIN_TOL:
                prob = self._problem(state[2], ids, joints)  # re-linearise the shape
            sq, e, G, x, WQ = self._evaluate(state, pts, ids, joints, prob)
            nrm, facing = None, 1.0
            if aniso:
                # A vertex that faces away from the camera cannot have been observed: a
                # point on it is a wrong correspondence (IRLS weight only, like the GM's).
                v = pts + e
                sq, e, nrm = self._anisotropic(e, prob[5], G, ids, tw)
                facing = np.where((nrm * v).sum(-1) > 0, cfg.back_facing_weight, 1.0)
            fterm = self._free_space_term(state, prob, G, x, free) if free else None
            sigma = sigma_at(it)
            if prev is not None and sigma != prev_sigma:
                prev = None  # energies at different scales are not comparable
            prev_sigma = sigma
            en, _, aa, viol = self._energy_terms(state, sq, wts, sigma)
            if fterm is not None:
                en += fterm[0]
            if anchor is not None:
                en += _anchor_energy(state[0], anchor)
            if prev is not None and en > prev[0]:
                # Reject the step: restore the last accepted state and damp more (LM).
                en, state, (sq, e, G, x, WQ, nrm, facing, fterm), aa, viol = prev
                mu *= 10
            else:
                mu = max(mu / 3, 1e-6)
                prev = (en, state, (sq, e, G, x, WQ, nrm, facing, fterm), aa, viol)
            rot, transl, shape = state
            # IRLS weights of the Geman-McClure term.
            om = objective.gm_weights(sq, sigma) * facing * cfg.lambda_data / wsum
            if wts is not None:
                om = om * wts
            sw = np.sqrt(om)
            Jd = self._jacobian(state, prob, G, x, WQ, free_shape)
            Jd *= sw[:, None, None]
            Jf = Jd.reshape(-1, n)
            H = Jf.T @ Jf
            if aniso:
                # r = A e_raw with A = a I + (1 - a) n n^T (symmetric): the Gauss-Newton
                # system of r is J^T A^2 J = a^2 J^T J + (1 - a^2) (n.J)^T (n.J) and
                # J^T A r, without forming A J.
                a = tw
                Jn = np.einsum('nd,ndk->nk', nrm, Jd)
                H *= a * a
                H += (1 - a * a) * (Jn.T @ Jn)
                e = a * e + (1 - a) * nrm * (nrm * e).sum(-1, keepdims=True)
            g = Jf.T @ (e * sw[:, None]).reshape(-1)
            if fterm is not None and len(fterm[2]):
                _, w_f, e_f, prob_f, WQ_f = fterm
                Jf = self._jacobian(state, prob_f, G, x, WQ_f, free_shape).reshape(-1, n)
                H += w_f * Jf.T @ Jf
                g += w_f * Jf.T @ e_f.reshape(-1)
            # Pose priors (Jacobian of the canonical axis-angle ~ C for the increment).
            out = (viol != 0).astype(np.float64)
            Jp = out[..., None] * rig.C[None]  # (P, 3, 3), sign irrelevant in H
            Hp = lam_p * Jp.transpose(0, 2, 1) @ Jp + lam_l2[:, None, None] * np.eye(3)
            gp = lam_p * (-Jp.transpose(0, 2, 1) @ viol[..., None])[..., 0] + lam_l2[:, None] * aa
            for j in range(P):
                b = 3 + 3 * j
                H[b:b + 3, b:b + 3] += Hp[j]
            if support is not None:
                sup = support
                if fterm is not None and len(fterm[2]):
                    sup = support + (fterm[3][5] @ rig.desc[1:].T).sum(0)
                for j in np.flatnonzero(sup < cfg.min_joint_support):
                    b = 3 + 3 * j
                    H[b:b + 3, b:b + 3] += FREEZE * np.eye(3)
            g[3:n_rot] += gp.reshape(-1)
            if anchor is not None:  # d log(exp(delta) R R0^T) / d delta ~ I near R0
                dr = _log(rot @ anchor[0].transpose(0, 2, 1))
                H[:n_rot, :n_rot] += anchor[1] * np.eye(n_rot)
                g[:n_rot] += anchor[1] * dr.reshape(-1)
            if free_shape:
                inv2 = lam_s / rig.shape_std ** 2
                H[n_rot + 3:, n_rot + 3:] += np.diag(inv2)
                g[n_rot + 3:] += inv2 * (shape - rig.shape_mean)
            Hd = H + mu * np.diag(np.diag(H)) + 1e-9 * np.eye(n)
            step = -np.linalg.solve(Hd, g)
            rot = _rodrigues(step[:n_rot].reshape(P + 1, 3)) @ rot
            transl = transl + step[n_rot:n_rot + 3]
            if free_shape:
                shape = shape + step[n_rot + 3:]
                if rig.bounds is not None:
                    shape = shape.clip(rig.bounds[0] + 1e-4, rig.bounds[1] - 1e-4)
            state = (rot, transl, shape)
            if np.abs(step).max() < 1e-5:
                break
        # Final state: the better of the last step and the best accepted one.
        prob = self._problem(state[2], ids, joints)
        sq, e, G, x, _ = self._evaluate(state, pts, ids, joints, prob)
        if aniso:
            sq = self._anisotropic(e, prob[5], G, ids, tw)[0]
        en = self._energy_terms(state, sq, wts, s_end)[0]
        if free:
            en += self._free_space_term(state, prob, G, x, free)[0]
        if anchor is not None:
            en += _anchor_energy(state[0], anchor)
        if prev is not None and prev_sigma == s_end and en > prev[0]:
            en, state, sq = prev[0], prev[1], prev[2][0]
        return state, en, it, sq

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

    def _free_space_term(self, state, prob, G, x, free: FreeSpace):
        """The free-space term at `state` (G, x from `_evaluate` with `prob`):
        (energy, weight per residual, residuals (M, 3), the problem and skinning terms of
        the M vertices in free space for `_jacobian`)."""
        rig = self.rig
        rot, transl, shape = state
        s0, _, _, h0, B, _ = prob
        _, r0, A, _, _ = self._rest(s0)
        ds = shape - s0
        heads = h0 + B @ ds
        verts = rig.skin_points(rig.weights, G, x, heads, r0 + A @ ds) + transl
        ids, tgt = free.targets(verts)
        w = self.cfg.free_space_weight / len(verts)
        if not len(ids):
            return 0.0, w, np.zeros((0, 3)), None, None
        prob_f = (s0, r0[ids], A[ids], h0, B, rig.weights[ids])
        _, e, _, _, WQ = self._evaluate(state, tgt, ids, False, prob_f)
        return w * float((e * e).sum()), w, e, prob_f, WQ

    def _anisotropic(self, e, W, G, ids, a: float):
        """Residuals with their component along the surface scaled by the tangent weight
        a: r = a e + (1 - a) n (n . e) with n the posed vertex normal."""
        M = (W @ G.reshape(len(G), 9)).reshape(len(e), 3, 3)
        n = np.einsum('nij,nj->ni', M, self._rest_normals[ids])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        r = a * e + (1 - a) * n * (n * e).sum(-1, keepdims=True)
        return (r * r).sum(-1), r, n

    def _joint_support(self, W, wts):
        """Per pose joint (0-based, root excluded): how many targets' worth of skinning
        weight its rotation moves; joints below cfg.min_joint_support are held."""
        moved = W @ self.rig.desc[1:].T  # (N, P): share of each target moved by joint j
        return (moved if wts is None else moved * (wts / wts.mean())[:, None]).sum(0)

    def _complete_hidden(self, state, ids, wts):
        """The state with its unsupported joints (cfg.min_joint_support) set to their
        conditional mean given the others under the learned pose Gaussian."""
        rig = self.rig
        prob = self._problem(state[2], ids, False)
        hidden = self._joint_support(prob[5], wts) < self.cfg.min_joint_support
        if not hidden.any() or hidden.all():
            return state
        rot = state[0].copy()
        canon = _log(rot[1:]) @ rig.C.T
        new = self._pose_gaussian.complete(canon, hidden)
        rot[1:][hidden] = _rodrigues(new[hidden] @ rig.C)
        return rot, state[1], state[2]

    def _flipped(self, state, pts):
        """The state turned 180 deg about the body's up axis, through the points' centroid."""
        rot, transl, shape = state
        rig = self.rig
        up = rot[0] @ rig.C.T @ np.array([0.0, 1.0, 0.0])
        F = _rodrigues(up * np.pi)
        root = self._rest(shape)[3][rig.jb[0]]
        c = pts.mean(0)
        rot = rot.copy()
        rot[0] = F @ rot[0]
        # New root position: rotate the current root position about the centroid.
        return rot, F @ (root + transl - c) + c - root, shape

    # ------------------------------------------------------------------ reference
    def _lbfgs(self, state, pts, ids, wts, joints, iterations, fix_shape):
        """The paper's solver: PyTorch L-BFGS (strong Wolfe) on axis-angle parameters."""
        cfg, body = self.cfg, self.body
        kw = dict(dtype=body.dtype, device=body.device)
        rot, transl, shape = state
        aa = _log(rot)
        init = dict(pose=aa[None, 1:], global_orient=aa[None, 0], transl=transl[None],
                    shape=shape[None])
        p = {k: torch.tensor(v, **kw).requires_grad_(not (k == 'shape' and fix_shape))
             for k, v in init.items()}
        pts_t, ids_t = torch.as_tensor(pts, **kw), torch.as_tensor(ids, device=body.device)
        wts_t = None if wts is None else torch.as_tensor(wts, **kw)
        opt = torch.optim.LBFGS([v for v in p.values() if v.requires_grad], lr=cfg.lbfgs_lr,
                                max_iter=iterations, line_search_fn='strong_wolfe')

        def closure():
            opt.zero_grad()
            en = objective.energy(body, p, pts_t, ids_t, cfg, wts_t, joints)['total']
            en.backward()
            return en
        with torch.enable_grad():  # whatever the caller's grad mode
            opt.step(closure)
        n_iter = opt.state[opt._params[0]].get('n_iter', iterations)
        f = {k: v.detach().cpu().double().numpy()[0] for k, v in p.items()}
        rot = _rodrigues(np.concatenate([f['global_orient'][None], f['pose']]))
        return (rot, f['transl'], f['shape']), int(n_iter)

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
        bp = BodyParams(pose=f32(aa), shape=f32(shape), global_orient=f32(_log(rot[0])),
                        transl=f32(transl))
        return FitResult(params=bp, vertices=f32(verts), joints=f32(x[rig.jb] + transl),
                         residuals=f32(np.sqrt(sq)), data_term=data, energy=en,
                         iterations=iters, time_ms=(time.perf_counter() - t0) * 1e3,
                         solver=solver, warm=warm)
