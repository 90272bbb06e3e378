"""smpl backend: the user's own SMPL model file (licence-gated; never shipped or downloaded).

Reads the official `.pkl` (SMPL_NEUTRAL/MALE/FEMALE.pkl,
basicModel_*_lbs_10_207_0_v1.0.0.pkl: Python-2 pickles holding numpy arrays, scipy sparse
matrices and `chumpy` objects) without chumpy, through a restricted unpickler that maps
chumpy classes to a small stand-in exposing the stored array; or an smplx-style `.npz`
(v_template, shapedirs, posedirs, J_regressor, weights, kintree_table, f).

The model (Loper et al. 2015), with betas b (first 10) and per-joint rotations R_k:
    v_shaped = v_template + shapedirs b          J = J_regressor v_shaped
    v_posed  = v_shaped + posedirs vec(R_k - I, k = 1..23)
    G_k = G_parent R_k,  x_k = x_parent + G_parent (J_k - J_parent)   (lbs.forward_kinematics)
    v' = sum_k w_k (G_k (v_posed - J_k) + x_k)                        (lbs.skin, dense weights)
SMPL's frame is the canonical one (y up, facing +z, left +x), so `canonical_rotation` is I.
"""
from __future__ import annotations

import fnmatch
import os
import pickle

import numpy as np
import torch

from smpl_depth_ros.body import lbs
from smpl_depth_ros.body.base import GENERIC_JOINTS, BodyModel
from smpl_depth_ros.body.parts import PART_NAMES

ENV_VAR = 'SMPL_MODEL_PATH'
NUM_BETAS = 10
NUM_JOINTS = 24
# File names looked for inside a directory, in order (case-insensitive globs).
_DIR_CANDIDATES = ('SMPL_NEUTRAL.pkl', 'SMPL_NEUTRAL.npz', 'basicmodel_neutral*.pkl',
                   'basicmodel_neutral*.npz')

# Generic joint -> part (by name: 'left' selects the _l class, 'right' the _r class).
_JOINT_PART = {
    'neck': 'head', 'head': 'head',
    'pelvis': 'torso', 'spine1': 'torso', 'spine2': 'torso', 'spine3': 'torso',
    'left_collar': 'torso', 'right_collar': 'torso',
    'shoulder': 'upper_arm', 'elbow': 'lower_arm', 'wrist': 'hand', 'hand': 'hand',
    'hip': 'upper_leg', 'knee': 'lower_leg', 'ankle': 'foot', 'foot': 'foot',
}


def joint_part(name: str) -> int:
    """Part class id (body.parts.PART_NAMES) of an SMPL joint's segment."""
    if name in _JOINT_PART:
        return PART_NAMES.index(_JOINT_PART[name])
    side, base = name.split('_', 1)
    return PART_NAMES.index(f"{_JOINT_PART[base]}_{'l' if side == 'left' else 'r'}")


# -- finding and reading the model file ------------------------------------------------
def find_model_file(path: str | None = None) -> str:
    """The SMPL model file from `path`, else $SMPL_MODEL_PATH (a file or a directory)."""
    src = path if path else os.environ.get(ENV_VAR)
    how = f'path={path!r}' if path else f'${ENV_VAR}={src!r}'
    hint = (f'pass the model file (or its directory) as `path`/model_path, or set {ENV_VAR}; '
            'SMPL is licence-gated: get SMPL_NEUTRAL.pkl (or basicModel_neutral_lbs_10_207_'
            '0_v1.0.0.pkl) from https://smpl.is.tue.mpg.de yourself')
    if not src:
        raise FileNotFoundError(f'no SMPL model given: neither a path argument nor {ENV_VAR} '
                                f'is set; {hint}')
    src = os.path.expanduser(src)
    if os.path.isfile(src):
        return src
    if os.path.isdir(src):
        for d in (src, os.path.join(src, 'smpl')):
            names = {n.lower(): n for n in (os.listdir(d) if os.path.isdir(d) else ())}
            for pattern in _DIR_CANDIDATES:
                hits = sorted(n for lo, n in names.items()
                              if fnmatch.fnmatch(lo, pattern.lower()))
                if hits:
                    return os.path.join(d, hits[0])
        raise FileNotFoundError(f'no SMPL model in directory {src} ({how}): looked for '
                                f'{", ".join(_DIR_CANDIDATES)} there and in smpl/; {hint}')
    raise FileNotFoundError(f'SMPL model path {src} ({how}) does not exist; {hint}')


