"""The smpl backend on a synthetic model file with the official structure (no ROS).

The real SMPL is licence-gated, so a fixture builds an SMPL-like model (24 joints on
SMPL's skeleton, a tube mesh around the bones, smooth skinning weights, random small
shape and pose blendshapes, a sparse convex J_regressor) and writes it as an smplx-style
`.npz` and as a Python-2-style `.pkl` (py2 `str` opcodes, old module paths, a scipy
sparse J_regressor and `chumpy.ch.Ch` objects), which must load without chumpy. The
forward is checked against an independent numpy implementation of the SMPL paper.
"""
import pickle
import pickletools
import struct
import sys
import types

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from scipy.spatial.transform import Rotation

from smpl_depth_ros.body import load_body_model
from smpl_depth_ros.body.base import GENERIC_JOINTS
from smpl_depth_ros.body.parts import PART_NAMES
from smpl_depth_ros.body.smpl_model import ENV_VAR, SMPLBody

# SMPL's kinematic tree (independent of the backend's kintree parsing).
PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]
# Approximate SMPL neutral rest joints (metres; y up, facing +z, left +x).
JOINTS = np.array([
    [0.00, -0.22, 0.03], [0.06, -0.31, 0.02], [-0.06, -0.31, 0.02], [0.00, -0.11, 0.00],
    [0.10, -0.69, 0.02], [-0.10, -0.69, 0.02], [0.00, 0.03, 0.03], [0.09, -1.09, -0.02],
    [-0.09, -1.09, -0.02], [0.00, 0.08, 0.03], [0.12, -1.15, 0.10], [-0.12, -1.15, 0.10],
    [0.00, 0.29, -0.01], [0.08, 0.20, 0.00], [-0.08, 0.20, 0.00], [0.00, 0.36, 0.05],
    [0.17, 0.23, -0.01], [-0.17, 0.23, -0.01], [0.43, 0.21, -0.03], [-0.43, 0.21, -0.03],
    [0.68, 0.22, -0.03], [-0.68, 0.22, -0.03], [0.77, 0.21, -0.04], [-0.77, 0.21, -0.04],
])
# Leaf extensions (joint -> end point) so hands, feet and head get their own geometry.
LEAVES = {10: [0.12, -1.15, 0.18], 11: [-0.12, -1.15, 0.18], 15: [0.00, 0.55, 0.05],
          22: [0.85, 0.21, -0.04], 23: [-0.85, 0.21, -0.04]}
N_SHAPE_NPZ = 16  # > 10: the backend must use the first 10
N_POSE = 207


def _tube(a, b, radius, n_rings=5, n_around=8):
    """Open cylinder from a to b: vertices (n_rings*n_around, 3) and quad-split faces."""
    d = b - a
    d = d / np.linalg.norm(d)
    ref = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(d, ref)
    u /= np.linalg.norm(u)
    w = np.cross(d, u)
    ang = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    ring = radius * (np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * w)
    verts = np.concatenate([a + t * (b - a) + ring for t in np.linspace(0, 1, n_rings)])
    faces = []
    for r in range(n_rings - 1):
        for k in range(n_around):
            i0, i1 = r * n_around + k, r * n_around + (k + 1) % n_around
            faces += [[i0, i1, i1 + n_around], [i0, i1 + n_around, i0 + n_around]]
    return verts, np.array(faces)


