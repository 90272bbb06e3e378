"""The body model's kinematics in float64 numpy (no ROS): rotations (axis-angle <->
matrix), the weighted Kabsch alignment, the skeleton (`Rig`: forward kinematics, linear
blend skinning) and vertex normals - what the fast solver and the fitter's initialisation
evaluate.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from smpl_depth_ros.body.base import BodyModel


def kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray):
    """Weighted rigid transform (R, t) minimising sum w |R src + t - dst|^2."""
    w = w / w.sum()
    cs, cd = w @ src, w @ dst
    H = ((src - cs) * w[:, None]).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs


def rodrigues(v: np.ndarray) -> np.ndarray:
    """(..., 3) axis-angle -> (..., 3, 3)."""
    return Rotation.from_rotvec(v.reshape(-1, 3)).as_matrix().reshape(v.shape[:-1] + (3, 3))


def log(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 3) axis-angle."""
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-2] + (3,))


class Rig:
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


def facing_camera(vertices, faces, cos_max: float) -> np.ndarray | None:
    """(V,) bool: the vertices of a fitted mesh that face the camera (the cosine of
    their normal and the view ray below `cos_max`, e.g. fit.icp_front_cos), or None when
    that is 1 (any vertex). A pixel sees the front of the surface: the ICP step, the
    pixels the network left out (refine) and the see-through share (freespace) use
    these only."""
    if cos_max >= 1.0:
        return None
    v = np.asarray(vertices, np.float64)
    ray = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
    return (vertex_normals(v, faces) * ray).sum(1) < cos_max
