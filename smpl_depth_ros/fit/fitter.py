"""Fitting the body model to back-projected depth points with known correspondences.

Two solvers minimise the same objective (fit.objective):

* 'fast' (default): data-driven rigid initialisation (weighted Kabsch on the torso
  correspondences, Geman-McClure reweighted), then Levenberg-Marquardt / IRLS iterations
  with an analytic Jacobian of linear blend skinning for rotation increments
  (R_j <- exp(delta_j) R_j) and translation, and a forward-mode Jacobian for shape. Only
  the vertices that have correspondences are skinned (a random subset of at most
  `max_points`). Tracking mode warm-starts from the previous frame, keeps its shape and
  runs a few pose iterations.
* 'lbfgs': the paper's reference - PyTorch L-BFGS, strong Wolfe, lr 0.6, 20 iterations on
  axis-angle parameters, from the same initialisation.

`fit_joints` is the Table II row-1 baseline: the same solver on 3D joint positions.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from smpl_depth_ros.body import lbs
from smpl_depth_ros.body.base import BodyModel
from smpl_depth_ros.config import FitConfig
from smpl_depth_ros.fit import objective
from smpl_depth_ros.types import BodyParams

TORSO_PARTS = (1, 2)  # head + torso: the most rigid region, used for the rigid init


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
        data_term: robust data-term value (mean Geman-McClure, m^2).
        energy: total objective.
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


def _kabsch(src: torch.Tensor, dst: torch.Tensor, w: torch.Tensor):
    """Weighted rigid transform (R, t) minimising sum w |R src + t - dst|^2."""
    w = w / w.sum()
    cs, cd = (w[:, None] * src).sum(0), (w[:, None] * dst).sum(0)
    H = ((src - cs) * w[:, None]).T @ (dst - cd)
    U, _, Vt = torch.linalg.svd(H.double())
    d = torch.sign(torch.det(Vt.T @ U.T))
    D = torch.diag(torch.tensor([1.0, 1.0, float(d)], dtype=torch.float64, device=src.device))
    R = (Vt.T @ D @ U.T).to(src.dtype)
    return R, cd - R @ cs


def _skew_cross_cols(G: torch.Tensor, U: torch.Tensor) -> torch.Tensor:
    """Columns (G e_a) x u for a = 0..2: G (J,3,3), U (J,N,3) -> (N, 3, J*3)."""
    cols = torch.linalg.cross(G.transpose(-1, -2)[:, None, :, :].expand(-1, U.shape[1], -1, -1),
                              U[:, :, None, :].expand(-1, -1, 3, -1), dim=-1)  # (J,N,a,c)
    J, N = U.shape[:2]
    return cols.permute(1, 3, 0, 2).reshape(N, 3, J * 3)


class Fitter:
    """Fits a BodyModel to points with correspondences. Stateless apart from caches.

    Args:
        body: the body model (anny or SMPL backend).
        cfg: objective weights and solver settings.
    """

    def __init__(self, body: BodyModel, cfg: FitConfig = FitConfig()):
        self.body = body
        self.cfg = cfg
        kw = dict(device=body.device, dtype=body.dtype)
        self._limits = body.limits_canonical()
        self._C = body.canonical_rotation.to(**kw)
        # Descendant-or-self mask: fitted joint -> bones moved by its rotation.
        parents = body.bone_parents.tolist()
        nb = len(parents)
        jb = body.joint_bones.tolist()
        D = torch.zeros(len(jb), nb, **kw)
        for j, b in enumerate(jb):
            for k in range(nb):
                a = k
                while True:
                    if a == b:
                        D[j, k] = 1
                        break
                    if a == 0:
                        break
                    a = parents[a]
        self._desc = D
        # Parent bone of each fitted joint's bone (root: itself) for the joint baseline.
        self._joint_parent_bone = torch.tensor([parents[b] if b != 0 else 0 for b in jb],
                                               device=body.device)
        self._gen = torch.Generator().manual_seed(0)

    # ------------------------------------------------------------------ helpers
    def _to_tensor(self, a, dtype=None):
        return torch.as_tensor(np.asarray(a), device=self.body.device,
                               dtype=dtype or self.body.dtype)

    def _params_from(self, init: BodyParams | None) -> dict[str, torch.Tensor]:
        p = self.body.zero_params(1)
        if init is not None:
            p['pose'] = self._to_tensor(init.pose)[None].clone()
            p['shape'] = self._to_tensor(init.shape)[None].clone()
            p['global_orient'] = self._to_tensor(init.global_orient)[None].clone()
            p['transl'] = self._to_tensor(init.transl)[None].clone()
        return p

    def _rest_linear(self, shape, ids, joints: bool):
        """Linearised rest geometry of the fitted points around `shape`.

        Returns (rest0 (N,3), A (N,3,S), heads0 (Jb,3), B (Jb,3,S), w (N,K), idx (N,K)).
        Joint targets are bone heads rigidly attached to their parent bone.
        """
        body = self.body
        if joints:
            _, _, h0, B = body.rest_linear(shape, vertex_ids=ids[:1])
            jb = body.joint_bones[ids]
            w = torch.ones(len(ids), 1, dtype=body.dtype, device=body.device)
            return h0[jb], B[jb], h0, B, w, self._joint_parent_bone[ids][:, None]
        uniq, inv = torch.unique(ids, return_inverse=True)
        r0, A, h0, B = body.rest_linear(shape, vertex_ids=uniq)
        r0, A = r0[inv], A[inv]
        w, idx = body.skin_weights[ids], body.skin_indices
        idx = (torch.arange(w.shape[1], device=w.device).expand(len(ids), -1)
               if idx is None else idx[ids])
        return r0, A, h0, B, w, idx

    def _pose_points(self, rot, rest_pts, w, idx, heads, ids=None):
        """Per-influence and blended posed points (no global translation).

        With `ids` (vertex targets) the backend's pose-corrective offsets (SMPL's pose
        blendshapes) are added to the rest points; their derivative is left out of the
        Jacobian (a small, standard Gauss-Newton approximation).
        """
        body = self.body
        if ids is not None and hasattr(body, 'pose_offsets'):
            rest_pts = rest_pts + body.pose_offsets(rot[None], ids)[0]
        G, x = body.skeleton_pose(rot[None], heads[None])
        G, x = G[0], x[0]
        vk = (G[idx] @ (rest_pts[:, None, :] - heads[idx])[..., None])[..., 0] + x[idx]
        v = (w[..., None] * vk).sum(1)
        return v, vk, G, x

    def _initial_rigid(self, points, ids, part_of_point, joints: bool, shape):
        """Weighted Kabsch (GM-reweighted) from the rest model to the points."""
        body = self.body
        zero = torch.zeros(1, body.num_pose_joints, 3, dtype=body.dtype, device=body.device)
        out = body(zero, shape, vertex_ids=None if joints else ids)
        src = out.joints[0, ids] if joints else out.vertices[0]
        sel = torch.ones(len(points), dtype=torch.bool, device=points.device)
        if part_of_point is not None:
            torso = torch.zeros_like(sel)
            for p in TORSO_PARTS:
                torso |= part_of_point == p
            if int(torso.sum()) >= 30:
                sel = torso
        s, d = src[sel], points[sel]
        w = torch.ones(len(s), dtype=s.dtype, device=s.device)
        for sig in (0.3, 0.2, 0.12, 0.08, 0.05, 0.05):
            # Reweighted Kabsch with a shrinking Geman-McClure scale: robust to wrong
            # correspondences, and to the non-rigid (posed) part of the torso region.
            R, t = _kabsch(s, d, w)
            r2 = ((s @ R.T + t - d) ** 2).sum(-1)
            w = objective.gm_weights(r2, sig)
        root = out.joints[0, 0]
        transl = t + R @ root - root
        return lbs.matrix_to_axis_angle(R), transl

    # ------------------------------------------------------------------ API
    def fit(self, points, vertex_ids, init: BodyParams | None = None, *,
            solver: str | None = None, iterations: int | None = None,
            fix_shape: bool | None = None, weights=None,
            targets_are_joints: bool = False) -> FitResult:
        """Fit to points with correspondences.

        Args:
            points: (N, 3) camera-frame points (numpy or torch), metres.
            vertex_ids: (N,) template vertex per point (joint index if targets_are_joints).
            init: warm start (tracking); None = cold start from the data.
            solver: 'fast' | 'lbfgs' (default cfg.solver).
            iterations: override the solver's iteration count.
            fix_shape: keep init's shape (default: True when warm-started).
            weights: optional (N,) per-point confidence.

        Returns:
            FitResult.
        """
        t0 = time.perf_counter()
        cfg, body = self.cfg, self.body
        solver = solver or cfg.solver
        pts_all = self._to_tensor(points)
        ids_all = torch.as_tensor(np.asarray(vertex_ids), device=body.device).long()
        if pts_all.ndim != 2 or pts_all.shape[1] != 3 or ids_all.shape != pts_all.shape[:1]:
            raise ValueError('points must be (N, 3) and vertex_ids (N,)')
        if len(ids_all) < 10:
            raise ValueError(f'too few correspondences to fit ({len(ids_all)})')
        wts_all = None if weights is None else self._to_tensor(weights)
        sel = torch.arange(len(ids_all), device=body.device)
        if len(sel) > cfg.max_points and not targets_are_joints:
            sel = torch.randperm(len(sel), generator=self._gen)[:cfg.max_points].to(body.device)
        pts, ids = pts_all[sel], ids_all[sel]
        wts = None if wts_all is None else wts_all[sel]
        warm = init is not None
        fix_shape = warm if fix_shape is None else fix_shape
        params = self._params_from(init)
        if not warm:
            part = None if targets_are_joints else body.part_labels[ids]
            go, tr = self._initial_rigid(pts, ids, part, targets_are_joints, params['shape'])
            params['global_orient'], params['transl'] = go[None], tr[None]
        if solver == 'lbfgs':
            params, iters = self._lbfgs(params, pts, ids, wts, targets_are_joints,
                                        iterations or cfg.lbfgs_iterations, fix_shape)
        elif solver == 'fast':
            n = iterations or (cfg.tracking_iterations if warm else cfg.iterations)
            start = {k: v.clone() for k, v in params.items()}
            s0 = None if warm else cfg.gm_sigma_start
            params, iters = self._gauss_newton(params, pts, ids, wts, targets_are_joints, n,
                                               fix_shape, s0)
            if not warm and cfg.flip_restart and not targets_are_joints:
                # Depth-only correspondences can confuse front and back: when the fit
                # leaves a large residual, also try the init turned 180 deg about the
                # body's vertical axis and keep the lower energy.
                med = float(self._median_residual(params, pts, ids))
                if med > cfg.flip_residual_m:
                    alt = self._flipped(start, pts)
                    alt, it2 = self._gauss_newton(alt, pts, ids, wts, False, n, fix_shape, s0)
                    if self._energy(alt, pts, ids, wts, False) < \
                            self._energy(params, pts, ids, wts, False):
                        params = alt
                    iters += it2
        else:
            raise ValueError(f"unknown solver {solver!r} (expected 'fast' or 'lbfgs')")
        return self._result(params, pts_all, ids_all, wts_all, targets_are_joints, iters,
                            t0, solver, warm)

    def fit_joints(self, joints, init: BodyParams | None = None, **kw) -> FitResult:
        """Baseline (paper Table II row 1): fit to 3D joint positions (J, 3), model order."""
        joints = np.asarray(joints)
        return self.fit(joints, np.arange(len(joints)), init, targets_are_joints=True, **kw)

    # ------------------------------------------------------------------ solvers
    def _gauss_newton(self, params, pts, ids, wts, joints: bool, iterations: int,
                      fix_shape: bool, sigma_start: float | None = None):
        cfg, body = self.cfg, self.body
        s_end = cfg.gm_sigma
        s_start = max(sigma_start or s_end, s_end)

        def sigma_at(it):
            # Graduated non-convexity: a wide robust kernel first (big basin), then the
            # final scale, reached half-way through the iterations.
            f = min(1.0, (it - 1) / max(iterations / 2, 1))
            return s_start * (s_end / s_start) ** f
        P, S = body.num_pose_joints, body.num_shape
        rot = lbs.axis_angle_to_matrix(
            torch.cat([params['global_orient'][:, None], params['pose']], 1))[0]  # (J,3,3)
        transl = params['transl'][0].clone()
        shape = params['shape'].clone()
        n_rot = 3 * (P + 1)
        n = n_rot + 3 + (0 if fix_shape else S)
        Cm = self._C
        lim = self._limits
        sq_lp, sq_l2, sq_ls = cfg.lambda_pose ** 0.5, cfg.lambda_pose_l2 ** 0.5, \
            cfg.lambda_shape ** 0.5
        mu = 1e-3
        prev = None
        prev_sigma = None
        wsum = float(len(pts)) if wts is None else float(wts.sum())
        r0, A, h0, B, w, idx = self._rest_linear(shape, ids, joints)
        s0 = shape[0].clone()
        vids = None if joints else ids

        def rest_at(sh):
            ds = sh[0] - s0
            return r0 + A @ ds, h0 + B @ ds
        rest_cache = rest_at(shape)

        def evaluate_state(rot, transl, rest_cache):
            """Posed points, residuals and pose-prior terms at one solver state."""
            rp, heads = rest_cache
            v, vk, G, x = self._pose_points(rot, rp, w, idx, heads, vids)
            e = v + transl - pts
            aa = lbs.matrix_to_axis_angle(rot[1:])
            viol = objective.limit_violation(aa @ Cm.T, lim)
            return v, vk, G, x, e, (e * e).sum(-1), aa, viol
        it = 0
        for it in range(1, iterations + 1):
            if not fix_shape:
                if float((shape[0] - s0).abs().max()) > 0.01:
                    # anny's phenotype mapping is piecewise linear: re-linearise.
                    r0, A, h0, B, w, idx = self._rest_linear(shape, ids, joints)
                    s0 = shape[0].clone()
                rest_cache = rest_at(shape)
            st = evaluate_state(rot, transl, rest_cache)
            v, vk, G, x, e, sq, aa, viol = st
            sigma = sigma_at(it)
            if prev is not None and sigma != prev_sigma:
                prev = None  # energies at different scales are not comparable
            prev_sigma = sigma
            rho = objective.geman_mcclure(sq, sigma)
            data = (rho.sum() if wts is None else (rho * wts).sum()) / wsum
            en = (cfg.lambda_data * data + cfg.lambda_pose * (viol ** 2).sum()
                  + cfg.lambda_pose_l2 * (aa ** 2).sum()
                  + cfg.lambda_shape * (((shape[0] - body.shape_mean) / body.shape_std) ** 2).sum())
            if prev is not None and en > prev[0]:
                # Reject the step: restore the last accepted state and damp more (LM).
                _, rot, transl, shape, rest_cache, st = prev
                v, vk, G, x, e, sq, aa, viol = st
                mu *= 10
            else:
                mu = max(mu / 3, 1e-6)
                prev = (en, rot, transl, shape, rest_cache, st)
            # IRLS weights of the Geman-McClure term.
            om = objective.gm_weights(sq, sigma) * cfg.lambda_data / wsum
            if wts is not None:
                om = om * wts
            # Data Jacobian: rotations (analytic), translation (identity), shape (fwd-mode).
            jb = body.joint_bones
            Dm = self._desc[:, idx] * w[None]  # (J, N, K)
            xj = x[jb]  # (J, 3)
            U = torch.einsum('jnk,nkc->jnc', Dm, vk) - Dm.sum(-1)[..., None] * xj[:, None]
            Gp = G[body.bone_parents[jb]].clone()
            Gp[0] = torch.eye(3, dtype=G.dtype, device=G.device)
            Jr = _skew_cross_cols(Gp, U)  # (N, 3, 3J)
            cols = [Jr, torch.eye(3, dtype=e.dtype, device=e.device).expand(len(e), 3, 3)]
            if not fix_shape:
                # d v'/d s = sum_k w_k (G_k (A - B_k) + dx_k), dx from tangent FK.
                dx = lbs.forward_kinematics_tangent(G, B, body.bone_parents, body._levels)
                Js = (G[idx] @ (A[:, None] - B[idx])) + dx[idx]  # (N, K, 3, S)
                cols.append((w[..., None, None] * Js).sum(1))
            Jd = torch.cat(cols, -1)  # (N, 3, n)
            Jw = Jd * om.sqrt()[:, None, None]
            ew = e * om.sqrt()[:, None]
            Jf = Jw.reshape(-1, n)
            H = Jf.T @ Jf
            g = Jf.T @ ew.reshape(-1)
            # Pose priors (Jacobian of the canonical axis-angle ~ C for the increment).
            out = (viol != 0).to(e.dtype)  # (P, 3)
            Jp = -(out[..., None] * Cm[None]) * sq_lp  # (P, 3, 3)
            rp_res = viol * sq_lp
            blk = slice(3, n_rot)
            Hp = torch.zeros(P, 3, 3, dtype=e.dtype, device=e.device)
            Hp += Jp.transpose(-1, -2) @ Jp + (sq_l2 ** 2) * torch.eye(3, dtype=e.dtype,
                                                                       device=e.device)
            gp = (Jp.transpose(-1, -2) @ rp_res[..., None])[..., 0] + (sq_l2 ** 2) * aa
            H[blk, blk] += torch.block_diag(*Hp)
            g[blk] += gp.reshape(-1)
            if not fix_shape:
                sblk = slice(n_rot + 3, n)
                inv = 1.0 / body.shape_std
                H[sblk, sblk] += torch.diag((sq_ls * inv) ** 2)
                g[sblk] += (sq_ls * inv) ** 2 * (shape[0] - body.shape_mean)
            Hd = H + mu * torch.diag(torch.diagonal(H)) + 1e-9 * torch.eye(n, dtype=H.dtype,
                                                                        device=H.device)
            step = -torch.linalg.solve(Hd.double(), g.double()).to(e.dtype)
            dR = lbs.axis_angle_to_matrix(step[:n_rot].reshape(P + 1, 3))
            rot = dR @ rot
            transl = transl + step[n_rot:n_rot + 3]
            if not fix_shape:
                shape = shape + step[n_rot + 3:][None]
                if body.shape_bounds is not None:
                    shape = shape.clamp(body.shape_bounds[0] + 1e-4, body.shape_bounds[1] - 1e-4)
            if float(step.abs().max()) < 1e-5:
                break
        # Final state: the better of the last step and the best accepted one.
        params = self._pack(rot, transl, shape)
        if prev is not None:
            en_last = self._energy(params, pts, ids, wts, joints)
            if en_last > prev[0]:
                params = self._pack(prev[1], prev[2], prev[3])
        return params, it

    def _median_residual(self, params, pts, ids):
        with torch.no_grad():
            uniq, inv = torch.unique(ids, return_inverse=True)
            v = self.body(params['pose'], params['shape'], params['global_orient'],
                          params['transl'], vertex_ids=uniq).vertices[0, inv]
            return ((v - pts) ** 2).sum(-1).sqrt().median()

    def _flipped(self, params, pts):
        """params turned 180 deg about the body's up axis, through the points' centroid."""
        body = self.body
        R = lbs.axis_angle_to_matrix(params['global_orient'][0])
        up = R @ self._C.T @ torch.tensor([0.0, 1.0, 0.0], dtype=R.dtype, device=R.device)
        F = lbs.axis_angle_to_matrix(up * torch.pi)
        with torch.no_grad():
            zero = torch.zeros_like(params['pose'])
            root = body(zero, params['shape']).joints[0, 0]
        c = pts.mean(0)
        out = {k: v.clone() for k, v in params.items()}
        out['global_orient'] = lbs.matrix_to_axis_angle(F @ R)[None]
        # New root position: rotate the current root position about the centroid.
        p_root = root + params['transl'][0]
        out['transl'] = (F @ (p_root - c) + c - root)[None]
        return out

    def _pack(self, rot, transl, shape):
        aa = lbs.matrix_to_axis_angle(rot)
        return dict(pose=aa[None, 1:].contiguous(), global_orient=aa[None, 0].contiguous(),
                    transl=transl[None].clone(), shape=shape.clone())

    def _energy(self, params, pts, ids, wts, joints):
        with torch.no_grad():
            return float(objective.energy(self.body, params, pts, ids, self.cfg, wts,
                                          joints)['total'])

    def _lbfgs(self, params, pts, ids, wts, joints, iterations, fix_shape):
        cfg = self.cfg
        p = {k: v.detach().clone().requires_grad_(not (k == 'shape' and fix_shape))
             for k, v in params.items()}
        opt = torch.optim.LBFGS([v for v in p.values() if v.requires_grad], lr=cfg.lbfgs_lr,
                                max_iter=iterations, line_search_fn='strong_wolfe')

        def closure():
            opt.zero_grad()
            en = objective.energy(self.body, p, pts, ids, cfg, wts, joints)['total']
            en.backward()
            return en
        opt.step(closure)
        n_iter = opt.state[opt._params[0]].get('n_iter', iterations)
        return {k: v.detach() for k, v in p.items()}, int(n_iter)

    def _result(self, params, pts, ids, wts, joints, iters, t0, solver, warm) -> FitResult:
        body, cfg = self.body, self.cfg
        with torch.no_grad():
            out = body(params['pose'], params['shape'], params['global_orient'],
                       params['transl'])
            model = out.joints[0, ids] if joints else out.vertices[0, ids]
            sq = ((model - pts) ** 2).sum(-1)
            en = objective.energy(body, params, pts, ids, cfg, wts, joints)
        f = lambda t: t.detach().cpu().numpy().astype(np.float32)  # noqa: E731
        bp = BodyParams(pose=f(params['pose'][0]), shape=f(params['shape'][0]),
                        global_orient=f(params['global_orient'][0]),
                        transl=f(params['transl'][0]))
        return FitResult(params=bp, vertices=f(out.vertices[0]), joints=f(out.joints[0]),
                         residuals=f(sq.sqrt()), data_term=float(en['data']),
                         energy=float(en['total']), iterations=iters,
                         time_ms=(time.perf_counter() - t0) * 1e3, solver=solver, warm=warm)