def _seg_dist(p, a, b):
    ab = b - a
    t = np.clip(((p - a) @ ab) / (ab @ ab), 0, 1)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def make_model(seed=0):
    """A synthetic SMPL-like model as a dict of arrays with the official names/shapes."""
    rng = np.random.default_rng(seed)
    # Segments owned by each joint (the joint rotates them): joint -> children / leaf.
    segs = [(PARENTS[c], JOINTS[PARENTS[c]], JOINTS[c]) for c in range(1, 24)]
    segs += [(j, JOINTS[j], np.array(e)) for j, e in LEAVES.items()]
    verts, faces = [], []
    for j, a, b in segs:
        name = GENERIC_JOINTS[j]
        r = 0.10 if name in ('pelvis', 'spine1', 'spine2', 'spine3') else (
            0.04 if any(k in name for k in ('shoulder', 'elbow', 'wrist', 'hand')) else 0.06)
        v, f = _tube(a, b, r)
        faces.append(f + sum(len(x) for x in verts))
        verts.append(v)
    v_template = np.concatenate(verts)
    f = np.concatenate(faces).astype(np.uint32)
    V = len(v_template)
    # Smooth skinning weights from distances to each joint's segments.
    dist = np.full((V, 24), np.inf)
    for j, a, b in segs:
        dist[:, j] = np.minimum(dist[:, j], _seg_dist(v_template, a, b))
    w = np.exp(-(dist / 0.05) ** 2) * rng.uniform(0.8, 1.2, (V, 24))
    w[w < 1e-4 * w.max(1, keepdims=True)] = 0
    weights = w / w.sum(1, keepdims=True)
    # Sparse convex J_regressor: the 12 vertices nearest each designed joint.
    J_reg = np.zeros((24, V))
    for j in range(24):
        near = np.argsort(np.linalg.norm(v_template - JOINTS[j], axis=1))[:12]
        J_reg[j, near] = rng.uniform(0.5, 1.5, 12)
    J_reg /= J_reg.sum(1, keepdims=True)
    # Smooth shape blendshapes (random linear fields) plus a little noise.
    vh = np.concatenate([v_template, np.ones((V, 1))], 1)
    fields = rng.normal(0, 0.03, (N_SHAPE_NPZ, 4, 3))
    shapedirs = np.einsum('vi,sik->vks', vh, fields) + rng.normal(0, 1e-3, (V, 3, N_SHAPE_NPZ))
    posedirs = rng.normal(0, 3e-3, (V * 3, N_POSE))
    kintree = np.array([[4294967295] + PARENTS[1:], list(range(24))], dtype=np.int64)
    return dict(v_template=v_template, shapedirs=shapedirs, posedirs=posedirs,
                J_regressor=J_reg, weights=weights, kintree_table=kintree, f=f)


# -- a Python-2-style pickle writer ------------------------------------------------------
_PY2_MODULES = {'numpy._core.multiarray': 'numpy.core.multiarray',
                'numpy._core.numeric': 'numpy.core.numeric',
                'scipy.sparse._csc': 'scipy.sparse.csc', 'builtins': '__builtin__',
                'copyreg': 'copy_reg'}


class _Py2Pickler(pickle._Pickler):
    """Protocol 2 as Python 2's cPickle wrote it: byte and ASCII strings as py2 `str`
    (BINSTRING: Python 3 needs encoding='latin1' for numpy's raw data) and py2-era module
    paths for globals."""

    dispatch = pickle._Pickler.dispatch.copy()

    def _binstring(self, obj, data):
        n = len(data)
        if n < 256:
            self.write(pickle.SHORT_BINSTRING + bytes([n]) + data)
        else:
            self.write(pickle.BINSTRING + struct.pack('<i', n) + data)
        self.memoize(obj)

    def save_bytes(self, obj):
        self._binstring(obj, obj)

    def save_str(self, obj):
        if obj.isascii():
            self._binstring(obj, obj.encode('ascii'))
        else:
            pickle._Pickler.save_str(self, obj)

    def save_global(self, obj, name=None):
        name = name or obj.__qualname__
        module = getattr(obj, '__module__', None) or pickle.whichmodule(obj, name)
        module = _PY2_MODULES.get(module, module)
        self.write(pickle.GLOBAL + f'{module}\n{name}\n'.encode())
        self.memoize(obj)

    dispatch[bytes] = save_bytes
    dispatch[str] = save_str
    dispatch[types.FunctionType] = save_global


class FakeCh:
    """Stands for chumpy.ch.Ch when writing: pickles as chumpy does (its state dict)."""

    def __init__(self, x):
        self.__dict__.update(x=np.asarray(x), _dirty_vars=set(), _itr=None,
                             _depends_on_deps={}, _make_dense=False, _make_sparse=False)


def write_py2_pkl(path, m):
    chumpy = types.ModuleType('chumpy')
    chumpy_ch = types.ModuleType('chumpy.ch')
    chumpy.ch = chumpy_ch
    chumpy_ch.Ch = FakeCh
    saved = {k: sys.modules.get(k) for k in ('chumpy', 'chumpy.ch')}
    FakeCh.__module__, FakeCh.__qualname__ = 'chumpy.ch', 'Ch'
    sys.modules.update({'chumpy': chumpy, 'chumpy.ch': chumpy_ch})  # at write time only
    try:
        V = len(m['v_template'])
        data = {
            'v_template': m['v_template'], 'weights': m['weights'],
            'shapedirs': FakeCh(m['shapedirs'][:, :, :10]),  # official: a chumpy Ch
            'posedirs': m['posedirs'].reshape(V, 3, N_POSE),  # official layout
            'J_regressor': sp.csc_matrix(m['J_regressor']),
            'J_regressor_prior': sp.csc_matrix(m['J_regressor']),
            'J': FakeCh(m['J_regressor'] @ m['v_template']),
            'kintree_table': m['kintree_table'], 'f': m['f'],
            'bs_style': 'lbs', 'bs_type': 'lrotmin', 'vert_sym_idxs': np.arange(V),
            'weights_prior': m['weights'], 'pose_training_info': {'nPoses': 1786},
        }
        with open(path, 'wb') as fh:
            _Py2Pickler(fh, protocol=2).dump(data)
    finally:
        FakeCh.__module__, FakeCh.__qualname__ = __name__, 'FakeCh'
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v