class _ChumpyStandIn:
    """Stand-in for every chumpy class when unpickling (chumpy itself is not needed).

    Keeps the pickled state and exposes the array a plain `chumpy.Ch` stores in its `x`
    term, as `.r` and through `np.asarray(obj)`.
    """

    def __setstate__(self, state):
        if isinstance(state, tuple):  # (dict state, slot state)
            state = {**(state[0] or {}), **(state[1] or {})}
        self.__dict__.update(state)

    @property
    def r(self) -> np.ndarray:
        d = self.__dict__
        if 'x' in d:
            x = d['x']
            return x.r if isinstance(x, _ChumpyStandIn) else np.asarray(x)
        cached = (d.get('_cache') or {}).get('r')
        if cached is not None:
            return np.asarray(cached)
        raise ValueError('the SMPL file holds a chumpy expression, not a plain chumpy array; '
                         'convert the model to .npz (e.g. with chumpy installed)')

    def __array__(self, dtype=None, copy=None):
        r = self.r
        return r if dtype is None else r.astype(dtype)


_SAFE_BUILTINS = {'set', 'frozenset', 'list', 'dict', 'tuple', 'object', 'int', 'float',
                  'complex', 'bool', 'str', 'bytes', 'bytearray', 'slice', 'range'}
_SAFE_NUMPY = {'_reconstruct', 'scalar', 'ndarray', 'dtype', '_frombuffer'}


class _SMPLUnpickler(pickle.Unpickler):
    """Loads SMPL pickles without chumpy, and only with the globals such a file needs."""

    def find_class(self, module, name):
        top = module.split('.', 1)[0]
        if top == 'chumpy':
            return _ChumpyStandIn
        if module in ('builtins', '__builtin__') and name in _SAFE_BUILTINS:
            return super().find_class('builtins', name)
        if module in ('copyreg', 'copy_reg') and name in ('_reconstructor', '__newobj__'):
            return super().find_class('copyreg', name)
        if module == '_codecs' and name == 'encode':
            return super().find_class(module, name)
        if top == 'numpy' and name in _SAFE_NUMPY:
            if name in ('ndarray', 'dtype'):
                return getattr(np, name)
            try:  # numpy >= 2 moved numpy.core to numpy._core
                return super().find_class(module.replace('numpy.core', 'numpy._core'), name)
            except (ImportError, AttributeError):
                return super().find_class(module, name)
        if module.startswith('scipy.sparse'):
            import scipy.sparse as sp
            cls = getattr(sp, name, None)  # old private module paths: scipy.sparse.csc, ...
            if isinstance(cls, type):
                return cls
        raise pickle.UnpicklingError(f'refusing global {module}.{name} in an SMPL model file')


def _to_numpy(a) -> np.ndarray:
    if isinstance(a, _ChumpyStandIn):
        return a.r
    if hasattr(a, 'toarray'):  # scipy sparse
        return a.toarray()
    return np.asarray(a)


def load_model_arrays(path: str) -> dict[str, np.ndarray]:
    """The model arrays of an SMPL `.pkl` or `.npz` as float64/int64 numpy arrays."""
    keys = ('v_template', 'shapedirs', 'posedirs', 'J_regressor', 'weights',
            'kintree_table', 'f')
    if path.endswith('.npz'):
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in keys if k not in z.files]
            raw = {k: z[k] for k in keys if k in z.files}
    else:
        with open(path, 'rb') as fh:
            data = _SMPLUnpickler(fh, encoding='latin1').load()
        if not isinstance(data, dict):
            raise ValueError(f'{path}: expected a dict of model arrays, got {type(data)}')
        missing = [k for k in keys if k not in data]
        raw = {k: data[k] for k in keys if k in data}
    if missing:
        raise ValueError(f'{path} is not an SMPL model file: missing {missing}')
    out = {k: _to_numpy(v) for k, v in raw.items()}
    # C-contiguous copies: a pickle's arrays may be Fortran-ordered, and BLAS sums a
    # product of differently laid-out operands in another order (last-bit differences
    # between the .pkl and the .npz of one model).
    for k in ('kintree_table', 'f'):
        out[k] = np.ascontiguousarray(out[k], dtype=np.int64)
    for k in ('v_template', 'shapedirs', 'posedirs', 'J_regressor', 'weights'):
        out[k] = np.ascontiguousarray(out[k], dtype=np.float64)
    return out


