"""Correspondence network, preprocessing and the shipped weights (core, no ROS)."""
import os

import numpy as np
import pytest
import torch
from PIL import Image

from smpl_depth_ros.body.anny_model import AnnyBody
from smpl_depth_ros.net.data import make_fixed_set
from smpl_depth_ros.net.infer import CorrespondenceNet, default_weights
from smpl_depth_ros.net.preprocess import crop_depth, find_persons, network_input
from smpl_depth_ros.net.unet import INPUT_SIZE, build_network

REAL = os.path.join(os.path.dirname(__file__), 'data', 'five_people_depth_mm.png')
K_KINECT = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])


@pytest.fixture(scope='module')
def body():
    return AnnyBody()


@pytest.mark.parametrize('kind', ['double', 'single'])
def test_network_shapes(kind):
    net = build_network(kind).eval()
    with torch.no_grad():
        logits, coords = net(torch.zeros(2, 2, INPUT_SIZE, INPUT_SIZE))
    assert logits.shape == (2, 15, INPUT_SIZE, INPUT_SIZE)
    assert coords.shape == (2, 3, INPUT_SIZE, INPUT_SIZE)
    assert coords.min() >= 0 and coords.max() <= 1


def test_shipped_weights_are_small_and_useful(body):
    """The shipped double U-Net segments held-out synthetic crops (seed unseen in training)."""
    path = default_weights('anny')
    assert os.path.getsize(path) < 20e6
    net = CorrespondenceNet(body)
    assert net.meta['kind'] == 'double' and net.meta['body_vertices'] == body.num_vertices
    x, labels, coords, cm = make_fixed_set(body, 12, seed=4242)
    lab, co = net.predict(x.numpy())
    gt = labels.numpy()
    ious = [((lab == c) & (gt == c)).sum() / max(((lab == c) | (gt == c)).sum(), 1)
            for c in range(1, 15) if (gt == c).any()]
    assert np.mean(ious) > 0.6, np.mean(ious)
    m = cm.numpy()
    err = np.linalg.norm(co.transpose(0, 2, 3, 1)[m] - coords.numpy().transpose(0, 2, 3, 1)[m],
                         axis=1)
    assert np.median(err) < 0.08  # normalised canonical units (1 = body extent)
    ids = net.lookup(lab[0], co[0], (lab[0] > 0) & (x[0, 1].numpy() > 0))
    assert ids.min() >= 0 and ids.max() < body.num_vertices


def test_broad_network_segments_stereo_crops_and_broad_poses_better(body):
    """The second shipped network (the broad poses and, in its last training stage, the
    stereo presets it serves) segments held-out stereo-camera crops of broad poses better
    than the original one (Kinect v1 noise, activity templates), and is as small."""
    from smpl_depth_ros.net.data import SampleConfig
    from smpl_depth_ros.net.infer import broad_weights
    from smpl_depth_ros.synth.sensors import SENSORS
    path = broad_weights('anny')
    assert path is not None and os.path.getsize(path) < 20e6
    stereo = tuple(n for n, s in SENSORS.items() if s.kind == 'stereo')
    cfg = SampleConfig(poses='broad', sensors=stereo)
    x, labels, _, _ = make_fixed_set(body, 24, seed=4545, cfg=cfg)
    gt = labels.numpy()

    def miou(net):
        lab, _ = net.predict(x.numpy())
        return np.mean([((lab == c) & (gt == c)).sum() / max(((lab == c) | (gt == c)).sum(), 1)
                        for c in range(1, 15) if (gt == c).any()])
    broad, original = CorrespondenceNet(body, path), CorrespondenceNet(body)
    assert broad.meta['poses'] == 'broad'
    assert {'realsense_d435', 'oak_d'} <= set(broad.meta['sensors'])
    assert miou(broad) > miou(original) + 0.05, (miou(broad), miou(original))


def test_flip_tta_is_mirror_consistent_and_no_worse(body):
    """With flip_tta the prediction of a mirrored crop is exactly the mirrored prediction
    (left/right parts swapped, canonical x mirrored), which the plain pass is not; and it
    segments held-out crops at least as well."""
    from smpl_depth_ros.body.parts import MIRROR
    net = CorrespondenceNet(body)
    x, labels, coords, cm = make_fixed_set(body, 12, seed=4343)
    x = x.numpy()
    xm = x[..., ::-1].copy()

    def mirrored(lab, co):
        co = co[..., ::-1].copy()
        co[:, 0] = 1.0 - co[:, 0]
        return MIRROR[lab[..., ::-1]], co

    fg = x[:, 1] > 0
    for tta in (True, False):
        lab, co = net.predict(x, flip_tta=tta)
        lab_m, co_m = mirrored(*net.predict(xm, flip_tta=tta))
        same = (lab == lab_m)[fg].mean()
        cdiff = np.abs(co - co_m).transpose(0, 2, 3, 1)[fg].max()
        if tta:
            assert same > 0.999 and cdiff < 1e-4, (same, cdiff)
        else:
            assert same < 0.995 or cdiff > 1e-2, (same, cdiff)  # the plain pass is not

    def miou(lab):
        lt = labels.numpy()
        return np.mean([((lab == c) & (lt == c)).sum() / max(((lab == c) | (lt == c)).sum(), 1)
                        for c in range(1, 15) if (lt == c).any()])
    plain, tta = miou(net.predict(x, flip_tta=False)[0]), miou(net.predict(x, flip_tta=True)[0])
    assert tta > plain - 0.01, (plain, tta)