# -- an independent reference: the SMPL paper in numpy -------------------------------------
def reference_smpl(m, pose, betas, global_orient, transl):
    """One body: pose (23, 3), betas (10,), global_orient (3,), transl (3,), float64."""
    V = len(m['v_template'])
    v_shaped = m['v_template'] + m['shapedirs'][:, :, :10] @ betas
    J = m['J_regressor'] @ v_shaped
    R = Rotation.from_rotvec(np.concatenate([global_orient[None], pose])).as_matrix()
    v_posed = v_shaped + (m['posedirs'] @ (R[1:] - np.eye(3)).ravel()).reshape(V, 3)
    G = np.zeros((24, 4, 4))
    for k in range(24):
        local = np.eye(4)
        local[:3, :3] = R[k]
        local[:3, 3] = J[k] - (J[PARENTS[k]] if k else 0)
        G[k] = local if k == 0 else G[PARENTS[k]] @ local
    T = np.zeros_like(G)
    for k in range(24):
        back = np.eye(4)
        back[:3, 3] = -J[k]
        T[k] = G[k] @ back  # world transform applied to rest-pose points
    Tv = np.einsum('vk,kab->vab', m['weights'], T)
    verts = np.einsum('vab,vb->va', Tv[:, :3, :3], v_posed) + Tv[:, :3, 3]
    return verts + transl, G[:, :3, 3] + transl


@pytest.fixture(scope='module')
def model_files(tmp_path_factory):
    d = tmp_path_factory.mktemp('smpl')
    m = make_model()
    np.savez(d / 'SMPL_NEUTRAL.npz', **m)
    write_py2_pkl(d / 'basicModel_neutral_lbs_10_207_0_v1.0.0.pkl', m)
    return m, d / 'SMPL_NEUTRAL.npz', d / 'basicModel_neutral_lbs_10_207_0_v1.0.0.pkl'


@pytest.fixture
def no_chumpy(monkeypatch):
    """`import chumpy` fails while loading."""
    monkeypatch.setitem(sys.modules, 'chumpy', None)
    monkeypatch.setitem(sys.modules, 'chumpy.ch', None)


