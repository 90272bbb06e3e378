"""Forward kinematics and linear blend skinning shared by the body backends (torch only)."""
from __future__ import annotations

import torch


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Rodrigues: (..., 3) axis-angle -> (..., 3, 3), smooth (and differentiable) at 0."""
    theta2 = (rotvec * rotvec).sum(-1, keepdim=True)[..., None]  # (..., 1, 1)
    small = theta2 < 1e-8
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = theta2_safe.sqrt()
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2_safe)
    x, y, z = rotvec.unbind(-1)
    o = torch.zeros_like(x)
    K = torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(rotvec.shape[:-1] + (3, 3))
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand_as(K)
    return eye + a * K + b * (K @ K)


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation -> (..., 3) axis-angle (via quaternions, stable near pi)."""
    import roma
    return roma.rotmat_to_rotvec(R)


def kinematic_levels(parents: list[int]) -> list[torch.Tensor]:
    """Group joints by depth so FK takes one batched product per level."""
    depth = [0] * len(parents)
    for j, p in enumerate(parents):
        depth[j] = 0 if p < 0 else depth[p] + 1
    return [torch.tensor([j for j in range(len(parents)) if depth[j] == d])
            for d in range(max(depth) + 1)]


def forward_kinematics(rot: torch.Tensor, heads: torch.Tensor, parents: torch.Tensor,
                       levels: list[torch.Tensor]):
    """World rotations and posed heads.

    G_c = G_p R_c;  x_c = x_p + G_p (h_c - h_p);  root: G_0 = R_0, x_0 = h_0.

    Args:
        rot: (B, J, 3, 3) local rotations (world-aligned, relative to the parent).
        heads: (B, J, 3) rest joint positions.
        parents: (J,) long, root's parent arbitrary.
        levels: from kinematic_levels.

    Returns:
        G (B, J, 3, 3), x (B, J, 3).
    """
    B, J = rot.shape[:2]
    G = rot.new_empty(B, J, 3, 3)
    x = heads.new_empty(B, J, 3)
    r0 = levels[0]
    G[:, r0] = rot[:, r0]
    x[:, r0] = heads[:, r0]
    for lv in levels[1:]:
        p = parents[lv]
        Gp = G[:, p]
        G[:, lv] = Gp @ rot[:, lv]
        x[:, lv] = x[:, p] + (Gp @ (heads[:, lv] - heads[:, p])[..., None])[..., 0]
    return G, x


def skin(rest_vertices: torch.Tensor, G: torch.Tensor, x: torch.Tensor, heads: torch.Tensor,
         weights: torch.Tensor, indices: torch.Tensor | None = None) -> torch.Tensor:
    """Linear blend skinning.

    v' = sum_k w_k (G_k (v - h_k) + x_k)

    Args:
        rest_vertices: (B, V, 3).
        G, x: (B, J, 3, 3), (B, J, 3) from forward_kinematics; heads (B, J, 3) rest heads.
        weights: (V, K) sparse weights with `indices` (V, K) bone ids, or dense (V, J)
            when indices is None.
    """
    t = x - (G @ heads[..., None])[..., 0]  # (B, J, 3): v' = G v + t
    A = torch.cat([G, t[..., None]], -1)  # (B, J, 3, 4)
    if indices is None:
        Av = torch.einsum('vj,bjrc->bvrc', weights, A)
    else:
        Av = (A[:, indices] * weights[None, :, :, None, None]).sum(2)  # (B, V, 3, 4)
    return (Av[..., :3] @ rest_vertices[..., None])[..., 0] + Av[..., 3]


def forward_kinematics_tangent(G: torch.Tensor, dheads: torch.Tensor, parents: torch.Tensor,
                               levels: list[torch.Tensor]) -> torch.Tensor:
    """Derivative of the posed heads w.r.t. the rest heads, rotations held fixed.

    dx_c = dx_p + G_p (dh_c - dh_p), dx_root = dh_root.

    Args:
        G: (J, 3, 3) world rotations (from forward_kinematics, batch removed).
        dheads: (J, 3, S) rest-head tangents for S directions.

    Returns:
        (J, 3, S) posed-head tangents.
    """
    dx = torch.empty_like(dheads)
    dx[levels[0]] = dheads[levels[0]]
    for lv in levels[1:]:
        p = parents[lv]
        dx[lv] = dx[p] + G[p] @ (dheads[lv] - dheads[p])
    return dx