def test_bfloat16_network_gives_the_float32_labels(body):
    """In bfloat16 (`net_precision`, the default on a CPU with bfloat16 units) both
    shipped networks give float32's labels on held-out crops but for a few border pixels
    and coordinates within a small part of the network's own error (~0.07); 'auto' picks
    it only where the CPU has the units, never on CUDA; a switch back is float32 again."""
    from smpl_depth_ros.net.infer import bfloat16_units, broad_weights, resolve_precision
    x, _, _, _ = make_fixed_set(body, 12, seed=4646)
    x = x.numpy()
    for path in (default_weights('anny'), broad_weights('anny')):
        net = CorrespondenceNet(body, path)
        l32, c32 = net.predict(x)
        net.set_precision('bfloat16')
        assert net.dtype == torch.bfloat16
        l16, c16 = net.predict(x)
        assert c16.dtype == np.float32
        body_px = (l32 > 0) | (l16 > 0)
        assert (l16 == l32)[body_px].mean() > 0.99, (l16 == l32)[body_px].mean()
        d = np.linalg.norm(c16 - c32, axis=1)[l32 > 0]
        assert 0 < np.median(d) < 0.01, np.median(d)  # bfloat16 ran, and is close
        net.set_precision('float32')
        np.testing.assert_array_equal(net.predict(x)[1], c32)
    cpu, cuda = torch.device('cpu'), torch.device('cuda')
    assert resolve_precision('auto', cpu) == (torch.bfloat16 if bfloat16_units()
                                              else torch.float32)
    assert resolve_precision('auto', cuda) == torch.float32
    assert resolve_precision('bfloat16', cuda) == torch.bfloat16
    with pytest.raises(ValueError, match='net_precision'):
        resolve_precision('half', cpu)


def test_person_detection_on_real_kinect_frame():
    depth = np.asarray(Image.open(REAL)).astype(np.float32) / 1000.0
    crops = find_persons(depth, K_KINECT, 0.5, 10.0, min_pixels=400, max_persons=8)
    big = [c for c in crops if c.mask.sum() > 15000]
    assert len(big) >= 4  # five people, two of them touching
    # Most central first.
    centres = [abs(c.u0 + c.scale * c.size / 2 - 320) for c in crops]
    assert centres[0] == min(centres)
    x = network_input(crop_depth(depth, crops[0]), crops[0].median_depth)
    assert x.shape == (2, INPUT_SIZE, INPUT_SIZE) and x[1].sum() > 500


def test_weights_for_another_body_are_refused(body, tmp_path):
    ck = torch.load(default_weights('anny'), map_location='cpu', weights_only=False)
    ck['meta']['body_vertices'] = 6890
    p = tmp_path / 'w.pt'
    torch.save(ck, p)
    with pytest.raises(ValueError, match='6890'):
        CorrespondenceNet(body, str(p))
    with pytest.raises(FileNotFoundError, match='train_correspondence'):
        CorrespondenceNet(body, str(tmp_path / 'missing.pt'))


