"""Synthetic data: camera, ray-cast renderer, background, noise model, frames (no ROS)."""
import dataclasses

import numpy as np
import pytest
import trimesh
import trimesh.triangles

from smpl_depth_ros.synth import dataset, noise, render
from smpl_depth_ros.synth.camera import CAMERAS, Camera, get_camera
from smpl_depth_ros.synth.poses import PoseSampler

CAM = CAMERAS['kinect_v1'].scaled(320, 240)
SMALL = CAMERAS['kinect_v1'].scaled(160, 120)


@pytest.fixture(scope='module')
def body():
    from smpl_depth_ros.body.anny_model import AnnyBody
    return AnnyBody()


@pytest.fixture(scope='module')
def sampler(body):
    return PoseSampler(body)


@pytest.fixture(scope='module')
def clean_frame(body, sampler):
    return dataset.make_frame(body, sampler, np.random.default_rng(10), CAM, noise=False,
                              background=False)


def test_camera_presets():
    for name, cam in CAMERAS.items():
        assert cam.K.shape == (3, 3) and cam.K.dtype == np.float64
        assert cam.name == name
    k = CAMERAS['kinect_v1']
    s = k.scaled(320, 240)
    assert (s.width, s.height) == (320, 240)
    np.testing.assert_allclose([s.fx, s.fy, s.cx, s.cy], [262.5, 262.5, 159.5, 119.5])
    rs = get_camera('realsense_d435', 640, 480)
    assert (rs.width, rs.height) == (640, 480) and rs.fx == rs.fy
    assert get_camera('kinect_v1', 320).height == 240
    with pytest.raises(ValueError):
        get_camera('nope')
    with pytest.raises(ValueError):
        Camera(0, 10, 1, 1, 0, 0)
    # project / backproject round trip
    d = np.full((k.height, k.width), 2.0, np.float32)
    p = k.backproject(d)
    np.testing.assert_allclose(k.project(p.reshape(-1, 3)),
                               np.stack(np.meshgrid(np.arange(k.width), np.arange(k.height)),
                                        -1).reshape(-1, 2), atol=1e-9)


def test_head_turns_are_drawn_only_when_asked(body):
    """head_turn_deg widens the neck and head yaw within the joint limits; off, the
    random stream is exactly the default one (earlier bags and training runs)."""
    plain = PoseSampler(body)
    n = plain.names
    off = PoseSampler(body, head_turn_deg=0.0)
    r0, r1 = np.random.default_rng(3), np.random.default_rng(3)
    assert all(np.array_equal(plain.sample_canonical(r0), off.sample_canonical(r1))
               for _ in range(5))
    turned = PoseSampler(body, head_turn_deg=35)
    rng0, rng1 = np.random.default_rng(4), np.random.default_rng(4)
    yaw = {k: np.array([[s.sample_canonical(r)[n.index(j), 1] for j in ('neck', 'head')]
                        for _ in range(300)])
           for k, s, r in (('plain', plain, rng0), ('turned', turned, rng1))}
    assert yaw['turned'].std() > 2 * yaw['plain'].std()
    lim = plain.limits[[n.index('neck'), n.index('head')], 1]
    assert (yaw['turned'] >= lim[:, 0] - 1e-9).all() and (yaw['turned'] <= lim[:, 1] + 1e-9).all()


