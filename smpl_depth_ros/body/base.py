"""The body-model interface shared by the anny and SMPL backends (no ROS).

Conventions:
  * metres; every backend works in its own model frame, and `canonical_rotation` maps it
    to the canonical frame used across the package: x = the person's left, y = up,
    z = forward (the direction the body faces), i.e. SMPL's frame.
  * pose: axis-angle per fitted joint, (B, P, 3), in the model frame, world-aligned and
    relative to the parent (`G_c = G_p R_c`); global orientation (B, 3) rotates the body
    about the root joint's rest position; translation (B, 3) is added afterwards.
    All-zero pose, orientation and translation give the rest mesh.
  * shape: (B, S); `shape_mean` is the neutral body, `shape_bounds` is None for an
    unbounded space (SMPL betas) or (lo, hi) for a box (anny phenotypes in [0, 1]).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from smpl_depth_ros.body import lbs

# Generic joint names shared by the backends (SMPL order; a backend may use a subset).
GENERIC_JOINTS = (
    'pelvis', 'left_hip', 'right_hip', 'spine1', 'left_knee', 'right_knee', 'spine2',
    'left_ankle', 'right_ankle', 'spine3', 'left_foot', 'right_foot', 'neck',
    'left_collar', 'right_collar', 'head', 'left_shoulder', 'right_shoulder',
    'left_elbow', 'right_elbow', 'left_wrist', 'right_wrist', 'left_hand', 'right_hand',
)

# Canonical-frame joint limits in degrees: (min, max) for rotation about the canonical
# x (lateral, flexion), y (vertical, twist) and z (forward, ab/adduction) axes.
_DEFAULT_LIMIT = ((-30, 30), (-30, 30), (-30, 30))
JOINT_LIMITS_DEG = {
    'left_hip': ((-125, 30), (-40, 40), (-25, 70)),
    'right_hip': ((-125, 30), (-40, 40), (-70, 25)),
    'left_knee': ((-5, 150), (-15, 15), (-10, 10)),
    'right_knee': ((-5, 150), (-15, 15), (-10, 10)),
    'left_ankle': ((-40, 45), (-20, 20), (-25, 25)),
    'right_ankle': ((-40, 45), (-20, 20), (-25, 25)),
    'left_foot': ((-20, 20), (-10, 10), (-10, 10)),
    'right_foot': ((-20, 20), (-10, 10), (-10, 10)),
    'spine1': ((-20, 45), (-25, 25), (-20, 20)),
    'spine2': ((-15, 35), (-25, 25), (-15, 15)),
    'spine3': ((-15, 30), (-25, 25), (-15, 15)),
    'neck': ((-30, 40), (-45, 45), (-25, 25)),
    'head': ((-30, 40), (-45, 45), (-25, 25)),
    'left_collar': ((-15, 15), (-20, 20), (-10, 25)),
    'right_collar': ((-15, 15), (-20, 20), (-25, 10)),
    'left_shoulder': ((-120, 70), (-90, 90), (-60, 120)),
    'right_shoulder': ((-120, 70), (-90, 90), (-120, 60)),
    'left_elbow': ((-150, 150), (-150, 150), (-150, 150)),
    'right_elbow': ((-150, 150), (-150, 150), (-150, 150)),
    'left_wrist': ((-70, 70), (-40, 40), (-60, 60)),
    'right_wrist': ((-70, 70), (-40, 40), (-60, 60)),
    'left_hand': ((-20, 20), (-20, 20), (-20, 20)),
    'right_hand': ((-20, 20), (-20, 20), (-20, 20)),
}


@dataclass
class BodyOutput:
    """Posed body.

    Attributes:
        vertices: (B, V', 3) posed vertices (V' = V, or len(vertex_ids) when given).
        joints: (B, J, 3) posed joints, J = 1 + P (root first), order of `joint_names`.
    """

    vertices: torch.Tensor
    joints: torch.Tensor


class BodyModel(torch.nn.Module):
    """Base class: a stateless module of buffers. Subclasses fill the attributes below.

    Attributes:
        name: backend name ('anny' or 'smpl').
        joint_names: J generic joint names, root first; `pose` covers joint_names[1:].
        joint_parents: (J,) parent index within joint_names (-1 for the root).
        shape_names: S shape-parameter names.
        faces: (F, 3) int64 buffer.
        part_labels: (V,) int64 buffer, body-part class ids 1..14.
        valid_vertices: (V,) bool buffer, vertices used for matching and metrics.
        canonical_rotation: (3, 3) buffer, model frame -> canonical frame.
    """

    name: str = 'base'
    joint_names: tuple[str, ...] = ()
    shape_names: tuple[str, ...] = ()

    # -- properties ------------------------------------------------------------------
    @property
    def num_pose_joints(self) -> int:
        return len(self.joint_names) - 1

    @property
    def num_shape(self) -> int:
        return len(self.shape_names)

    @property
    def num_vertices(self) -> int:
        return int(self.template_vertices.shape[0])

    @property
    def device(self) -> torch.device:
        return self.faces.device

    @property
    def dtype(self) -> torch.dtype:
        return self.template_vertices.dtype

    @property
    def shape_bounds(self) -> tuple[float, float] | None:
        return None

    # -- the forward -----------------------------------------------------------------
    def forward(self, pose: torch.Tensor, shape: torch.Tensor,
                global_orient: torch.Tensor | None = None,
                transl: torch.Tensor | None = None,
                vertex_ids: torch.Tensor | None = None) -> BodyOutput:
        """Pose the body.

        Args:
            pose: (B, P, 3) axis-angle, model frame.
            shape: (B, S).
            global_orient: (B, 3) axis-angle about the root's rest position, or None.
            transl: (B, 3) metres, or None.
            vertex_ids: optional (K,) long; only these vertices are computed.

        Returns:
            BodyOutput with vertices (B, V or K, 3) and joints (B, J, 3).
        """
        B = pose.shape[0]
        if pose.shape[1:] != (self.num_pose_joints, 3):
            raise ValueError(f'pose must be (B, {self.num_pose_joints}, 3), '
                             f'got {tuple(pose.shape)}')
        if shape.shape != (B, self.num_shape):
            raise ValueError(f'shape must be (B, {self.num_shape}), got {tuple(shape.shape)}')
        z = pose.new_zeros(B, 3)
        global_orient = z if global_orient is None else global_orient
        transl = z if transl is None else transl
        rest_vertices, rest_joints = self.rest(shape, vertex_ids)
        rot = lbs.axis_angle_to_matrix(torch.cat([global_orient[:, None], pose], 1))
        vertices, joints = self.pose_rest(rest_vertices, rest_joints, rot, vertex_ids)
        return BodyOutput(vertices=vertices + transl[:, None], joints=joints + transl[:, None])

    # -- to implement ----------------------------------------------------------------
    def rest(self, shape: torch.Tensor, vertex_ids: torch.Tensor | None = None):
        """Rest (unposed) vertices (B, V|K, 3) and skeleton heads for the given shape."""
        raise NotImplementedError

    def pose_rest(self, rest_vertices, rest_joints, rot, vertex_ids):
        """Skin rest geometry with per-joint rotations rot (B, 1 + P, 3, 3)."""
        raise NotImplementedError

    def canonical_vertices(self) -> np.ndarray:
        """(V, 3) mean-shape T-pose template in the canonical frame (for the embedding)."""
        raise NotImplementedError

    def rest_linear(self, shape: torch.Tensor, vertex_ids: torch.Tensor | None = None):
        """First-order model of the rest geometry around `shape` (1, S).

        Returns rest vertices (N, 3), their shape Jacobian (N, 3, S), rest heads (Jb, 3) and
        their Jacobian (Jb, 3, S). Exact for SMPL (linear in betas) and within a linear
        piece of anny's phenotype mapping. Default: one-sided finite differences, batched.
        """
        eps = 1e-3
        lo_hi = self.shape_bounds
        s0 = shape[0]
        step = torch.full_like(s0, eps)
        if lo_hi is not None:  # step inwards near the upper bound
            step = torch.where(s0 + eps > lo_hi[1], -step, step)
        batch = torch.cat([s0[None], s0[None] + torch.diag(step)], 0)
        rv, heads = self.rest(batch, vertex_ids)
        A = ((rv[1:] - rv[:1]) / step[:, None, None]).permute(1, 2, 0)
        B = ((heads[1:] - heads[:1]) / step[:, None, None]).permute(1, 2, 0)
        return rv[0], A, heads[0], B

    # -- helpers shared by all backends -----------------------------------------------
    def zero_params(self, batch_size: int = 1) -> dict[str, torch.Tensor]:
        """Neutral parameters: rest pose, mean shape, at the origin."""
        kw = dict(device=self.device, dtype=self.dtype)
        return dict(pose=torch.zeros(batch_size, self.num_pose_joints, 3, **kw),
                    shape=self.shape_mean.to(**kw).expand(batch_size, -1).clone(),
                    global_orient=torch.zeros(batch_size, 3, **kw),
                    transl=torch.zeros(batch_size, 3, **kw))

    def limits_canonical(self) -> torch.Tensor:
        """(P, 3, 2) joint limits in radians, canonical axes, for joint_names[1:]."""
        lim = [JOINT_LIMITS_DEG.get(n, _DEFAULT_LIMIT) for n in self.joint_names[1:]]
        return torch.deg2rad(torch.tensor(lim, dtype=self.dtype, device=self.device))

    def pose_to_canonical(self, pose: torch.Tensor) -> torch.Tensor:
        """Axis-angle vectors (..., 3) from the model frame to canonical axes."""
        return pose @ self.canonical_rotation.T

    def pose_from_canonical(self, pose: torch.Tensor) -> torch.Tensor:
        return pose @ self.canonical_rotation

    def faces_numpy(self) -> np.ndarray:
        return self.faces.detach().cpu().numpy().astype(np.int32)