def test_depth_jumps_are_edges_above_the_threshold_widened_by_the_noise():
    """A depth jump is an edge above 6 cm (at 2 m) plus 3 times the sensor's excess noise:
    with 1 cm of excess a 7.5 cm step is no edge and a 10 cm one is; with none, both are.
    Rows and columns alike, at full and half resolution, in both edge maps."""
    from smpl_depth_ros.net.preprocess import _depth_edges

    def excess(z):
        return np.full(np.shape(z), 0.01)
    for step, with_noise in ((0.075, False), (0.10, True)):
        for d in (np.full((40, 60), 2.0, np.float32), np.full((60, 40), 2.0, np.float32).T):
            if d.flags['C_CONTIGUOUS']:
                d[:, 30:] += step  # a jump between columns 29 and 30
            else:
                d[30:, :] += step  # (transposed: between rows 29 and 30)
            for s, side in ((1, 0), (1, 1), (2, 0), (2, 1)):  # side: far side, both
                plain, noisy = _depth_edges(d, s)[side], _depth_edges(d, s, excess)[side]
                for edges, expected in ((plain, True), (noisy, with_noise)):
                    e = edges if d.flags['C_CONTIGUOUS'] else edges.T
                    cols = np.flatnonzero(e.any(0))
                    assert (len(cols) > 0) == expected, (step, s, cols)
                    assert all(29 // s <= c <= 30 // s for c in cols), cols


def test_a_depth_jump_cuts_on_its_far_side_and_a_thin_limb_stays_whole():
    """A limb two (decimated) pixels wide at 4 m before a wall at 5 m, with an invalid
    pixel on one side (a flying pixel dropped): the far-side map marks the wall's pixels,
    not the limb's, so the limb keeps its width and is still cut apart from the wall; the
    both-sides map marks the limb's border too. At full and half resolution."""
    from scipy import ndimage

    from smpl_depth_ros.net.preprocess import _depth_edges
    for s in (1, 2):
        d = np.full((40 * s, 60 * s), 5.0, np.float32)
        d[:, 30 * s:32 * s] = 4.0  # the limb: decimated columns 30 and 31
        d[:, 29 * s] = 0.0  # an invalid pixel column on its left
        edges, jumps = _depth_edges(d, s)
        assert not edges[:, 30:32].any()
        assert edges[:, 32].all()  # the wall beside it
        assert jumps[:, 30].all() and jumps[:, 32].all()
        valid = d[::s, ::s] > 0
        lab, _ = ndimage.label(valid & ~edges)
        assert len(np.unique(lab[:, 30:32])) == 1 and lab[0, 30] > 0
        assert not np.isin(lab[:, 33:], lab[0, 30]).any()
        assert not np.isin(lab[:, :29], lab[0, 30]).any()


def test_split_side_by_side():
    """Two people touching side by side -> split at the dip between the heads; one person
    (a single high point, arms out) -> not split."""
    from smpl_depth_ros.net.preprocess import square_crop, split_side_by_side
    K = np.array([[500.0, 0, 160], [0, 500, 120], [0, 0, 1]])  # 2 m: 250 px per metre
    m = np.zeros((240, 320), bool)
    m[60:240, 60:140] = True     # body 1 (shoulders at row 60), 0.32 m wide
    m[20:60, 85:115] = True      # head 1: 16 cm above the shoulders
    m[60:240, 140:220] = True    # body 2, touching body 1
    m[10:60, 165:195] = True     # head 2
    crop = square_crop(60, 10, 219, 239, median_depth=2.0, mask=m)
    assert split_side_by_side(crop, K) == []  # a 16-20 cm dip is less than 20 cm
    m[0:60, 85:115] = True       # taller heads/necks: the dip is now 24 cm
    m[0:60, 165:195] = True
    a, b = split_side_by_side(crop, K)
    assert a.mask.any(1).sum() > 0 and not (a.mask & b.mask).any()
    assert (a.mask | b.mask).sum() == m.sum()
    cut = np.flatnonzero(b.mask.any(0))[0]
    assert 115 <= cut <= 165  # between the heads
    assert (a.exclude == b.mask).all() and (b.exclude == a.mask).all()
    one = np.zeros_like(m)
    one[40:240, 120:200] = True  # torso
    one[40:60, 40:280] = True    # arms out
    one[0:40, 145:175] = True    # head
    assert split_side_by_side(square_crop(40, 0, 279, 239, median_depth=2.0, mask=one),
                              K) == []


def test_background_seen_between_the_legs_is_ranked_last():
    """A synthetic scene: a person-sized blob at 2.5 m whose legs frame a patch of the
    4 m wall (cut off from the rest of the wall by the person); find_persons returns the
    person first and flags the patch as `behind`."""
    from smpl_depth_ros.net.preprocess import find_persons
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    d = np.zeros((480, 640), np.float32)
    d[0:300, 250:390] = 2.5           # the person (~0.7 m wide, cut by the image top)
    d[180:300, 300:340] = 4.0         # the wall between the legs: nearer the image centre
    cands = find_persons(d, K, 0.5, 6.0, min_pixels=300, max_persons=3)
    assert len(cands) == 2
    assert not cands[0].behind and abs(cands[0].median_depth - 2.5) < 0.05
    assert cands[1].behind and abs(cands[1].median_depth - 4.0) < 0.05


def test_enclosed_share_tells_a_gap_from_a_person_beside():
    """The wall seen between a person's legs is enclosed by the person's pixels, row by
    row; a person standing beside a nearer one whose blob a floor strip widens (so that
    the blob's box holds them, as stereo noise makes it) is not."""
    from smpl_depth_ros.net.preprocess import enclosed_share
    near = np.zeros((480, 640), bool)
    near[0:300, 250:390] = True
    gap = np.zeros_like(near)
    gap[180:300, 300:340] = True
    near &= ~gap
    assert enclosed_share(gap, near) == 1.0
    near[300:340, 250:600] = True      # a floor strip joined to the near person
    beside = np.zeros_like(near)
    beside[100:300, 450:520] = True    # a farther person standing above that strip
    assert enclosed_share(beside, near) == 0.0
    half = np.zeros_like(near)
    half[150:250, 100:200] = True      # half of its rows have the near blob on both sides
    other = np.zeros_like(near)
    other[150:200, 50:250] = True
    other[150:200, 100:200] = False
    assert enclosed_share(half, other) == 0.5
    assert enclosed_share(np.zeros_like(near), near) == 0.0


def test_person_cut_in_two_by_an_arm_is_one_candidate():
    """An arm held across the body (nearer by 0.4 m) cuts a person bent forward into an
    upper and a lower half of similar size: they are one candidate. Two people side by
    side at the same depth stay two."""
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    d = np.zeros((480, 640), np.float32)
    d[60:420, 100:180] = 3.0          # person 1: ~2 m tall, ~0.45 m wide at 3 m
    d[232:420, 100:180] = 3.4         # ... bent forward: its legs 40 cm further
    d[220:232, 90:190] = 2.6          # its forearm across the waist, 40 cm nearer
    d[60:420, 400:480] = 3.0          # person 2, alone, same depth
    d[60:420, 490:570] = 3.05         # person 3, beside person 2 (a 10 cm gap)
    cands = find_persons(d, K, 0.5, 6.0, min_pixels=300, max_persons=6)
    people = sorted((c for c in cands if c.mask.sum() > 10000), key=lambda c: c.u0)
    assert len(people) == 3, [int(c.mask.sum()) for c in cands]
    rows = np.flatnonzero(people[0].mask.any(1))
    assert rows[0] <= 62 and rows[-1] >= 417  # both halves of person 1 in one mask
    for p in people[1:]:
        cols = np.flatnonzero(p.mask.any(0))
        assert cols[-1] - cols[0] < 100  # side by side: not merged


def test_a_person_beside_the_edge_of_a_nearer_wall_is_not_a_piece_of_it():
    """A person 0.2 m beside the edge of a wall 0.2 m nearer, and smaller than it in the
    image: within the depth gap of a piece of one body, and the two together no wider
    than a person could be, but too far apart in the image to be one body: the person is
    a candidate of their own, without the wall. A piece of a body small beside it (a
    hand) joins it from as far."""
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    d = np.zeros((480, 640), np.float32)
    d[:, :215] = 2.2                 # the wall's edge, 0.9 m of it in view
    d[60:432, 261:359] = 2.4         # the person: 1.7 m x 0.45 m, 0.2 m beside it
    cands = find_persons(d, K, 0.5, 6.0, min_pixels=300, max_persons=3)
    person = [c for c in cands if c.mask[250, 310]]
    assert person, [(round(c.median_depth, 2), int(c.mask.sum())) for c in cands]
    assert not person[0].mask[:, :215].any()
    # A small piece as far off is still the body's: a hand raised out of the image at the
    # top, its tips back in view 0.15 m above the head.
    d = np.zeros((480, 640), np.float32)
    d[40:432, 261:359] = 2.4         # the person
    d[0:8, 330:356] = 2.35           # their fingertips, the arm above the image
    (c,) = [c for c in find_persons(d, K, 0.5, 6.0, min_pixels=300, max_persons=3)
            if c.mask[250, 310]]
    assert c.mask[4, 340]


def test_a_person_touching_a_nearer_walls_edge_is_a_candidate_on_the_second_look():
    """A person right at the edge of a wall 0.15 m nearer is one blob with it in the first
    pass (a piece of a similar depth, touching it, the whole no wider than a person); the
    second look (`peel`) takes such a piece, big enough to be a body, as a candidate of its
    own."""
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    d = np.zeros((480, 640), np.float32)
    d[:, :215] = 2.2                 # the wall's edge
    d[60:432, 217:315] = 2.35        # the person, touching it in the image
    first = find_persons(d, K, 0.5, 6.0, min_pixels=300, max_persons=3)
    assert [c for c in first if c.mask[250, 260]][0].mask[250, 100]  # one blob
    again = find_persons(d, K, 0.5, 6.0, min_pixels=300, max_persons=3, peel=True)
    person = [c for c in again if c.mask[250, 260]]
    assert person and not person[0].mask[:, :205].any()  # (grown by GROW_PX at most)


def test_child_in_front_of_an_adult_stays_two_candidates():
    """One below the other but the lower one nearer (a child 0.4 m in front of an adult):
    two people, not the two halves of one."""
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    d = np.zeros((480, 640), np.float32)
    d[100:420, 280:360] = 3.4         # the adult, 1.9 m tall at 3.4 m
    d[250:420, 270:370] = 3.0         # the child in front, hiding the adult's legs
    cands = find_persons(d, K, 0.5, 6.0, min_pixels=300, max_persons=6)
    assert sorted(round(c.median_depth, 1) for c in cands) == [3.0, 3.4]


def test_training_crops_see_close_bodies_as_the_sensor_does(body, monkeypatch):
    """A body taller than the image (close range): with truncation the training crop is
    cut around its part inside the image, as at run time, and the crop pixels outside
    the sensor image are empty; without, around the whole projected body."""
    from smpl_depth_ros.net.data import SampleConfig, SampleMaker, training_crop
    uv = np.array([[250.0, -300.0], [390.0, 700.0]])  # 1000 px tall on a 640x480 image
    for truncate, rows in ((1.0, (0, 480)), (0.0, (-300, 700))):
        cfg = SampleConfig(truncate=truncate, crop_jitter=0.0, crop_scale=(1.0, 1.0))
        crop, truncated = training_crop(uv, 640, 480, cfg, np.random.default_rng(0))
        assert truncated == (truncate > 0)
        centre = crop.v0 + crop.scale * crop.size / 2
        assert abs(centre - sum(rows) / 2) < 2, (centre, rows)
        assert abs(crop.scale * crop.size - 1.15 * (rows[1] - rows[0])) < 3
    # A whole sample: the crop pixels outside the sensor image are empty.
    import smpl_depth_ros.net.data as data
    made = []

    def spy(*args):
        made.append(training_crop(*args))
        return made[-1]
    monkeypatch.setattr(data, 'training_crop', spy)
    maker = SampleMaker(body, SampleConfig(truncate=1.0, depth_range=(1.0, 1.1),
                                           background=0.0))
    cam = maker.cameras[0]
    maker.cameras = [cam]
    x, labels, coords, cm = maker(np.random.default_rng(1))
    crop, truncated = made[-1]
    assert truncated and labels.max() > 0 and x[1].sum() > 500
    outside = ~crop.sample_indices((cam.height, cam.width))[2]
    assert outside.any()
    # (The sample may come mirrored.)
    assert not x[1][outside].any() or not x[1][:, ::-1][outside].any()


def test_person_close_to_a_wall_is_peeled_off_it():
    """A person 8 cm in front of a wall at 4 m (less than the depth-jump threshold there)
    is one blob with the wall, too big for a person: the wall plane is peeled off it and
    the person found."""
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    d = np.full((480, 640), 4.08, np.float32)   # the wall fills the view
    d[150:400, 300:340] = 4.0                  # ~1.9 m tall, ~0.3 m wide
    cands = find_persons(d, K, 0.5, 6.0, min_pixels=300, max_persons=3)
    assert len(cands) == 1
    rows, cols = np.flatnonzero(cands[0].mask.any(1)), np.flatnonzero(cands[0].mask.any(0))
    assert abs(cands[0].median_depth - 4.0) < 0.02
    assert rows[0] >= 145 and rows[-1] <= 405 and cols[0] >= 295 and cols[-1] <= 345


def test_scene_planes_are_reported_facing_the_camera():
    """A floor 1.2 m below a camera looking 15 deg down, a person-sized box in front of
    it: the box is the candidate, and the floor comes back as its frame's plane
    (n . x = offset in the camera frame, unit n towards the camera), its points on it;
    the wall peeled off a person is reported too."""
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    H, W = 480, 640
    t = np.radians(15.0)
    # Floor y_world = -1.2 (world y up); camera optical frame: y down, tilted by t.
    n_cam = np.array([0.0, -np.cos(t), -np.sin(t)])  # world up, in the camera frame
    v, u = np.mgrid[0:H, 0:W]
    ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1)
    denom = ray @ n_cam  # the floor: n_cam . x = -1.2
    z = np.where(denom < -1e-3, -1.2 / np.minimum(denom, -1e-3), 0.0)
    d = np.where((z > 0) & (z < 6.0), z, 0.0).astype(np.float32)
    d[120:330, 290:350] = 3.0  # a box at 3 m
    cands = find_persons(d, K, 0.5, 6.0, min_pixels=300, max_persons=3)
    assert len(cands) == 1 and abs(cands[0].median_depth - 3.0) < 0.05
    (plane,) = cands[0].planes
    assert plane[3] < 0 and np.allclose(plane[:3], n_cam, atol=0.03)
    assert abs(plane[3] + 1.2) < 0.03
    d2 = np.full((480, 640), 4.08, np.float32)
    d2[150:400, 300:340] = 4.0
    (c,) = find_persons(d2, K, 0.5, 6.0, min_pixels=300, max_persons=3)
    wall = [p for p in c.planes if abs(p[2]) > 0.9]
    assert len(wall) == 1 and wall[0][2] < 0 and abs(wall[0][3] + 4.08) < 0.03