def test_render_plane_exact():
    # A slanted square: z = 2 + 0.3 x, checked in closed form at every pixel.
    v = np.array([[-1, -1, 1.7], [1, -1, 2.3], [1, 1, 2.3], [-1, 1, 1.7]], np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    r = render.render_body(v, f, np.array([2, 2, 2, 2]), SMALL)
    hit = r.depth > 0
    assert hit.mean() > 0.5
    u = np.arange(SMALL.width)[None, :].repeat(SMALL.height, 0)
    x = (u - SMALL.cx) / SMALL.fx
    z = 2.0 / (1 - 0.3 * x)  # z = 2 + 0.3 (x z)
    np.testing.assert_allclose(r.depth[hit], z[hit], rtol=1e-6)
    assert (r.labels[hit] == 2).all() and (r.vertex_ids[hit] >= 0).all()
    cos_expected = np.abs(np.array([-0.3, 0, 1]) @ np.stack(
        [x, (np.arange(SMALL.height)[:, None] - SMALL.cy) / SMALL.fy + 0 * x, 1 + 0 * x], -1)
        .reshape(-1, 3).T).reshape(z.shape)
    cos_expected /= np.sqrt(1.09) * np.linalg.norm(
        SMALL.backproject(np.ones(z.shape)), axis=-1)
    np.testing.assert_allclose(r.normals_cos[hit], cos_expected[hit], rtol=1e-5)


def _first_hit_z(tris, dirs):
    """z of the nearest intersection of rays from the origin with triangles (brute force)."""
    p0, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    pv = np.cross(dirs[:, None], e2[None])  # (R, T, 3)
    det = np.einsum('tk,rtk->rt', e1, pv)
    tv = -p0[None]
    with np.errstate(divide='ignore', invalid='ignore'):
        u = np.einsum('rtk,rtk->rt', np.broadcast_to(tv, pv.shape), pv) / det
        qv = np.cross(np.broadcast_to(tv, pv.shape), e1[None])
        w = np.einsum('rk,rtk->rt', dirs, qv) / det
        t = np.einsum('tk,rtk->rt', e2, qv) / det
    ok = (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)
    return np.where(ok, t * dirs[:, 2:3], np.inf).min(1)


def test_render_depth_matches_mesh(body, clean_frame):
    v, faces = clean_frame['vertices'].astype(np.float64), body.faces_numpy()
    r = render.render_body(v, faces, body.part_labels.numpy(), CAM)
    np.testing.assert_allclose(r.depth, clean_frame['depth'], atol=1e-5)  # float32 vertices
    m = r.body_mask
    assert m.sum() > 2000
    pts = CAM.backproject(r.depth)[m]
    # Back-projected pixels lie on their hit triangle (no rtree needed: pairwise).
    tris = v[faces[r.face_ids[m]]]
    closest = trimesh.triangles.closest_point(tris, pts)
    assert np.linalg.norm(closest - pts, axis=1).max() < 1e-3
    # First hit along the ray: brute-force Moller-Trumbore against every triangle.
    rng = np.random.default_rng(0)
    rows, cols = np.nonzero(m)
    pick = rng.choice(len(rows), 150, replace=False)
    dirs = np.stack([(cols[pick] - CAM.cx) / CAM.fx, (rows[pick] - CAM.cy) / CAM.fy,
                     np.ones(len(pick))], 1)
    first = _first_hit_z(v[faces], dirs)
    np.testing.assert_allclose(r.depth[rows[pick], cols[pick]], first, atol=1e-5)


def test_labels_and_vertex_ids(body, clean_frame):
    parts = body.part_labels.numpy()
    faces = body.faces_numpy()
    lab, vid, depth = clean_frame['labels'], clean_frame['vertex_ids'], clean_frame['depth']
    on = vid >= 0
    assert on.any()
    assert ((lab[on] >= 1) & (lab[on] <= 14)).all()
    np.testing.assert_array_equal(parts[vid[on]], lab[on])
    assert (lab[~on] == 0).all() and (depth[on] > 0).all()
    assert lab.dtype == np.uint8 and vid.dtype == np.int32 and depth.dtype == np.float32
    r = render.render_body(clean_frame['vertices'], faces, parts, CAM)
    hit_faces = faces[r.face_ids[on]]
    assert (hit_faces == vid[on][:, None]).any(1).all()
    assert len(np.unique(lab[on])) >= 8


def test_background_on_off(body, sampler):
    a = dataset.make_frame(body, sampler, np.random.default_rng(5), CAM, noise=False,
                           background=False)
    b = dataset.make_frame(body, sampler, np.random.default_rng(5), CAM, noise=False,
                           background=True)
    np.testing.assert_array_equal(a['vertices'], b['vertices'])  # same person
    assert (b['depth'] > 0).sum() > 3 * (a['depth'] > 0).sum()
    assert ((a['depth'] > 0) == (a['vertex_ids'] >= 0)).all()  # body only
    both = (a['vertex_ids'] >= 0) & (b['vertex_ids'] >= 0)
    np.testing.assert_array_equal(a['depth'][both], b['depth'][both])
    np.testing.assert_array_equal(a['vertex_ids'][both], b['vertex_ids'][both])
    # Body pixels survive (boxes may hide a little), background pixels carry no label.
    assert both.sum() >= 0.8 * (a['vertex_ids'] >= 0).sum()
    assert (b['labels'][b['vertex_ids'] < 0] == 0).all()
    assert (b['depth'][(b['vertex_ids'] < 0)] > 0).any()


def test_sample_background_geometry():
    rng = np.random.default_rng(0)
    root = np.array([0.2, 0.0, 3.0])
    verts = root + rng.uniform(-0.3, 0.3, (50, 3)) + [0, 0.5, 0]  # feet 0.8 m below root
    for _ in range(10):
        bg = render.sample_background(rng, CAM, root, verts)
        assert bg.faces.max() < len(bg.vertices) and len(bg.kinds) == len(bg.faces)
        floor = bg.vertices[bg.faces[bg.kinds == render.FLOOR].ravel()]
        np.testing.assert_allclose(floor[:, 1], verts[:, 1].max(), atol=1e-9)
    # Camera below the floor: no floor.
    bg = render.sample_background(rng, CAM, root, verts - [0, 1.5, 0])
    assert not (bg.kinds == render.FLOOR).any()


def test_axial_noise_statistics():
    rng = np.random.default_rng(0)
    p = noise.NoiseParams()
    for z in (2.0, 4.0):
        d = np.full((200, 200), z, np.float32)
        out = noise.apply_noise(d, np.ones_like(d), rng, p, fx=525.0)
        v = out.depth[out.depth > 0]
        assert v.size > 0.95 * d.size
        expected = 0.0012 + 0.0019 * (z - 0.4) ** 2
        assert abs(v.std() / expected - 1) < 0.08, (z, v.std(), expected)
        assert abs(v.mean() - z) < 0.002
        mm = v.astype(np.float64) * 1000
        np.testing.assert_allclose(mm, np.round(mm), atol=1e-2)  # millimetre grid
    assert noise.axial_sigma(2.0, np.deg2rad(70)) > noise.axial_sigma(2.0, 0.0)
    assert noise.lateral_sigma_px(0.0) == pytest.approx(0.8)


def test_disparity_quantisation():
    d = np.full((20, 20), 3.0, np.float32)
    p = noise.NoiseParams(axial=False, disparity_quantisation=True, quantise_m=0.0,
                          holes_per_frame=0, pixel_dropout=0)
    out = noise.apply_noise(d, np.ones_like(d), np.random.default_rng(0), p, fx=580.0)
    fb = 580.0 * 0.075
    disp = fb / out.depth[out.depth > 0].astype(np.float64)
    np.testing.assert_allclose(disp * 8, np.round(disp * 8), atol=1e-3)


def test_shadow_mask():
    d = np.full((5, 100), 3.0)
    d[:, 50:70] = 1.0
    s = noise.shadow_mask(d, 525.0, 0.075)
    width = 525.0 * 0.075 * (1 / 1.0 - 1 / 3.0)  # 26.25 px on the left
    cols = np.flatnonzero(s[0])
    assert cols.min() == pytest.approx(50 - width, abs=1.01) and cols.max() == 49
    assert not s[:, 50:].any()


def test_noise_dropouts_and_ground_truth(body, sampler):
    fr = dataset.make_frame(body, sampler, np.random.default_rng(10), CAM, noise=True,
                            background=True)
    clean_body = dataset.make_frame(body, sampler, np.random.default_rng(10), CAM,
                                    noise=False, background=True)['vertex_ids'] >= 0
    d, lab, vid = fr['depth'], fr['labels'], fr['vertex_ids']
    assert (lab[d == 0] == 0).all() and (vid[d == 0] == -1).all()
    on = vid >= 0
    np.testing.assert_array_equal(body.part_labels.numpy()[vid[on]], lab[on])
    # Some body pixels lost (edges, holes), most kept.
    assert 0.75 * clean_body.sum() < on.sum() < clean_body.sum()
    # Noisy depth of a body pixel stays close to its clean surface.
    both = on & clean_body & (fr['depth_clean'] > 0)
    err = np.abs(d[both] - fr['depth_clean'][both])
    assert np.median(err) < 0.01


def test_noise_result_take():
    d = np.array([[1.0, 1.0], [0.0, 2.0]], np.float32)
    out = noise.NoiseResult(d, np.array([[0, 0], [-1, 3]]))
    np.testing.assert_array_equal(out.take(np.array([[7, 8], [9, 10]]), -1),
                                  [[7, 7], [-1, 10]])


def test_determinism(body, sampler):
    a = dataset.make_frame(body, sampler, np.random.default_rng(11), SMALL)
    b = dataset.make_frame(body, sampler, np.random.default_rng(11), SMALL)
    c = dataset.make_frame(body, sampler, np.random.default_rng(12), SMALL)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert not np.array_equal(a['depth'], c['depth'])
    assert set(a) >= {'depth', 'labels', 'vertex_ids', 'vertices', 'joints', 'pose', 'shape',
                      'global_orient', 'transl', 'K'}
    assert a['vertices'].shape == (body.num_vertices, 3)
    assert a['joints'].shape == (len(body.joint_names), 3)
    np.testing.assert_array_equal(a['K'], SMALL.K)


def test_frame_placement(body, sampler):
    rng = np.random.default_rng(7)
    for _ in range(6):
        fr = dataset.make_frame(body, sampler, rng, SMALL, noise=False, background=False)
        root = fr['joints'][0]
        assert 1.0 - 0.3 <= root[2] <= 5.0 + 0.3
        uv = SMALL.project(fr['vertices'])
        inside = ((uv >= -0.5) & (uv <= [SMALL.width - 0.5, SMALL.height - 0.5])).all(1)
        if root[2] > 2.5:  # far enough to fit: the whole body is in view
            assert inside.all()
        assert inside.mean() > 0.5
        # The returned parameters reproduce the vertices.
        import torch
        out = body(torch.as_tensor(fr['pose'])[None], torch.as_tensor(fr['shape'])[None],
                   torch.as_tensor(fr['global_orient'])[None],
                   torch.as_tensor(fr['transl'])[None])
        np.testing.assert_allclose(out.vertices[0].detach().numpy(), fr['vertices'],
                                   atol=1e-4)


def test_sequence_smooth(body, sampler):
    seq = list(dataset.make_sequence(body, sampler, np.random.default_rng(4), SMALL, 8,
                                     noise=False, background=True))
    seq2 = list(dataset.make_sequence(body, sampler, np.random.default_rng(4), SMALL, 8,
                                      noise=False, background=True))
    assert len(seq) == 8
    roots = np.stack([f['joints'][0] for f in seq])
    assert np.linalg.norm(np.diff(roots, axis=0), axis=1).max() < 0.05  # < 1.5 m/s @ 30 Hz
    np.testing.assert_array_equal(seq[0]['shape'], seq[-1]['shape'])
    for a, b in zip(seq, seq2):
        np.testing.assert_array_equal(a['depth'], b['depth'])
    v = np.stack([f['vertices'] for f in seq])
    assert np.abs(np.diff(v, axis=0)).max() < 0.1


def test_benchmark_render_runs(body):
    res = render.benchmark_render(body, sizes=((80, 60),), repeats=1)
    assert res['80x60']['body'] > 0 and res['80x60']['background'] > 0


def test_render_panel(tmp_path, body):
    from PIL import Image

    from smpl_depth_ros.body.parts import template_embedding
    from smpl_depth_ros.tools import render_panel
    fr = dataset.make_frame(body, PoseSampler(body), np.random.default_rng(1), SMALL)
    emb = template_embedding(body.canonical_vertices(), body.part_labels.numpy())
    img = render_panel.make_panel(fr['depth'], fr['labels'], fr['vertex_ids'], emb)
    assert img.size[0] > 3 * SMALL.width
    path = tmp_path / 'p.png'
    img.save(path)
    assert Image.open(path).size == img.size


def test_a_seated_body_gets_a_chair_under_it(body):
    """Pose mode 'seated' with SynthParams.chairs: a chair whose seat touches the
    buttocks and whose legs reach the floor, nothing of the body inside the seat, the
    same person as without it; a standing body gets none."""
    seated = PoseSampler(body, mode='seated')
    parts = body.part_labels.cpu().numpy()
    up = np.array([0.0, -1.0, 0.0])
    p = dataset.SynthParams(chairs=True, depth_range=(2.0, 3.0))
    found = 0
    for seed in range(6):
        a = dataset.make_frame(body, seated, np.random.default_rng(seed), CAM, noise=False,
                               params=p)
        b = dataset.make_frame(body, seated, np.random.default_rng(seed), CAM, noise=False,
                               params=dataclasses.replace(p, chairs=False))
        np.testing.assert_array_equal(a['vertices'], b['vertices'])  # the same person
        v = a['vertices'].astype(np.float64)
        up = dataset._up_axis(body, a['global_orient'])
        chair = render.chair_under(v, parts, up, np.random.default_rng(0))
        if chair is None:
            continue
        found += 1
        h, hc = v @ up, chair.vertices @ up
        assert abs(hc.min() - h.min()) < 1e-6  # legs on the floor under the feet
        on_seat = v[np.isin(parts, render.SEAT_PARTS)] @ up
        seat_top = on_seat.min() - 0.003
        assert np.isclose(hc[hc < seat_top + 1e-6].max(), seat_top, atol=1e-6)
        # The chair is seen: pixels that are neither body nor room without it.
        assert ((a['depth'] != b['depth']) & (a['vertex_ids'] < 0)).sum() > 50
    assert found >= 4
    stand = PoseSampler(body).template('stand')
    from smpl_depth_ros.synth.poses import placement
    go, tr = placement(body, np.zeros(body.num_shape), 0.3, 0.0, 0.0, np.array([0, 0, 2.5]))
    v, _ = dataset._forward(body, PoseSampler(body).to_model(stand[None])[0],
                            np.zeros(body.num_shape), go, tr)
    assert render.chair_under(v, parts, np.array([0.0, -1.0, 0.0]),
                              np.random.default_rng(0)) is None