def _parents_from_kintree(kt: np.ndarray) -> list[int]:
    """Parent column per column of a (2, J) kintree_table (row 0 parents, row 1 ids)."""
    col = {int(i): c for c, i in enumerate(kt[1])}
    parents = [col.get(int(p), -1) for p in kt[0]]
    if parents[0] != -1 or any(not 0 <= p < c for c, p in enumerate(parents) if c):
        raise ValueError(f'kintree_table is not a root-first tree: parents {parents}')
    return parents


# -- the backend -----------------------------------------------------------------------
class SMPLBody(BodyModel):
    """SMPL as a BodyModel. Shape = the first 10 betas (unbounded, mean 0, std 1).

    Args:
        path: model file (.pkl/.npz) or a directory holding SMPL_NEUTRAL.pkl/.npz or
            basicmodel_neutral*; None reads $SMPL_MODEL_PATH.
        dtype: floating dtype of the buffers.

    Buffers: faces (F, 3), template_vertices (V, 3), shapedirs (V, 3, 10),
    posedirs (V, 3, 207), skin_weights (V, 24) dense (`skin_indices` is None),
    J_regressor (24, V), template_joints (24, 3) and joint_shapedirs (24, 3, 10)
    (= J_regressor applied to the former two), part_labels, valid_vertices,
    canonical_rotation, shape_mean, shape_std. Like the anny backend it exposes its
    skeleton as bones (`bone_names`, `bone_parents`, `joint_bones`, `skeleton_pose`); for
    SMPL every bone is a fitted joint.
    """

    name = 'smpl'

    def __init__(self, path: str | None = None, dtype: torch.dtype = torch.float32):
        super().__init__()
        self.model_path = find_model_file(path)
        m = load_model_arrays(self.model_path)
        v_template = m['v_template']
        V = v_template.shape[0]
        kt = m['kintree_table']
        if v_template.shape != (V, 3) or kt.shape != (2, NUM_JOINTS):
            raise ValueError(f'{self.model_path}: expected an SMPL body with {NUM_JOINTS} '
                             f'joints, got v_template {v_template.shape}, kintree_table '
                             f'{kt.shape} (SMPL-H/SMPL-X are not supported)')
        parents = _parents_from_kintree(kt)
        shapedirs = m['shapedirs']
        if shapedirs.ndim != 3 or shapedirs.shape[:2] != (V, 3):
            raise ValueError(f'shapedirs must be (V, 3, S), got {shapedirs.shape}')
        shapedirs = shapedirs[:, :, :NUM_BETAS]
        n_pose = 9 * (NUM_JOINTS - 1)
        posedirs = m['posedirs']
        if posedirs.shape == (n_pose, V * 3):
            posedirs = posedirs.T
        if posedirs.shape not in ((V, 3, n_pose), (V * 3, n_pose)):
            raise ValueError(f'posedirs must be (V, 3, {n_pose}) or (V*3, {n_pose}), '
                             f'got {posedirs.shape}')
        posedirs = posedirs.reshape(V, 3, n_pose)
        J_reg, weights, faces = m['J_regressor'], m['weights'], m['f']
        if J_reg.shape != (NUM_JOINTS, V) or weights.shape != (V, NUM_JOINTS):
            raise ValueError(f'J_regressor {J_reg.shape} / weights {weights.shape} do not '
                             f'match {NUM_JOINTS} joints and {V} vertices')
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= V:
            raise ValueError(f'bad faces f {faces.shape}')

        self.joint_names = GENERIC_JOINTS
        self.shape_names = tuple(f'beta{i}' for i in range(shapedirs.shape[2]))
        self.bone_names = self.joint_names
        self.register_buffer('joint_parents', torch.tensor(parents), persistent=False)
        self.register_buffer('bone_parents', torch.tensor([max(p, 0) for p in parents]),
                             persistent=False)
        self.register_buffer('joint_bones', torch.arange(NUM_JOINTS), persistent=False)
        self._levels = lbs.kinematic_levels(parents)

        t = torch.from_numpy
        self.register_buffer('faces', t(faces), persistent=False)
        self.register_buffer('template_vertices', t(v_template), persistent=False)
        self.register_buffer('shapedirs', t(np.ascontiguousarray(shapedirs)), persistent=False)
        self.register_buffer('posedirs', t(np.ascontiguousarray(posedirs)), persistent=False)
        self.register_buffer('skin_weights', t(weights), persistent=False)
        self.skin_indices = None  # dense weights over all 24 joints
        self.register_buffer('J_regressor', t(J_reg), persistent=False)
        # J(beta) = J_regressor (v_template + shapedirs beta), folded (exact: it is linear).
        self.register_buffer('template_joints', t(J_reg @ v_template), persistent=False)
        self.register_buffer('joint_shapedirs',
                             t(np.einsum('jv,vks->jks', J_reg, shapedirs)), persistent=False)
        # Parts: dominant part by summed skinning weight (as the anny backend).
        joint_part_ids = torch.tensor([joint_part(n) for n in self.joint_names])
        acc = torch.zeros(V, len(PART_NAMES), dtype=torch.float64)
        acc.index_add_(1, joint_part_ids, t(weights))
        self.register_buffer('part_labels', acc.argmax(1), persistent=False)
        self.register_buffer('valid_vertices', torch.ones(V, dtype=torch.bool),
                             persistent=False)
        self.register_buffer('canonical_rotation', torch.eye(3, dtype=torch.float64),
                             persistent=False)
        S = len(self.shape_names)
        self.register_buffer('shape_mean', torch.zeros(S, dtype=torch.float64),
                             persistent=False)
        self.register_buffer('shape_std', torch.ones(S, dtype=torch.float64), persistent=False)
        self.to(dtype=dtype)

    def rest(self, shape: torch.Tensor, vertex_ids: torch.Tensor | None = None):
        """Shaped rest vertices (B, V|K, 3) and joints J(beta) (B, 24, 3).

        The joints always come from the full shaped mesh (J_regressor on all vertices).
        """
        if vertex_ids is None:
            tv, sd = self.template_vertices, self.shapedirs
        else:
            tv, sd = self.template_vertices[vertex_ids], self.shapedirs[vertex_ids]
        verts = tv + torch.einsum('bs,vks->bvk', shape, sd)
        joints = self.template_joints + torch.einsum('bs,jks->bjk', shape, self.joint_shapedirs)
        return verts, joints

    def rest_linear(self, shape: torch.Tensor, vertex_ids: torch.Tensor | None = None):
        """First-order rest geometry at `shape` (1, S); exact, SMPL is linear in betas.

        Returns rest vertices (N, 3), their shapedirs (N, 3, S), rest joints (24, 3) and the
        joint shapedirs (24, 3, S).
        """
        verts, joints = self.rest(shape, vertex_ids)
        sd = self.shapedirs if vertex_ids is None else self.shapedirs[vertex_ids]
        return verts[0], sd, joints[0], self.joint_shapedirs

    def skeleton_pose(self, rot: torch.Tensor, rest_heads: torch.Tensor):
        """FK: rot (B, 24, 3, 3) local, rest_heads (B, 24, 3) -> G (B, 24, 3, 3), x (B, 24, 3)."""
        return lbs.forward_kinematics(rot, rest_heads, self.bone_parents, self._levels)

    def pose_offsets(self, rot: torch.Tensor, vertex_ids: torch.Tensor | None = None):
        """Pose-blendshape displacements (B, V|K, 3) for rot (B, 24, 3, 3).

        posedirs applied to vec(R_k - I), k = 1..23, row-major as in SMPL.
        """
        B = rot.shape[0]
        eye = torch.eye(3, dtype=rot.dtype, device=rot.device)
        feat = (rot[:, 1:] - eye).reshape(B, -1)  # (B, 207)
        pd = self.posedirs if vertex_ids is None else self.posedirs[vertex_ids]
        return torch.einsum('bp,vkp->bvk', feat, pd)

    def pose_rest(self, rest_vertices, rest_joints, rot, vertex_ids=None):
        """Pose blendshapes, FK and dense LBS.

        Args:
            rest_vertices: (B, V|K, 3) shaped rest vertices; rest_joints (B, 24, 3).
            rot: (B, 24, 3, 3) local rotations, global orientation first.
            vertex_ids: the (K,) vertex ids rest_vertices holds, or None for all.

        Returns:
            vertices (B, V|K, 3), joints (B, 24, 3).
        """
        w = self.skin_weights if vertex_ids is None else self.skin_weights[vertex_ids]
        v_posed = rest_vertices + self.pose_offsets(rot, vertex_ids)
        G, x = self.skeleton_pose(rot, rest_joints)
        return lbs.skin(v_posed, G, x, rest_joints, w), x

    def canonical_vertices(self) -> np.ndarray:
        """Mean-shape T-pose: SMPL's v_template (its rest pose is a T-pose; frame is I)."""
        return (self.template_vertices @ self.canonical_rotation.T).detach().cpu().numpy()