def test_a_floor_in_a_tenth_of_the_view_is_found_for_any_seed():
    """Plane removal finds a floor that holds only a tenth of the points, beside a wall
    (not floor-like) and a large box top that is floor-like but not scene-sized: random
    RANSAC triples are all-floor once in a thousand draws, and the best-supported
    floor-like hypothesis (the box top) failing the size test must not end the search;
    the plane is fitted to its inliers (three points fix it only to their noise)."""
    from smpl_depth_ros.net.preprocess import _remove_planes
    rng = np.random.default_rng(0)
    wall = np.stack([rng.uniform(-2, 2, 6000), rng.uniform(-1.5, 0.9, 6000),
                     np.full(6000, 4.0)], 1)
    floor = np.stack([rng.uniform(-2, 2, 1000), np.full(1000, 0.9),
                      rng.uniform(1.5, 4.0, 1000)], 1)
    box_top = np.stack([rng.uniform(-0.4, 0.4, 2500), np.full(2500, 0.3),
                        rng.uniform(2.0, 2.6, 2500)], 1)
    box_front = np.stack([rng.uniform(-0.4, 0.4, 1500), rng.uniform(0.3, 0.9, 1500),
                          np.full(1500, 2.0)], 1)
    pts = np.concatenate([wall, floor, box_top, box_front])
    pts += rng.normal(0, 0.005, pts.shape)
    is_floor = np.zeros(len(pts), bool)
    is_floor[6000:7000] = True
    for seed in range(8):
        planes = []
        keep = _remove_planes(pts, np.random.default_rng(seed), planes=planes)
        assert (~keep[is_floor]).mean() > 0.95, seed
        assert keep[~is_floor].mean() > 0.95, seed
        assert len(planes) == 1, seed  # the box top is not one
        assert np.allclose(planes[0], [0, -1, 0, -0.9], atol=0.01), (seed, planes)


