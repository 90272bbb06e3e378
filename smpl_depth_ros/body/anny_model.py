"""anny backend: the embedded default body model (Apache-2.0 code, CC0 MakeHuman assets).

Topology `notoes_collapse10pc` (1,229 vertices, 2,454 triangles) with the
`anny-notoes-nohands` rig (38 bones), linear blend skinning. The model data ship inside
the package (smpl_depth_ros/data/anny_*.safetensors, 5.6 MB, written by
`python -m smpl_depth_ros.tools.export_anny`), so nothing is built or downloaded at run
time: loading takes milliseconds instead of anny's ~100 s first construction.

Pose and skinning are ours (body.lbs), on anny's rest geometry: rest vertices and bone
heads are anny's linear blendshapes of the phenotype coefficients, which come from anny's
own piecewise-linear phenotype mapping. Tests check the result against anny's forward.
"""
from __future__ import annotations

import json
import os
from importlib import resources

import numpy as np
import torch

from smpl_depth_ros.body import lbs
from smpl_depth_ros.body.base import BodyModel

RIG = 'anny-notoes-nohands'
TOPOLOGY = 'notoes_collapse10pc'
DATA_NAME = 'anny_notoes_nohands_collapse10pc'

# Generic joint -> anny bone. Everything else (twist bones, spine04/02, neck02/03,
# shoulder01, pelvis.L/R, eyes) is held at rest.
JOINT_BONES = {
    'pelvis': 'root',
    'left_hip': 'upperleg01.L', 'right_hip': 'upperleg01.R',
    'spine1': 'spine05',
    'left_knee': 'lowerleg01.L', 'right_knee': 'lowerleg01.R',
    'spine2': 'spine03',
    'left_ankle': 'foot.L', 'right_ankle': 'foot.R',
    'spine3': 'spine01',
    'neck': 'neck01',
    'left_collar': 'clavicle.L', 'right_collar': 'clavicle.R',
    'head': 'head',
    'left_shoulder': 'upperarm01.L', 'right_shoulder': 'upperarm01.R',
    'left_elbow': 'lowerarm01.L', 'right_elbow': 'lowerarm01.R',
    'left_wrist': 'wrist.L', 'right_wrist': 'wrist.R',
}

# Bone -> part class id (see body.parts.PART_NAMES), by prefix; '.L'/'.R' chooses the side.
_PART_OF_BONE = [
    ('neck', 1), ('head', 1), ('eye', 1),
    ('root', 2), ('pelvis', 2), ('spine', 2), ('clavicle', 2), ('shoulder', 2),
    ('upperarm', 3), ('lowerarm', 5), ('wrist', 7), ('upperleg', 9), ('lowerleg', 11),
    ('foot', 13),
]

# anny: Z up, facing -Y, left +X  ->  canonical: y up, facing +z, left +x.
ANNY_TO_CANONICAL = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=np.float64)


def bone_part(bone: str) -> int:
    for prefix, part in _PART_OF_BONE:
        if bone.startswith(prefix):
            return part + (1 if bone.endswith('.R') and part > 2 else 0)
    raise KeyError(bone)


def data_path(name: str = DATA_NAME) -> str:
    env = os.environ.get('SMPL_DEPTH_ROS_ANNY_DATA')
    if env:
        return env
    return str(resources.files('smpl_depth_ros') / 'data' / f'{name}.safetensors')


def load_anny_module(path: str | None = None):
    """anny.Anny from the shipped model data (no cache build, no download)."""
    import anny
    from anny.models.model_data import ModelData, RigConfig

    rc = RigConfig.from_string(RIG)
    data = ModelData.load_safetensors(path or data_path())
    return anny.Anny.from_model_data(
        data, skinning_method='lbs', pose_parameterization='local-ref',
        bone_orientation=rc.bone_orientation,
        root_identity_orientation=rc.root_identity_orientation)


