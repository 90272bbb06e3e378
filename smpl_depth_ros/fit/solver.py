"""The solvers' iterations on the objective of fit.objective (no ROS).

* `FastSolver`: the 'fast' solver, Levenberg-Marquardt / IRLS in float64 numpy with the
  analytic Jacobian of linear blend skinning (fit.rig). A mixin of fit.fitter.Fitter: it
  evaluates its host's rest geometry (`_rest`, `_problem`, `_pose_offsets`), `rig`,
  `cfg`, `_pose_l2_weights` and `_rest_normals`. Its constants are config.LM_*.
* `lbfgs`: the paper's reference solver, PyTorch L-BFGS on axis-angle parameters.
"""
from __future__ import annotations

import numpy as np
import torch

from smpl_depth_ros.config import (FitConfig, LM_ANNEAL_DIV, LM_DAMPING_DOWN, LM_DAMPING_MIN,
                                   LM_DAMPING_START, LM_DAMPING_UP, LM_FREEZE, LM_RELIN_TOL,
                                   LM_RIDGE, LM_SHAPE_HOLD_DIV, LM_SHAPE_MARGIN, LM_STEP_TOL)
from smpl_depth_ros.fit import objective
from smpl_depth_ros.fit.freespace import FreeSpace
from smpl_depth_ros.fit.rig import log, rodrigues


def _anchor_energy(rot: np.ndarray, anchor) -> float:
    """Temporal prior: weight * sum of the squared angles between `rot` (P + 1, 3, 3) and
    the anchor's rotations; anchor = (rotations, weight)."""
    return anchor[1] * float((log(rot @ anchor[0].transpose(0, 2, 1)) ** 2).sum())


# Levi-Civita: (a x b)_c = eps[c, b_, d] a_b b_d.
_EPS = np.zeros((3, 3, 3))
for _c, _b, _d in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _EPS[_c, _b, _d], _EPS[_c, _d, _b] = 1.0, -1.0


class FastSolver:
    """The fast solver's methods (see the module docstring for what the host provides)."""

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
        aa = log(rot[1:])
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
            f = min(1.0, (it - 1) / max(iterations / LM_ANNEAL_DIV, 1))
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
        hold = 0 if sigma_start is None or joints else iterations // LM_SHAPE_HOLD_DIV
        # Joints whose rotation moves (almost) no target are held where they are: with no
        # data, a few wrong correspondences (or none) would swing an unseen limb anywhere.
        # Free-space targets (when given) count as support too: they do constrain a limb.
        support = self._joint_support(prob[5], wts) if not joints else None
        mu, prev, prev_sigma, it = LM_DAMPING_START, None, None, 0
        tw = cfg.tangent_weight if tangent_weight is None else tangent_weight
        aniso = tw < 1 and not joints
        for it in range(1, iterations + 1):
            free_shape = not fix_shape and it > hold
            n = n_rot + 3 + (S if free_shape else 0)
            if free_shape and np.abs(state[2] - prob[0]).max() > LM_RELIN_TOL:
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
                mu *= LM_DAMPING_UP
            else:
                mu = max(mu / LM_DAMPING_DOWN, LM_DAMPING_MIN)
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
                    H[b:b + 3, b:b + 3] += LM_FREEZE * np.eye(3)
            g[3:n_rot] += gp.reshape(-1)
            if anchor is not None:  # d log(exp(delta) R R0^T) / d delta ~ I near R0
                dr = log(rot @ anchor[0].transpose(0, 2, 1))
                H[:n_rot, :n_rot] += anchor[1] * np.eye(n_rot)
                g[:n_rot] += anchor[1] * dr.reshape(-1)
            if free_shape:
                inv2 = lam_s / rig.shape_std ** 2
                H[n_rot + 3:, n_rot + 3:] += np.diag(inv2)
                g[n_rot + 3:] += inv2 * (shape - rig.shape_mean)
            Hd = H + mu * np.diag(np.diag(H)) + LM_RIDGE * np.eye(n)
            step = -np.linalg.solve(Hd, g)
            rot = rodrigues(step[:n_rot].reshape(P + 1, 3)) @ rot
            transl = transl + step[n_rot:n_rot + 3]
            if free_shape:
                shape = shape + step[n_rot + 3:]
                if rig.bounds is not None:
                    shape = shape.clip(rig.bounds[0] + LM_SHAPE_MARGIN,
                                       rig.bounds[1] - LM_SHAPE_MARGIN)
            state = (rot, transl, shape)
            if np.abs(step).max() < LM_STEP_TOL:
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


def lbfgs(body, cfg: FitConfig, state, pts, ids, wts, joints, iterations, fix_shape):
    """The paper's solver: PyTorch L-BFGS (strong Wolfe) on axis-angle parameters.
    Returns (state, iterations run)."""
    kw = dict(dtype=body.dtype, device=body.device)
    rot, transl, shape = state
    aa = log(rot)
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
    rot = rodrigues(np.concatenate([f['global_orient'][None], f['pose']]))
    return (rot, f['transl'], f['shape']), int(n_iter)