def test_peel_finds_a_person_at_a_wall_beside_a_person_sized_box():
    """The same wall scene with a box nearer the camera: the box is a person-sized
    candidate, so by default the wall blob is not peeled; with peel (the pipeline's second
    look when no candidate was a person) both are candidates."""
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    d = np.full((480, 640), 4.08, np.float32)
    d[150:400, 300:340] = 4.0
    d[100:350, 50:150] = 2.5  # 1.2 m x 0.5 m box
    first = find_persons(d, K, 0.5, 6.0, min_pixels=300, max_persons=3)
    assert [round(c.median_depth, 1) for c in first] == [2.5]
    both = find_persons(d, K, 0.5, 6.0, min_pixels=300, max_persons=3, peel=True)
    assert sorted(round(c.median_depth, 1) for c in both) == [2.5, 4.0]


def test_a_person_beside_a_wide_low_box_at_the_same_depth_is_a_candidate():
    """A box a hand's width beside a person, at the same depth and smaller in pixels, is
    merged as a small piece; the whole is too wide for one person, so the person's
    component alone is the candidate: in the first pass already, as it holds more than
    ALONE_SHARE of the group. With a box on either side (the person less than that
    share), the first pass drops the person with the boxes, and only the second look
    takes their component alone."""
    from smpl_depth_ros.net.preprocess import ALONE_SHARE
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    z = 3.0
    px = lambda m: int(round(m * 525.0 / z))  # noqa: E731 - metres at z to pixels
    top, left = 100, 300
    for boxes in (1, 2):
        d = np.zeros((480, 640), np.float32)
        d[top:top + px(1.7), left:left + px(0.5)] = z  # the person: 0.5 m x 1.7 m
        b0 = left + px(0.5) + px(0.08)
        d[top + px(1.3):top + px(1.7), b0:b0 + px(1.2)] = z + 0.05  # a box: 1.2 m x 0.4 m
        if boxes == 2:  # ... and one as big on the left
            d[top + px(1.3):top + px(1.7), left - px(1.28):left - px(0.08)] = z + 0.05
        person = 1.7 * 0.5 / (1.7 * 0.5 + boxes * 1.2 * 0.4)
        assert (person > ALONE_SHARE) == (boxes == 1)
        first = find_persons(d, K, 0.5, 6.0, min_pixels=300, max_persons=3)
        assert len(first) == (1 if boxes == 1 else 0)
        (c,) = find_persons(d, K, 0.5, 6.0, min_pixels=300, max_persons=3, peel=True)
        for crop in first + [c]:
            assert crop.mask[top + 10, left + 10]
            assert not crop.mask[top + px(1.5), b0 + px(0.6)]