class AnnyBody(BodyModel):
    """anny as a BodyModel. Shape = the 6 phenotypes in [0, 1]."""

    name = 'anny'

    def __init__(self, path: str | None = None, dtype: torch.dtype = torch.float32):
        super().__init__()
        path = path or data_path()
        m = load_anny_module(path).to(dtype=torch.float64)
        with open(path.replace('.safetensors', '.json')) as f:
            meta = json.load(f)
        self._anny = m  # only for the phenotype -> blendshape-coefficient mapping
        bones = list(m.bone_labels)
        bone_parents = [int(p) for p in m.bone_parents]
        self.bone_names = tuple(bones)
        self.shape_names = tuple(m.phenotype_labels)
        self.joint_names = tuple(JOINT_BONES)
        jb = [bones.index(JOINT_BONES[n]) for n in self.joint_names]
        # Parent of each fitted joint within the fitted set.
        jparents = []
        for b in jb:
            p = bone_parents[b]
            while p >= 0 and p not in jb:
                p = bone_parents[p]
            jparents.append(jb.index(p) if p >= 0 else -1)
        self.register_buffer('joint_parents', torch.tensor(jparents), persistent=False)
        self.register_buffer('joint_bones', torch.tensor(jb), persistent=False)
        self.register_buffer('bone_parents', torch.tensor([max(p, 0) for p in bone_parents]),
                             persistent=False)
        self._levels = lbs.kinematic_levels(bone_parents)

        faces = m.get_triangular_faces().long()
        self.register_buffer('faces', faces, persistent=False)
        self.register_buffer('template_vertices', m.template_vertices.clone(), persistent=False)
        self.register_buffer('blendshapes', m.blendshapes.clone(), persistent=False)
        self.register_buffer('template_heads', m.template_bone_heads.clone(), persistent=False)
        self.register_buffer('heads_blendshapes', m.bone_heads_blendshapes.clone(),
                             persistent=False)
        self.register_buffer('skin_weights', m.vertex_bone_weights.clone(), persistent=False)
        self.register_buffer('skin_indices', m.vertex_bone_indices.long(), persistent=False)
        # Parts: dominant part by summed skinning weight.
        bone_part_ids = torch.tensor([bone_part(b) for b in bones])
        acc = torch.zeros(len(m.template_vertices), 15, dtype=torch.float64)
        acc.scatter_add_(1, bone_part_ids[self.skin_indices], self.skin_weights)
        self.register_buffer('part_labels', acc.argmax(1), persistent=False)
        self.register_buffer('valid_vertices', torch.ones(len(acc), dtype=torch.bool),
                             persistent=False)
        self.register_buffer('canonical_rotation', torch.tensor(ANNY_TO_CANONICAL),
                             persistent=False)
        self.register_buffer('shape_mean', torch.tensor(meta['shape_mean']), persistent=False)
        self.register_buffer('shape_std', torch.tensor(meta['shape_std']), persistent=False)
        self.to(dtype=dtype)

    @property
    def shape_bounds(self):
        return (0.0, 1.0)

    def _apply(self, fn, *args, **kwargs):
        # Keep the helper anny module on the same device/dtype as our buffers.
        super()._apply(fn, *args, **kwargs)
        self._anny._apply(fn, *args, **kwargs)
        return self

    def blend_coefficients(self, shape: torch.Tensor) -> torch.Tensor:
        m = self._anny
        B = shape.shape[0]
        empty = shape.new_zeros(B, 0)
        return m._get_phenotype_blendshape_coefficients(shape, empty, empty)

    def rest(self, shape, vertex_ids=None):
        c = self.blend_coefficients(shape)
        if vertex_ids is None:
            tv, bs = self.template_vertices, self.blendshapes
        else:
            tv, bs = self.template_vertices[vertex_ids], self.blendshapes[:, vertex_ids]
        verts = tv + torch.einsum('ba,avk->bvk', c, bs)
        heads = self.template_heads + torch.einsum('ba,ajk->bjk', c, self.heads_blendshapes)
        return verts, heads

    def skeleton_pose(self, rot, rest_heads):
        """World rotations G (B, Jb, 3, 3) and posed heads x (B, Jb, 3) of every bone,
        from fitted-joint rotations rot (B, J, 3, 3); unfitted bones stay at rest."""
        B = rot.shape[0]
        eye = torch.eye(3, dtype=rot.dtype, device=rot.device)
        full = eye.expand(B, len(self.bone_names), 3, 3).clone()
        full[:, self.joint_bones] = rot
        return lbs.forward_kinematics(full, rest_heads, self.bone_parents, self._levels)

    def pose_rest(self, rest_vertices, rest_heads, rot, vertex_ids=None):
        G, x = self.skeleton_pose(rot, rest_heads)
        if vertex_ids is None:
            w, idx = self.skin_weights, self.skin_indices
        else:
            w, idx = self.skin_weights[vertex_ids], self.skin_indices[vertex_ids]
        verts = lbs.skin(rest_vertices, G, x, rest_heads, w, idx)
        return verts, x[:, self.joint_bones]

    def canonical_vertices(self) -> np.ndarray:
        """Mean-shape T-pose (arms raised to horizontal), canonical frame."""
        with torch.no_grad():
            p = self.zero_params(1)
            _, heads = self.rest(p['shape'])
            C = self.canonical_rotation
            jn = list(self.joint_names)
            hc = heads[0] @ C.T
            pose = torch.zeros_like(p['pose'])
            for side, s in (('left', 1.0), ('right', -1.0)):
                sh = hc[self.joint_bones[jn.index(f'{side}_shoulder')]]
                el = hc[self.joint_bones[jn.index(f'{side}_elbow')]]
                d = el - sh
                ang = torch.atan2(-d[1], abs(d[0]))  # angle below horizontal
                rv = torch.tensor([0.0, 0.0, s], dtype=d.dtype, device=d.device) * ang
                pose[0, jn.index(f'{side}_shoulder') - 1] = self.pose_from_canonical(rv)
            out = self(pose, p['shape'])
            return (out.vertices[0] @ C.T).cpu().numpy()