def _params(n, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return dict(pose=0.4 * torch.randn(n, 23, 3, generator=g, dtype=dtype),
                shape=torch.randn(n, 10, generator=g, dtype=dtype),
                global_orient=torch.randn(n, 3, generator=g, dtype=dtype),
                transl=torch.randn(n, 3, generator=g, dtype=dtype))


def test_pickle_is_python2_style(model_files):
    """The fixture's pkl has py2 strings and a chumpy global, like the official files."""
    _, _, pkl = model_files
    ops = {(op.name, arg) for op, arg, _ in pickletools.genops(pkl.read_bytes())}
    names = {o for o, _ in ops}
    assert 'BINUNICODE' not in names and 'SHORT_BINUNICODE' not in names
    assert ('GLOBAL', 'chumpy.ch Ch') in ops
    assert ('GLOBAL', 'scipy.sparse.csc csc_matrix') in ops
    assert ('GLOBAL', 'numpy.core.multiarray _reconstruct') in ops


def test_forward_matches_reference_float64(model_files, no_chumpy):
    m, npz, pkl = model_files
    for path in (npz, pkl):
        body = SMPLBody(str(path), dtype=torch.float64)
        p = _params(3, seed=1)
        out = body(**p)
        for b in range(3):
            rv, rj = reference_smpl(m, *(p[k][b].numpy() for k in
                                         ('pose', 'shape', 'global_orient', 'transl')))
            assert np.abs(out.vertices[b].numpy() - rv).max() < 1e-8
            assert np.abs(out.joints[b].numpy() - rj).max() < 1e-8


def test_forward_float32(model_files):
    m, npz, _ = model_files
    body = SMPLBody(str(npz))
    assert body.dtype == torch.float32
    p = _params(3, seed=2, dtype=torch.float32)
    out = body(**p)
    assert out.vertices.dtype == torch.float32
    for b in range(3):
        rv, rj = reference_smpl(m, *(p[k][b].double().numpy() for k in
                                     ('pose', 'shape', 'global_orient', 'transl')))
        np.testing.assert_allclose(out.vertices[b].numpy(), rv, atol=2e-5)
        np.testing.assert_allclose(out.joints[b].numpy(), rj, atol=2e-5)


def test_pkl_and_npz_identical(model_files, no_chumpy):
    _, npz, pkl = model_files
    a, b = SMPLBody(str(npz), torch.float64), SMPLBody(str(pkl), torch.float64)
    for name, buf in a.named_buffers():
        assert torch.equal(buf, getattr(b, name)), name
    p = _params(2, seed=3)
    oa, ob = a(**p), b(**p)
    assert torch.equal(oa.vertices, ob.vertices) and torch.equal(oa.joints, ob.joints)


def test_rest_pose_and_buffers(model_files):
    m, npz, _ = model_files
    body = SMPLBody(str(npz), torch.float64)
    V = len(m['v_template'])
    assert body.name == 'smpl' and body.joint_names == GENERIC_JOINTS
    assert body.shape_names == tuple(f'beta{i}' for i in range(10))
    assert body.joint_parents.tolist() == PARENTS
    assert body.shape_bounds is None and body.num_vertices == V
    assert body.faces.dtype == torch.int64 and body.faces.shape == m['f'].shape
    assert torch.equal(body.shape_mean, torch.zeros(10, dtype=torch.float64))
    assert torch.equal(body.shape_std, torch.ones(10, dtype=torch.float64))
    assert bool(body.valid_vertices.all()) and body.valid_vertices.shape == (V,)
    assert torch.equal(body.canonical_rotation, torch.eye(3, dtype=torch.float64))
    out = body(**body.zero_params(1))
    np.testing.assert_allclose(out.vertices[0].numpy(), m['v_template'], atol=1e-12)
    np.testing.assert_allclose(out.joints[0].numpy(), m['J_regressor'] @ m['v_template'],
                               atol=1e-12)
    cv = body.canonical_vertices()
    assert isinstance(cv, np.ndarray) and cv.shape == (V, 3)
    np.testing.assert_allclose(cv, m['v_template'], atol=1e-12)


def test_part_labels(model_files):
    m, npz, _ = model_files
    body = SMPLBody(str(npz))
    labels = body.part_labels
    assert labels.dtype == torch.int64
    assert set(labels.tolist()) == set(range(1, len(PART_NAMES)))
    # Left/right: vertices labelled left-side parts lie at +x (SMPL's left).
    x = torch.from_numpy(m['v_template'][:, 0])
    left = torch.tensor([i for i, n in enumerate(PART_NAMES) if n.endswith('_l')])
    right = torch.tensor([i for i, n in enumerate(PART_NAMES) if n.endswith('_r')])
    assert (x[torch.isin(labels, left)] > -0.02).all()
    assert (x[torch.isin(labels, right)] < 0.02).all()
    # Dominant joint of each part as specified.
    dom = body.skin_weights.argmax(1)
    for j, part in ((15, 'head'), (0, 'torso'), (16, 'upper_arm_l'), (19, 'lower_arm_r'),
                    (22, 'hand_l'), (2, 'upper_leg_r'), (4, 'lower_leg_l'), (11, 'foot_r')):
        assert (labels[dom == j] == PART_NAMES.index(part)).float().mean() > 0.9


def test_vertex_ids_subset(model_files):
    _, npz, _ = model_files
    body = SMPLBody(str(npz), torch.float64)
    p = _params(3, seed=4)
    full = body(**p)
    ids = torch.tensor([5, 0, 77, 300, 301, body.num_vertices - 1, 77])
    sub = body(**p, vertex_ids=ids)
    torch.testing.assert_close(sub.vertices, full.vertices[:, ids], atol=1e-12, rtol=0)
    torch.testing.assert_close(sub.joints, full.joints, atol=1e-12, rtol=0)


def test_gradcheck(model_files):
    _, npz, _ = model_files
    body = SMPLBody(str(npz), torch.float64)
    p = _params(1, seed=5)
    ids = torch.tensor([3, 150, 400, 777])

    def f(pose, shape, go, tr):
        o = body(pose, shape, go, tr, vertex_ids=ids)
        return torch.cat([o.vertices, o.joints], 1)

    inputs = tuple(p[k].clone().requires_grad_(True)
                   for k in ('pose', 'shape', 'global_orient', 'transl'))
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6)