def test_a_strip_of_floor_is_floor_on_the_second_look_only():
    """A floor seen only 0.7 m deep (a wall a metre behind a person) is not scene-sized
    for the first pass, but with the second look's `strip` rule it is; a wall-like plane
    of the same size is not, and neither is a floor-like patch narrower than a person
    could be wide."""
    from smpl_depth_ros.net.preprocess import FLOOR_STRIP_M, _scene_sized
    rng = np.random.default_rng(0)
    floor = np.stack([rng.uniform(-1.0, 1.0, 3000), np.full(3000, 0.9),
                      rng.uniform(1.8, 2.5, 3000)], 1)
    up = np.array([0.0, -1.0, 0.0])
    assert not _scene_sized(floor, up, 1.0)
    assert _scene_sized(floor, up, 1.0, FLOOR_STRIP_M)
    wall = floor[:, [0, 2, 1]]  # the same extents, standing
    assert not _scene_sized(wall, np.array([0.0, 0.0, -1.0]), 1.0, FLOOR_STRIP_M)
    narrow = floor * [0.7, 1, 1]  # 1.4 m wide
    assert not _scene_sized(narrow, up, 1.0, FLOOR_STRIP_M)


def _ray_cast(K, shape, surfaces):
    """A depth image of `surfaces`: each a function (ray directions (N, 3), z = 1) -> the
    depth at which each ray meets it (inf where it does not); the nearest wins."""
    H, W = shape
    rr, cc = np.mgrid[0:H, 0:W]
    rays = np.stack([(cc - K[0, 2]) / K[0, 0], (rr - K[1, 2]) / K[1, 1], np.ones((H, W))], -1)
    rays = rays.reshape(-1, 3)
    z = np.min([f(rays) for f in surfaces], axis=0)
    return np.where(np.isfinite(z), z, 0.0).reshape(H, W), rays.reshape(H, W, 3)


def _rect_at(z0, x, y):
    """A frontal rectangle at depth z0 over x = (lo, hi), y = (lo, hi)."""
    def hit(d):
        px, py = d[:, 0] * z0, d[:, 1] * z0
        return np.where((px >= x[0]) & (px <= x[1]) & (py >= y[0]) & (py <= y[1]), z0,
                        np.inf)
    return hit


def test_a_plane_is_measured_on_the_cells_the_camera_sees():
    """With the depth image given, a plane's empty cells hidden behind nearer surfaces or
    outside the image do not count against it: a floor strip half hidden by people
    standing on it is scene-sized. A horizontal slice through people, the wall seen
    through the gaps between them, is not."""
    from smpl_depth_ros.net.preprocess import FLOOR_STRIP_M, _scene_sized
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    up = np.array([0.0, -1.0, 0.0])

    def floor(d):  # y = 0.9 m below the camera, up to the wall at 2.5 m
        z = np.where(d[:, 1] > 1e-6, 0.9 / np.maximum(d[:, 1], 1e-6), np.inf)
        return np.where(z <= 2.5, z, np.inf)

    def wall(z0):
        return lambda d: np.full(len(d), z0)

    # A floor strip 0.7 m deep, 2 m wide, with people at 1.6 m hiding its middle.
    depth, rays = _ray_cast(K, (480, 640), [floor, wall(2.5), _rect_at(1.6, (-0.6, 0.6),
                                                                         (0.0, 0.9))])
    on = np.abs(rays[..., 1] * depth - 0.9) < 0.01
    q = (rays * depth[..., None])[on & (depth > 0)]
    q = q[np.abs(q[:, 0]) <= 1.0]
    assert not _scene_sized(q, up, 1.0, FLOOR_STRIP_M)
    assert _scene_sized(q, up, 1.0, FLOOR_STRIP_M, view=(depth, K, 1))
    # Three people at 2.0, 2.6 and 3.2 m, a wall at 4 m, sliced 0.3 m below the camera.
    people = [_rect_at(z0, (x - 0.15, x + 0.15), (-0.8, 0.9))
              for z0, x in ((2.0, -1.0), (2.6, 0.0), (3.2, 1.0))]
    depth, rays = _ray_cast(K, (480, 640), [wall(4.0), *people])
    pts = rays * depth[..., None]
    q = pts[(np.abs(pts[..., 1] - 0.3) < 0.01) & (depth < 3.5)]
    assert not _scene_sized(q, up, 1.0, view=(depth, K, 1))


