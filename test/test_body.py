"""anny backend, parts and the template embedding (core, no ROS)."""
import numpy as np
import pytest
import torch

from smpl_depth_ros.body import lbs, load_body_model
from smpl_depth_ros.body.anny_model import AnnyBody
from smpl_depth_ros.body.parts import (NUM_CLASSES, PART_COLORS_U8, EmbeddingIndex,
                                       template_embedding)


@pytest.fixture(scope='module')
def body64():
    return AnnyBody(dtype=torch.float64)


def _random_params(body, B, seed=0):
    g = torch.Generator().manual_seed(seed)
    kw = dict(dtype=body.dtype)
    return dict(pose=0.3 * torch.randn(B, body.num_pose_joints, 3, generator=g, **kw),
                shape=torch.rand(B, body.num_shape, generator=g, **kw),
                global_orient=0.5 * torch.randn(B, 3, generator=g, **kw),
                transl=torch.randn(B, 3, generator=g, **kw))


def test_anny_structure():
    b = load_body_model('anny')
    assert b.num_vertices == 1229 and tuple(b.faces.shape) == (2454, 3)
    assert len(b.joint_names) == 20 and b.joint_names[0] == 'pelvis'
    assert b.shape_names == ('gender', 'age', 'muscle', 'weight', 'height', 'proportions')
    assert b.dtype == torch.float32
    assert int(b.joint_parents[0]) == -1 and all(0 <= int(p) < i for i, p in
                                                  enumerate(b.joint_parents[1:], 1))


@pytest.mark.parametrize('dtype', [torch.float32, torch.float64])
def test_forward_shapes_and_rest(dtype):
    b = AnnyBody(dtype=dtype)
    p = _random_params(b, 3)
    out = b(**p)
    assert out.vertices.shape == (3, 1229, 3) and out.vertices.dtype == dtype
    assert out.joints.shape == (3, 20, 3)
    z = b.zero_params(2)
    rest, _ = b.rest(z['shape'])
    assert torch.allclose(b(**z).vertices, rest, atol=1e-6)


def test_matches_anny_forward(body64):
    """Our LBS equals anny's own forward (its 'world' pose parameterisation)."""
    b = body64
    p = _random_params(b, 2, seed=3)
    out = b(**p)
    m = b._anny
    rest = m.get_rest_model(b.blend_coefficients(p['shape']))
    rot = lbs.axis_angle_to_matrix(torch.cat([p['global_orient'][:, None], p['pose']], 1))
    G, x = b.skeleton_pose(rot, b.rest(p['shape'])[1])
    W = torch.eye(4, dtype=torch.float64).expand(2, len(b.bone_names), 4, 4).clone()
    W[..., :3, :3] = G @ rest['rest_bone_poses'][..., :3, :3]
    W[..., :3, 3] = x + p['transl'][:, None]
    ref = m(pose_parameters=W, phenotype_kwargs=p['shape'], pose_parameterization='world')
    assert (ref['vertices'] - out.vertices).abs().max() < 1e-9


def test_vertex_subset_and_gradients(body64):
    b = body64
    p = _random_params(b, 1, seed=5)
    ids = torch.tensor([0, 17, 400, 1228])
    assert torch.allclose(b(**p, vertex_ids=ids).vertices, b(**p).vertices[:, ids])
    leaves = [p[k].clone().requires_grad_(True) for k in ('pose', 'shape', 'global_orient',
                                                          'transl')]
    f = lambda a, s, g, t: b(a, s, g, t, vertex_ids=ids).vertices  # noqa: E731
    assert torch.autograd.gradcheck(f, leaves)


def test_parts_cover_body_and_are_symmetric():
    b = AnnyBody()
    counts = torch.bincount(b.part_labels, minlength=NUM_CLASSES).tolist()
    assert counts[0] == 0 and all(c > 0 for c in counts[1:])
    for left in (3, 5, 7, 9, 11, 13):
        assert counts[left] == counts[left + 1]
    # Left parts lie on the person's left (+x in the canonical frame).
    cv = b.canonical_vertices()
    lab = b.part_labels.numpy()
    assert cv[lab == 3, 0].mean() > 0.1 and cv[lab == 4, 0].mean() < -0.1
    # The canonical template is a T-pose: arms horizontal, hands far apart.
    assert cv[:, 0].max() - cv[:, 0].min() > 1.3
    assert len({tuple(c) for c in PART_COLORS_U8}) == NUM_CLASSES


def test_embedding_lookup_recovers_vertices():
    b = AnnyBody()
    emb = template_embedding(b.canonical_vertices(), b.part_labels.numpy())
    assert emb.shape == (1229, 6) and emb.min() >= 0 and emb.max() <= 1
    idx = EmbeddingIndex(emb)
    ids, dist = idx.query(emb)
    assert (dist < 1e-6).mean() > 0.98  # duplicates of coincident vertices aside
    rng = np.random.default_rng(0)
    q = emb[rng.integers(0, 1229, 20000)] + rng.normal(0, 0.005, (20000, 6)).astype(np.float32)
    ids, _ = idx.query(q)
    assert ids.shape == (20000,) and ids.min() >= 0 and ids.max() < 1229