def test_env_var_and_missing(model_files, monkeypatch, tmp_path):
    _, npz, pkl = model_files
    monkeypatch.delenv(ENV_VAR, raising=False)
    with pytest.raises(FileNotFoundError) as e:
        SMPLBody()
    assert ENV_VAR in str(e.value) and 'path' in str(e.value)
    monkeypatch.setenv(ENV_VAR, str(tmp_path))  # an empty directory
    with pytest.raises(FileNotFoundError, match=ENV_VAR):
        SMPLBody()
    monkeypatch.setenv(ENV_VAR, str(tmp_path / 'nope.pkl'))
    with pytest.raises(FileNotFoundError, match='does not exist'):
        SMPLBody()
    monkeypatch.setenv(ENV_VAR, str(npz.parent))  # a directory: SMPL_NEUTRAL.npz first
    assert SMPLBody().model_path == str(npz)
    monkeypatch.setenv(ENV_VAR, str(pkl))  # a file
    assert SMPLBody().model_path == str(pkl)
    d = tmp_path / 'models' / 'smpl'  # smplx layout, official file name
    d.mkdir(parents=True)
    (d / pkl.name).write_bytes(pkl.read_bytes())
    monkeypatch.setenv(ENV_VAR, str(tmp_path / 'models'))
    assert SMPLBody().model_path == str(d / pkl.name)


def test_load_body_model(model_files):
    m, npz, pkl = model_files
    body = load_body_model('smpl', str(pkl), dtype=torch.float64)
    assert isinstance(body, SMPLBody) and body.dtype == torch.float64
    out = body(**body.zero_params(2))
    assert out.vertices.shape == (2, len(m['v_template']), 3)
    assert out.joints.shape == (2, 24, 3)


def test_rejects_non_smpl(model_files, tmp_path):
    m, _, _ = model_files
    bad = dict(m, kintree_table=np.zeros((2, 52), np.int64))
    np.savez(tmp_path / 'smplh.npz', **bad)
    with pytest.raises(ValueError, match='24 joints'):
        SMPLBody(str(tmp_path / 'smplh.npz'))
    (tmp_path / 'evil.pkl').write_bytes(pickle.dumps({'x': print}, protocol=2))
    with pytest.raises(pickle.UnpicklingError, match='refusing'):
        SMPLBody(str(tmp_path / 'evil.pkl'))


def test_fitter_interface(model_files):
    """The bone interface the fitter uses (as anny's): exact rest_linear, skeleton_pose."""
    from smpl_depth_ros.body.base import BodyModel
    _, npz, _ = model_files
    body = SMPLBody(str(npz), torch.float64)
    assert body.bone_names == body.joint_names and body.skin_indices is None
    assert torch.equal(body.joint_bones, torch.arange(24))
    assert body.bone_parents.tolist() == [0] + PARENTS[1:]
    p = _params(1, seed=6)
    ids = torch.tensor([1, 50, 600])
    exact = body.rest_linear(p['shape'], ids)
    fd = BodyModel.rest_linear(body, p['shape'], ids)  # the base's finite differences
    for a, b in zip(exact, fd):
        torch.testing.assert_close(a, b, atol=1e-8, rtol=0)
    rot = torch.eye(3, dtype=torch.float64).expand(1, 24, 3, 3)
    assert float(body.pose_offsets(rot).abs().max()) == 0.0
    from smpl_depth_ros.body import lbs
    rot = lbs.axis_angle_to_matrix(torch.cat([p['global_orient'][:, None], p['pose']], 1))
    _, heads = body.rest(p['shape'])
    _, x = body.skeleton_pose(rot, heads)
    torch.testing.assert_close(x + p['transl'][:, None], body(**p).joints, atol=1e-12, rtol=0)


def test_fitter_runs_on_smpl(model_files):
    """The fast solver recovers a synthetic SMPL body (it omits pose blendshapes: mm-level)."""
    from smpl_depth_ros.fit.fitter import Fitter
    _, npz, _ = model_files
    body = SMPLBody(str(npz))
    p = _params(1, seed=7, dtype=torch.float32)
    p['pose'] *= 0.5
    p['transl'] = torch.tensor([[0.1, 0.2, 2.5]])
    out = body(**p)
    r = Fitter(body).fit(out.vertices[0].numpy(), np.arange(body.num_vertices))
    assert np.median(r.residuals) < 0.01