def test_a_noisy_wall_found_again_takes_no_further_planes_place():
    """A far wall seen with stereo noise wider than the inlier band: after its plane is
    removed, the rest of its points make the same plane again, which is removed too but
    does not use up `max_planes`: the floor is still found."""
    from smpl_depth_ros.net.preprocess import _remove_planes
    rng = np.random.default_rng(1)
    n = 20000
    for sd in (0.05, 0.08):  # the wall's noise, against a 3 cm inlier band
        wall = np.stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 0.9, n),
                         4.0 + rng.normal(0, sd, n)], 1)
        floor = np.stack([rng.uniform(-2, 2, 1500), 0.9 + rng.normal(0, 0.005, 1500),
                          rng.uniform(2.6, 3.9, 1500)], 1)
        for seed in range(3):
            keep = _remove_planes(np.concatenate([wall, floor]),
                                  np.random.default_rng(seed), max_planes=2, min_up=-1.0)
            assert keep[n:].mean() < 0.1, (sd, seed)  # the floor is removed
            assert keep[:n].mean() < 0.25, (sd, seed)  # and the wall


def test_stored_person_near_a_wall_on_a_strip_of_floor_is_found():
    """test/data/near_wall_kinect_v1.npz: a person bending forward 1.7 m from a Kinect
    v1, a wall 0.7 m behind, the floor between seen only 0.76 m deep: floor, person and
    wall are one blob. The second look peels the wall and, by the strip rule, the floor;
    the person is found, whatever the plane search's random stream and however the
    16UC1 frame is decoded (the node's float32 or float64), and fitted."""
    from smpl_depth_ros.config import PipelineConfig
    from smpl_depth_ros.depth_codec import bytes_to_depth, depth_mm_to_bytes
    from smpl_depth_ros.pipeline import Reconstructor
    f = np.load('test/data/near_wall_kinect_v1.npz')
    H, W = f['depth_mm'].shape
    node = bytes_to_depth(depth_mm_to_bytes(f['depth_mm'])[0], W, H, '16UC1')
    depth = f['depth_mm'] / 1000.0
    for decoded in (node, depth):
        for seed in range(8):
            crops = find_persons(decoded, f['K'], 0.5, 6.0, 400, max_persons=3, seed=seed)
            assert crops and 1.5 < crops[0].median_depth < 2.1, seed
    p = Reconstructor(PipelineConfig(tracking=False, device='cpu')).process(
        depth, f['K']).persons[0]
    assert np.linalg.norm(p.vertices - f['vertices'], axis=1).mean() < 0.04


def test_training_in_bfloat16_follows_float32(body, tmp_path):
    """--precision bfloat16: the forward pass runs under autocast, the loss and the
    gradients stay those of float32 within bfloat16's rounding, the weights and the
    optimiser stay float32, and the command runs end to end."""
    import argparse
    import copy

    from smpl_depth_ros.net import train
    from smpl_depth_ros.net.data import make_fixed_set
    x, labels, coords, cmask = make_fixed_set(body, 4, 5)
    base = argparse.Namespace(kind='double', ema=0.0, coord_weight=20.0, precision='float32')
    runs = {}
    for precision in ('float32', 'bfloat16'):
        torch.manual_seed(0)
        r = train._Run(argparse.Namespace(**{**vars(base), 'precision': precision}), 1e-3,
                       str(tmp_path / f'{precision}.pt'), '', torch.device('cpu'), None)
        before = copy.deepcopy(r.net.state_dict())
        r.train_step(x, labels, coords, cmask, None, 0.5)
        runs[precision] = (r, before)
    (f32, b32), (b16, _) = runs['float32'], runs['bfloat16']
    assert abs(b16.run_loss - f32.run_loss) < 0.05 * f32.run_loss
    step32 = torch.cat([(p - b32[k]).flatten() for k, p in f32.net.state_dict().items()
                        if p.is_floating_point()])
    step16 = torch.cat([(p - b32[k]).flatten() for k, p in b16.net.state_dict().items()
                        if p.is_floating_point()])
    assert float(torch.nn.functional.cosine_similarity(step32, step16, dim=0)) > 0.9
    assert not torch.equal(step32, step16)  # bfloat16 did run
    assert all(p.dtype == torch.float32 for p in b16.net.parameters())
    out = tmp_path / 'w.pt'
    train.main(['--out', str(out), '--steps', '2', '--batch', '2', '--workers', '0',
                '--val-size', '2', '--val-every', '2', '--precision', 'bfloat16'])
    meta = torch.load(out, map_location='cpu', weights_only=True)['meta']
    assert meta['steps'] == 2 and '--precision bfloat16' in meta['command']


def test_train_correspondence_runs_checkpoints_and_resumes(body, tmp_path):
    """The training command end to end on a tiny budget: weights, JSON log, validation
    PNG and checkpoint are written; --resume continues from the checkpoint's step; the
    weights load for inference; --class-balance weighs small parts up, not background;
    --ema validates and saves the weight average, kept across --resume; --truncate sets
    the training crops' truncation (recorded in the weights' meta); --also-lr trains a
    second network on the same samples into its own files."""
    import json

    from smpl_depth_ros.net import train
    out = tmp_path / 'w.pt'
    args = ['--out', str(out), '--steps', '3', '--batch', '2', '--workers', '0',
            '--val-size', '4', '--val-every', '2', '--ckpt-every', '2', '--seed', '3',
            '--class-balance', '0.4', '--ema', '0.5', '--truncate', '1.0', '--also-lr', '1e-4']
    train.main(args)
    other = torch.load(tmp_path / 'w.lr0.0001.pt', map_location='cpu', weights_only=True)
    assert other['meta']['lr'] == 1e-4 and other['meta']['steps'] == 3
    assert [e['step'] for e in json.loads((tmp_path / 'w.lr0.0001.log.json').read_text())] == [2, 3]
    log = json.loads((tmp_path / 'w.log.json').read_text())
    assert [e['step'] for e in log] == [2, 3] and 0 <= log[-1]['miou'] <= 1
    assert (tmp_path / 'w.val.png').exists() and (tmp_path / 'w.pt.ckpt').exists()
    train.main([*args[:2], '--steps', '5', *args[4:], '--resume'])
    log = json.loads((tmp_path / 'w.log.json').read_text())
    assert [e['step'] for e in log] == [2, 3, 4, 5]
    assert all(0 <= e['miou_live'] <= 1 for e in log)  # the live weights, beside the average
    ckpt = torch.load(str(out) + '.ckpt', map_location='cpu', weights_only=False)
    saved = torch.load(out, map_location='cpu', weights_only=False)['state_dict']
    for k, v in ckpt['ema'].items():  # the average is what was saved, not the live weights
        assert torch.equal(saved[k], v.half() if v.is_floating_point() else v), k
    assert any(not torch.allclose(ckpt['ema'][k], ckpt['net'][k])
               for k in ckpt['net'] if ckpt['net'][k].is_floating_point())
    ck = torch.load(out, map_location='cpu', weights_only=False)
    assert ck['meta']['steps'] == 5 and '--class-balance 0.4' in ck['meta']['command']
    assert ck['meta']['truncate'] == 1.0
    net = CorrespondenceNet(body, str(out))
    x = np.zeros((1, 2, INPUT_SIZE, INPUT_SIZE), np.float32)
    lab, coords = net.predict(x)
    assert lab.shape == (1, INPUT_SIZE, INPUT_SIZE) and coords.shape == (1, 3, INPUT_SIZE,
                                                                          INPUT_SIZE)
    labels = torch.tensor([0] * 800 + [2] * 150 + [7] * 10 + list(range(15)))
    w = train.class_weights(labels, 0.4)
    assert w[0] == 1.0 and w[2] == 1.0 and w[7] > 2.5
    # The average itself: a = d * a + (1 - d) * b on every float tensor.
    a, b = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
    avg = train.WeightAverage(a, 0.75)
    avg.update(b)
    assert torch.allclose(avg.net.weight, 0.75 * a.weight + 0.25 * b.weight)
    assert train.class_weights(labels, 0.0) is None


def test_small_holes_are_filled_from_their_nearest_valid_pixel_and_wide_gaps_stay():
    """fill_small_holes: an invalid pixel inside the valid region's closing by a 5x5 square
    (scipy's binary_closing, outside the image counted valid) takes its nearest valid
    pixel's depth; every other pixel keeps its own (random masks of any shape)."""
    from scipy import ndimage

    from smpl_depth_ros.net.preprocess import fill_small_holes
    rng = np.random.default_rng(0)
    for _ in range(100):
        h, w = rng.integers(1, 60, 2)
        d = np.where(rng.random((h, w)) < rng.random(), 0.0,
                     rng.uniform(0.5, 5.0, (h, w))).astype(np.float32)
        valid = d > 0
        holes = ndimage.binary_closing(valid, np.ones((5, 5), bool), border_value=1) & ~valid
        out = fill_small_holes(d)
        assert np.array_equal(out[~holes], d[~holes])
        if holes.any():
            r, c = ndimage.distance_transform_edt(~valid, return_distances=False,
                                                  return_indices=True)
            assert np.array_equal(out[holes], d[r[holes], c[holes]])
    d = np.full((20, 20), 2.0, np.float32)
    d[5:15, 8:14] = 0.0  # a gap 6 pixels wide: not a small hole
    d[2, 2] = 0.0
    out = fill_small_holes(d)
    assert out[2, 2] == 2.0 and (out[5:15, 8:14] == 0).all()
