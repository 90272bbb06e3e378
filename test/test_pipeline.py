"""The Reconstructor end to end on synthetic frames, and its input validation."""
from pathlib import Path

import numpy as np
import pytest

from smpl_depth_ros.config import PipelineConfig
from smpl_depth_ros.pipeline import Reconstructor
from smpl_depth_ros.synth.camera import get_camera
from smpl_depth_ros.synth.dataset import make_frame, make_sequence
from smpl_depth_ros.synth.poses import PoseSampler
from smpl_depth_ros.types import InputError


@pytest.fixture(scope='module')
def rec():
    return Reconstructor(PipelineConfig(device='cpu'))


def _frame(rec, seed, **kw):
    return make_frame(rec.body, PoseSampler(rec.body), np.random.default_rng(seed),
                      get_camera('kinect_v1'), **kw)


def test_reconstructs_a_synthetic_person(rec):
    errs = []
    for seed in (3, 9, 10):
        f = _frame(rec, seed)
        rec.reset()
        r = rec.process(f['depth'], f['K'])
        p = r.persons[0]
        assert p.vertices.shape == (rec.body.num_vertices, 3)
        assert r.labels.shape == f['depth'].shape and r.labels.max() <= 14
        assert p.mask.sum() > 200 and (r.labels[p.mask] > 0).all()
        assert set(r.timings_ms) >= {'preprocess', 'network', 'correspondence', 'fit', 'total'}
        errs.append(np.linalg.norm(p.vertices - f['vertices'], axis=1).mean())
    # Network + fit on noisy frames with background; the evaluation command reports
    # the real figures, this guards against regressions.
    assert np.median(errs) < 0.08, errs


def test_person_against_a_wall_beside_a_box_is_found(rec):
    """A person with their back 3 cm from a wall (one blob with it) and a person-sized box
    nearer the camera: the box is the only candidate of the first look and the network
    sees no body in it; the second look peels the wall off and finds the person."""
    from smpl_depth_ros.net.preprocess import find_persons
    f = _frame(rec, 3, background=False, noise=False)
    d = f['depth'].copy()
    body = d > 0
    d[~body] = np.percentile(d[body], 98) + 0.03  # the wall
    d[60:300, 10:110] = 2.0                       # the box: 1.1 m x 0.4 m at 2 m
    first = find_persons(d, f['K'], 0.5, 6.0, 400, 3)
    assert [round(c.median_depth, 1) for c in first] == [2.0]  # the person is hidden
    rec.reset()
    r = rec.process(d, f['K'])
    p = r.persons[0]
    assert abs(np.median(d[p.mask]) - np.median(f['depth'][body])) < 0.05
    assert np.linalg.norm(p.vertices - f['vertices'], axis=1).mean() < 0.08


def test_tracking_warm_starts_consecutive_frames(rec):
    f = _frame(rec, 3)
    rec.reset()
    a = rec.process(f['depth'], f['K'], stamp_ns=1_000_000_000)
    b = rec.process(f['depth'], f['K'], stamp_ns=1_033_000_000)
    c = rec.process(f['depth'], f['K'], stamp_ns=9_000_000_000)  # long gap: reset
    assert not a.persons[0].tracked and b.persons[0].tracked and not c.persons[0].tracked
    assert np.linalg.norm(a.persons[0].vertices - b.persons[0].vertices, axis=1).mean() < 0.03


def test_tracking_fits_the_pose_at_the_mean_of_sampled_shapes(monkeypatch):
    """A new track keeps its cold fit's shape; every n-th tracked frame adds a shape
    sample (a short fit with the shape free: the samples are recorded as the track
    receives them), and the frames after it are fitted at the samples' mean."""
    from smpl_depth_ros.tracking import Track
    samples = []
    add = Track.add_shape_sample

    def recorded(track, shape):
        samples.append(np.array(shape, np.float64))
        add(track, shape)
    monkeypatch.setattr(Track, 'add_shape_sample', recorded)
    rec = Reconstructor(PipelineConfig(device='cpu', shape_sample_every=2))
    f = _frame(rec, 3)
    rng = np.random.default_rng(0)
    shapes = []
    for n in range(6):  # the same body, new sensor noise in each frame
        d = np.where(f['depth'] > 0, f['depth'] + rng.normal(0, 0.01, f['depth'].shape), 0)
        r = rec.process(d.astype(np.float32), f['K'], stamp_ns=(1 + n) * 33_000_000)
        assert r.persons[0].tracked == (n > 0)
        shapes.append(r.persons[0].params.shape)
    (track,) = rec.tracker.tracks
    assert track.shapes[1] == 2 and len(samples) == 2  # tracked frames 2 and 4 were sampled
    np.testing.assert_array_equal(shapes[1], shapes[0])  # the cold fit's, until sampled
    np.testing.assert_array_equal(shapes[2], shapes[1])
    np.testing.assert_allclose(shapes[3], samples[0], atol=1e-6)  # the first sample's
    np.testing.assert_array_equal(shapes[4], shapes[3])
    np.testing.assert_allclose(shapes[5], (samples[0] + samples[1]) / 2, atol=1e-6)  # the mean
    # the samples are fits of their own (a short fit can leave one where it started)
    assert max(np.abs(s - shapes[0]).max() for s in samples) > 1e-4
    assert {p.track_id for p in r.persons} == {track.id}
    rec.reset()
    assert rec.tracker.tracks == []


def test_tracking_resets_when_the_person_leaves_or_the_track_is_lost(rec):
    f, g = _frame(rec, 3), _frame(rec, 9)
    rec.reset()
    assert not rec.process(f['depth'], f['K'], stamp_ns=1_000_000_000).persons[0].tracked
    # Nobody in the next frame: the track is dropped ...
    with pytest.raises(InputError):
        rec.process(np.where(f['depth'] > 0, 9.5, 0).astype(np.float32), f['K'],
                    stamp_ns=1_033_000_000)
    # ... so the person coming back is fitted cold, and tracked from then on.
    assert not rec.process(f['depth'], f['K'], stamp_ns=1_066_000_000).persons[0].tracked
    assert rec.process(f['depth'], f['K'], stamp_ns=1_100_000_000).persons[0].tracked
    # Another body in another pose 33 ms later: the warm fit's residual says the track is
    # lost; the frame is refitted cold and the result is close to that body.
    r = rec.process(g['depth'], g['K'], stamp_ns=1_133_000_000).persons[0]
    assert not r.tracked
    assert np.linalg.norm(r.vertices - g['vertices'], axis=1).mean() < 0.1


@pytest.mark.parametrize('make,reason', [
    (lambda f: (np.zeros_like(f['depth']), f['K']), 'no_valid_depth'),
    (lambda f: (np.full_like(f['depth'], np.nan), f['K']), 'no_valid_depth'),
    (lambda f: (f['depth'], np.zeros((3, 3))), 'bad_intrinsics'),
    (lambda f: (f['depth'][None], f['K']), 'bad_depth'),
    (lambda f: (np.ones((5000, 5000), np.float32), f['K']), 'too_large'),
    (lambda f: (np.where(f['depth'] > 0, 9.5, 0).astype(np.float32), f['K']), 'no_person'),
])
def test_bad_input_raises_clear_errors(rec, make, reason):
    f = _frame(rec, 3, background=False)
    depth, K = make(f)
    with pytest.raises(InputError) as e:
        rec.process(depth, K)
    assert e.value.reason == reason and str(e.value)
    # ... and the next good frame still works.
    assert rec.process(f['depth'], f['K']).persons


@pytest.mark.parametrize('fx', [1e-9, 1e-4, 0.1, 0.2, 20.0, 1e9])
def test_implausible_focal_lengths_are_bad_intrinsics_not_memory(rec, fx):
    """A focal length no depth camera has (a field of view beyond 170 degrees, or a
    pinhole of a few hundredths of a degree) is rejected at once as bad intrinsics; it
    once made person finding ask for GiB to PiB of memory."""
    import tracemalloc
    f = _frame(rec, 3, background=False)
    K = f['K'].copy()
    K[0, 0] = K[1, 1] = fx
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match='field of view') as e:
            rec.process(f['depth'], K)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    # checked before any work: less than a copy of the frame is allocated
    assert e.value.reason == 'bad_intrinsics' and peak < f['depth'].nbytes, peak
    K = f['K'].copy()
    K[2, 2] = 2.0
    with pytest.raises(InputError, match=r'last row \[0.0, 0.0, 2.0\]'):
        rec.process(f['depth'], K)
    K = f['K'].copy()
    K[0, 2] = 1e7
    with pytest.raises(InputError, match=r'cx=1e\+07'):
        rec.process(f['depth'], K)
    assert rec.process(f['depth'], f['K']).persons


def test_real_kinect_frame_several_people(rec):
    """The one real frame (five people, two touching): every separated, fully visible
    person gets a fit whose observed points lie within a median 25 mm of the surface."""
    import os

    from PIL import Image

    from smpl_depth_ros.config import PipelineConfig
    from smpl_depth_ros.tools.reconstruct_image import point_to_surface
    path = os.path.join(os.path.dirname(__file__), 'data', 'five_people_depth_mm.png')
    depth = np.asarray(Image.open(path)).astype(np.float32) / 1000.0
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    multi = Reconstructor(PipelineConfig(device='cpu', tracking=False, max_persons=6,
                                         depth_max=8.0), body=rec.body)
    res = multi.process(depth, K)
    # All five, the two who touch at the same depth included (their blob's fit is rejected
    # and the blob split at the dip between their heads).
    assert len(res.persons) == 5
    roots = np.array([p.joints[0] for p in res.persons])
    assert min(np.linalg.norm(roots[i] - roots[j]) for i in range(5) for j in range(i)) > 0.3
    for p in res.persons:
        r, c = np.nonzero(p.mask)
        z = depth[r, c]
        pts = np.stack([(c - 319.5) * z / 525.0, (r - 239.5) * z / 525.0, z], 1)
        assert np.median(point_to_surface(pts, p.vertices, rec.body.faces_numpy())) < 0.025


def test_model_segmentation_leaves_the_floor_under_the_feet(rec, monkeypatch):
    """The margin of segmentation 'model' (pixels the network called background, near the
    fitted mesh) does not take the floor a foot stands on: no such pixel lies within
    PLANE_M of the frame's floor plane, whereas without the rule some do, and they are
    background in the truth."""
    from smpl_depth_ros import refine, segmentation
    from smpl_depth_ros.net.preprocess import find_persons

    m = segmentation.PLANE_M

    def floor_pixels(f):
        rec.reset()
        r = rec.process(f['depth'], f['K'])
        (plane, *_) = find_persons(f['depth'], f['K'], 0.5, 6.0, 400, 3)[0].planes
        rr, cc = np.nonzero((r.labels > 0) & (r.network_labels == 0))
        z = f['depth'][rr, cc].astype(np.float64)
        K = f['K']
        pts = np.stack([(cc - K[0, 2]) * z / K[0, 0], (rr - K[1, 2]) * z / K[1, 1], z], 1)
        on = np.abs(pts @ plane[:3] - plane[3]) <= m
        return on.sum(), (f['labels'][rr[on], cc[on]] == 0).mean() if on.any() else 1.0
    frames = [_frame(rec, seed) for seed in (3, 9, 10)]
    assert all(floor_pixels(f)[0] == 0 for f in frames)
    monkeypatch.setattr(segmentation, 'PLANE_M', 0.0)  # the rule off
    monkeypatch.setattr(refine, 'PLANE_M', 0.0)
    without = [floor_pixels(f) for f in frames]
    on = [n for n, _ in without]
    assert sum(on) > 20, without
    assert np.mean([bg for n, bg in without if n]) > 0.5, without


def test_model_segmentation_beats_the_networks_labels(rec, monkeypatch):
    """segmentation 'model' (default): the published labels come from the fitted mesh and
    agree with the truth better than the network's own (kept in network_labels); the
    sub-grid shortcut for large windows gives the exact labels up to a few pixels;
    'network' publishes the network's labels as they are."""
    from smpl_depth_ros import evaluation as ev
    from smpl_depth_ros import segmentation
    conf_model, conf_net = np.zeros((15, 15)), np.zeros((15, 15))
    frames = [_frame(rec, seed) for seed in (3, 9, 10)]
    for f in frames:
        rec.reset()
        r = rec.process(f['depth'], f['K'])
        valid = f['depth'] > 0
        gt = np.where(valid, f['labels'], 0)
        conf_model += ev.confusion(np.where(valid, r.labels, 0), gt)
        conf_net += ev.confusion(np.where(valid, r.network_labels, 0), gt)
        assert (r.labels[r.persons[0].mask] > 0).all()
        assert not r.labels[~r.persons[0].mask].any()
    assert ev.miou(conf_model) > ev.miou(conf_net) + 0.01, (ev.miou(conf_model),
                                                            ev.miou(conf_net))
    f = frames[0]
    monkeypatch.setattr(segmentation, 'MODEL_LABEL_POINTS', 1000)  # a sub-grid of 3 to 5 px
    rec.reset()
    sub = rec.process(f['depth'], f['K']).labels
    monkeypatch.setattr(segmentation, 'MODEL_LABEL_POINTS', 10 ** 9)  # every pixel on its own
    rec.reset()
    exact = rec.process(f['depth'], f['K']).labels
    body = (exact > 0) | (sub > 0)
    assert body.sum() > 1000 and (exact[body] == sub[body]).mean() > 0.99
    net = Reconstructor(PipelineConfig(device='cpu', segmentation='network'), body=rec.body)
    r = net.process(f['depth'], f['K'])
    assert r.labels is r.network_labels and r.labels.any()


def test_candidates_are_scored_on_their_own_blob_not_their_crop():
    """A person in front of a wall: its crop holds the wall too. The score is the share of
    the candidate's blob labelled body (times the parts seen), so the wall around it does
    not lower it, and a box labelled body on half of its blob scores below the person."""
    from smpl_depth_ros.net.preprocess import square_crop
    from smpl_depth_ros.pipeline import body_score
    H, W = 480, 640
    mask = np.zeros((H, W), bool)
    mask[100:300, 200:260] = True  # the person's blob
    crop = square_crop(200, 100, 259, 299, median_depth=2.0, mask=mask, size=64)
    rr, cc, inside = crop.sample_indices((H, W))
    valid = inside.copy()  # the wall: every crop pixel has depth
    on_blob = mask[rr, cc] & inside
    labels = np.zeros(valid.shape, np.uint8)
    rows = np.flatnonzero(on_blob.any(1))
    thirds = np.array_split(rows, 3)
    for part, rws in zip((1, 2, 9), thirds):  # head, torso, a leg
        labels[rws] = np.where(on_blob[rws], part, 0)
    assert body_score(crop, valid, labels, (H, W)) == pytest.approx(3.0)
    # Without its mask the same crop counts the wall as not-body: the old, crop-share score.
    whole = square_crop(200, 100, 259, 299, median_depth=2.0, mask=None, size=64)
    assert body_score(whole, valid, labels, (H, W)) < 0.5 * 3.0
    # Half of the blob labelled body, with the same parts: half the score.
    half = labels.copy()
    half[:, : labels.shape[1] // 2] = 0
    assert body_score(crop, valid, half, (H, W)) < 0.75 * 3.0


def test_icp_refit_takes_the_body_pixels_the_network_left_out(rec):
    """near_surface_pixels: with the true mesh as the fit and half the person's pixels
    (and a whole arm) left out as if the network had missed them, it returns body pixels
    the network did not have, nearly all of the missed ones within the margin of a vertex,
    each with its nearest vertex facing the camera (any vertex with fit.icp_front_cos 1:
    then some face away), none already in the fit, none on the floor; nothing with the
    margin at 0."""
    from scipy.spatial import cKDTree

    from smpl_depth_ros.net.preprocess import find_persons, pixel_points
    from smpl_depth_ros.refine import facing_camera, near_surface_pixels
    f = _frame(rec, 9)
    d, K, V, lab = f['depth'], f['K'], f['vertices'], f['labels']
    crop = find_persons(d, K, 0.5, 6.0, 400, 3)[0]
    assert crop.planes  # the frame has a floor
    rr, cc = np.nonzero((lab > 0) & (d > 0))
    keep = (np.arange(len(rr)) % 2 == 0) & ~np.isin(lab[rr, cc], (5, 7))  # arm, hand
    r, c = rr[keep], cc[keep]
    fc = rec.config.fit

    def left_out(cos_max=fc.icp_front_cos, margin=fc.icp_margin_m):
        return near_surface_pixels(d, K, V, r, c, crop, rec.surface,
                                   facing_camera(V, rec.faces, cos_max), margin)
    pts, vids = left_out()
    assert len(pts) and pts.dtype == np.float32 and vids.shape == (len(pts),)
    u = np.rint(pts[:, 0] * K[0, 0] / pts[:, 2] + K[0, 2]).astype(int)
    v = np.rint(pts[:, 1] * K[1, 1] / pts[:, 2] + K[1, 2]).astype(int)
    got = set(zip(v.tolist(), u.tolist()))
    assert not got & set(zip(r.tolist(), c.tolist()))
    assert (lab[v, u] > 0).mean() > 0.95
    valid = rec.surface.valid_vertex_ids
    # Nearly every missed body pixel within the margin of a vertex (the vertices are ~3 cm
    # apart, and the depth noise at 4.5 m is a few cm: about half of them).
    near = cKDTree(V[valid]).query(pixel_points(rr[~keep], cc[~keep], d[rr[~keep], cc[~keep]],
                                                K))[0] <= rec.config.fit.icp_margin_m
    missed = set(zip(rr[~keep][near].tolist(), cc[~keep][near].tolist()))
    assert len(missed) > 500 and len(got & missed) > 0.9 * len(missed)
    # Each takes its nearest vertex among those facing the camera (fit.icp_front_cos):
    # with any vertex allowed, some take one on the far side of a limb or silhouette.
    front = facing_camera(V, rec.faces, fc.icp_front_cos)
    assert front is not None and not front[valid].all()
    fv = valid[front[valid]]
    assert np.array_equal(vids, fv[cKDTree(V[fv]).query(pts)[1]])
    for pl in crop.planes:
        assert (np.abs(pts @ pl[:3] - pl[3]) > 0.02).all()
    pts1, vids1 = left_out(cos_max=1.0)
    assert np.array_equal(vids1, valid[cKDTree(V[valid]).query(pts1)[1]])
    assert (~front[vids1]).mean() > 0.02
    assert len(left_out(cos_max=1.0, margin=0.0)[0]) == 0


def test_icp_step_matches_pixels_to_vertices_facing_the_camera(rec):
    """refine_correspondences on the true mesh, from the true vertices: without
    fit.icp_front_cos (1 = any vertex) some pixels of the front surface snap to a nearer
    vertex on the far side of a limb or silhouette; with it (the default) none do, and the
    matches lie closer to the truth on the template."""
    from smpl_depth_ros.fit.rig import vertex_normals
    from smpl_depth_ros.net.preprocess import pixel_points
    from smpl_depth_ros.refine import facing_camera, refine_correspondences
    f = _frame(rec, 9)
    d, K, V, vid = f['depth'], f['K'], f['vertices'], f['vertex_ids']
    rr, cc = np.nonzero((vid >= 0) & (d > 0))
    true = vid[rr, cc]
    pts = pixel_points(rr, cc, d[rr, cc], K)
    cos_max = rec.config.fit.icp_front_cos
    assert cos_max < 1.0
    facing = (vertex_normals(V.astype(np.float64), rec.faces)
              * V / np.linalg.norm(V, axis=1, keepdims=True)).sum(1) < cos_max
    canon = rec.body.canonical_vertices()
    err = {}
    for c in (cos_max, 1.0):
        out = refine_correspondences(pts, true, V, rec.surface, facing_camera(V, rec.faces, c))
        err[c] = np.linalg.norm(canon[out] - canon[true], axis=1).mean()
        away = (~facing[out]).mean()
        assert (away == 0.0) if c < 1.0 else (away > 0.02), (c, away)
    assert err[cos_max] < err[1.0]


def test_flip_tta_falls_back_on_the_plain_pass_when_its_fit_is_rejected(rec, monkeypatch):
    """val_s2 frame 63 (`synth_bag --out data/val_s2 --frames 100 --seed 2`, stored in
    test/data): a body seen from the side at 4 m. The averaged plain and mirrored network
    passes can mislead a fit the plain pass alone gets right (with the network of
    2026-12-01 this frame's: 0.108 m median residual against 0.045). Here the averaged
    passes are made to mislead it (their canonical coordinates reflected through the
    template's centre: head for feet, front for back), so its fit is rejected; with
    flip_tta the candidate is retried on the plain pass, so the frame is reconstructed as
    it is without flip_tta."""
    from pathlib import Path
    f = np.load(Path(__file__).parent / 'data' / 'val_s2_frame63.npz')
    depth = f['depth_mm'].astype(np.float32) / 1000.0
    tta = Reconstructor(rec.config.with_overrides(flip_tta=True, tracking=False),
                        body=rec.body)
    predict, combine = tta.net.predict, tta.net.combine
    averaged = []

    def misleading(lab_coords):
        averaged.append(1)
        return lab_coords[0], (1.0 - lab_coords[1]).astype(np.float32)
    monkeypatch.setattr(tta.net, 'predict', lambda x, flip_tta=None: misleading(
        predict(x, flip_tta=flip_tta)) if flip_tta else predict(x, flip_tta=False))
    monkeypatch.setattr(tta.net, 'combine', lambda *raws: misleading(combine(*raws)))
    err = {}
    for name, r in (('plain', Reconstructor(rec.config.with_overrides(tracking=False),
                                            body=rec.body)), ('tta', tta)):
        p = r.process(depth, f['K']).persons[0]
        err[name] = np.linalg.norm(p.vertices - f['vertices'], axis=1).mean()
    assert averaged, 'the averaged passes were not used'
    assert err['tta'] < 0.06 and abs(err['tta'] - err['plain']) < 0.01, err


def test_a_person_sized_box_is_not_a_further_person(rec):
    """`synth_bag --seed 5 --sequence`'s first frames (one person, a box beside them) with
    `max_persons` 3: only the person is reported, with one ID, and the box, once found to
    be no person, is skipped while it stays put; also with the broad network (given as
    weights_path), which labels the box as body parts more readily: a new person needs a
    body score of MIN_COLD_SCORE, and a further one a fit the sensor does not see through
    (MAX_SEE_THROUGH). (Without both tests and that memory the box came back with the
    Kinect network before its chair fine-tune; with the present networks on these frames
    only in some runs, so that control is not asserted.)"""
    from smpl_depth_ros.net.infer import broad_weights

    def run(crops_seen=None, weights=''):
        multi = Reconstructor(PipelineConfig(device='cpu', max_persons=3,
                                             weights_path=weights), body=rec.body)
        predict = multi.net.predict

        def counting(x, **kw):  # the crops the network is run on, per frame
            crops_seen[-1] += len(x)
            return predict(x, **kw)
        if crops_seen is not None:
            multi.net.predict = counting
        seq = make_sequence(rec.body, PoseSampler(rec.body), np.random.default_rng(5),
                            get_camera('kinect_v1'), 150)
        out = []
        for i in range(6):
            f = next(seq)
            if crops_seen is not None:
                crops_seen.append(0)
            persons = multi.process(f['depth'], f['K'], stamp_ns=i * 33_333_333).persons
            out.append([(p.track_id, float(np.linalg.norm(p.joints[0] - f['joints'][0])))
                        for p in persons])
        return out

    crops_seen = []
    frames = run(crops_seen)
    assert all(len(f) == 1 and f[0][0] == 1 and f[0][1] < 0.1 for f in frames), frames
    # Once found to be no person, the box is skipped while it stays put (NOT_PERSON_FRAMES):
    # the network then sees the person's crop alone.
    assert crops_seen[0] > 1 and crops_seen[-1] == 1, crops_seen
    frames = run(weights=broad_weights('anny'))
    assert all(len(f) == 1 and f[0][0] == 1 and f[0][1] < 0.1 for f in frames), frames


def test_a_scene_piece_with_a_few_body_parts_is_no_new_person(rec, monkeypatch):
    """test/data/scene_piece_azure.npz (a frame of the broad-pose validation sweep, Azure
    Kinect NFOV at 3.5 m): the network labels a piece of the scene as a few body parts
    (body score 2.6, below a person's 3.7 or more). With `max_persons` 1 only the person
    is reported, near the truth; with 3, still only the person. Negative control: with the
    body score asked of a new person as low as 2 the piece is reported, a body 0.8 m from
    the person, and with one person wanted it is the one reported. (The network in float32:
    its labels are the same on every CPU; bfloat16's differ between CPU makes, here not.)"""
    from smpl_depth_ros import pipeline
    f = np.load(Path(__file__).parent / 'data' / 'scene_piece_azure.npz')
    depth = f['depth_mm'] / 1000.0
    truth = f['vertices']

    def offsets(max_persons):
        r = Reconstructor(PipelineConfig(device='cpu', tracking=False, net_precision='float32',
                                         max_persons=max_persons), body=rec.body)
        return sorted(float(np.linalg.norm(p.vertices - truth, axis=1).mean())
                      for p in r.process(depth, f['K']).persons)

    assert pipeline.MIN_COLD_SCORE > 2.6
    for n in (1, 3):
        pve = offsets(n)
        assert len(pve) == 1 and pve[0] < 0.08, (n, pve)
    monkeypatch.setattr(pipeline, 'MIN_COLD_SCORE', 2.0)
    assert offsets(1)[0] > 0.3
    pve = offsets(3)
    assert len(pve) == 2 and pve[0] < 0.08 and pve[1] > 0.3, pve


def test_a_frame_whose_fits_are_all_rejected_says_so(rec):
    """A person the network segments but no fit is accepted for (here: a residual bound
    no fit meets) is reported as such, with the best residual, not as 'no body seen'."""
    f = _frame(rec, 3, background=False)
    strict = Reconstructor(rec.config.with_overrides(reject_residual_m=0.001, sensor='none',
                                                     tracking=False), body=rec.body)
    with pytest.raises(InputError, match=r'no body fit explained them \(best median '
                                         r'residual \d+ mm > reject_residual_m 1 mm\)') as e:
        strict.process(f['depth'], f['K'])
    assert e.value.reason == 'no_person'


def test_detecting_the_next_frame_first_changes_nothing(rec):
    """The live node detects frame t + 1 (`Reconstructor.detect`) and makes its network
    passes ahead (`look_ahead`) before frame t is reconstructed (`reconstruct`), and
    finishes frame t (`finish`: the labels from the fitted meshes) after frame t + 1 is
    reconstructed: on a sequence of two people walking, with tracking, several persons and
    the 'auto' sensor noise, that order gives exactly what `process` gives frame by
    frame, IDs, meshes, pixels and labels alike, and the passes made ahead are used."""
    from smpl_depth_ros.synth.dataset import make_multi_sequence

    seq = make_multi_sequence(rec.body, PoseSampler(rec.body), np.random.default_rng(31),
                              get_camera('kinect_v1'), 150, persons=2)
    frames = [next(seq) for _ in range(5)]
    stamps = [(k + 1) * 33_333_333 for k in range(len(frames))]

    def out(r):
        return ([(p.track_id, p.vertices, p.mask) for p in r.persons], r.labels)
    one = Reconstructor(PipelineConfig(device='cpu', max_persons=3), body=rec.body)
    ahead = Reconstructor(PipelineConfig(device='cpu', max_persons=3), body=rec.body)

    def counted(r):  # the network passes the core makes
        net, calls = r.net, []
        net.predict = lambda *a, **k: calls.append(1) or type(net).predict(net, *a, **k)
        return calls
    passes_one, passes_ahead = counted(one), counted(ahead)
    expected = [out(one.process(f['depth'], f['K'], stamp_ns=s))
                for f, s in zip(frames, stamps)]
    dets = [ahead.detect(frames[0]['depth'], frames[0]['K'], stamp_ns=stamps[0])]
    ahead.look_ahead(dets[0])
    got, in_reconstruct, unfinished = [], 0, []
    for f, s in zip(frames[1:] + [None], stamps[1:] + [None]):
        if f is not None:
            dets.append(ahead.detect(f['depth'], f['K'], stamp_ns=s))
            ahead.look_ahead(dets[-1])
        passes_ahead.clear()
        r = ahead.reconstruct(dets[-2] if f is not None else dets[-1], finish=False)
        assert r.unfinished is not None and not r.labels.any()
        unfinished.append(r)
        in_reconstruct += len(passes_ahead)
        if len(unfinished) == 2:
            got.append(out(ahead.finish(unfinished.pop(0))))
    got.append(out(ahead.finish(unfinished.pop(0))))
    assert len(got) == len(expected)
    # Most passes were made ahead (the first frame's ranking needs them all).
    assert in_reconstruct < 0.5 * len(passes_one)
    assert sum(len(d.passes) for d in dets) >= len(passes_one) - in_reconstruct
    assert sum(len(e[0]) for e in expected) > len(frames)  # two people in some frames
    for (pe, le), (pg, lg) in zip(expected, got):
        assert [p[0] for p in pe] == [p[0] for p in pg]
        for a, b in zip(pe, pg):
            np.testing.assert_array_equal(a[1], b[1])
            np.testing.assert_array_equal(a[2], b[2])
        np.testing.assert_array_equal(le, lg)


def test_restart_gives_what_a_fresh_core_gives(rec):
    """After `restart` a used core (tracks, IDs, the 'auto' noise estimate and the fit's
    random stream all advanced by the tests above) reconstructs a sequence exactly as a
    newly loaded one: what a bag chunk gets on a worker that did other chunks before."""
    frames = [_frame(rec, s) for s in (3, 9)]
    rec.process(frames[1]['depth'], frames[1]['K'], stamp_ns=5)  # some history
    fresh = Reconstructor(PipelineConfig(device='cpu'))
    rec.restart()
    for k, f in enumerate(frames + frames[:1]):
        a = fresh.process(f['depth'], f['K'], stamp_ns=(k + 1) * 33_000_000)
        b = rec.process(f['depth'], f['K'], stamp_ns=(k + 1) * 33_000_000)
        assert [p.track_id for p in a.persons] == [p.track_id for p in b.persons]
        for p, q in zip(a.persons, b.persons):
            np.testing.assert_array_equal(p.vertices, q.vertices)


def test_a_tracked_person_half_hidden_gets_their_last_body_moved_into_place(rec):
    """A person tracked over five frames, then seen on one side only (the rest hidden):
    `_move_held_body` lays their last tracked body on those pixels, near the truth, and
    every pixel takes a vertex facing the camera. A cold fit (no tracked fit held) has no
    body to move."""
    from smpl_depth_ros.net.preprocess import pixel_points
    from smpl_depth_ros.refine import facing_camera
    seq = make_sequence(rec.body, PoseSampler(rec.body), np.random.default_rng(7),
                        get_camera('kinect_v1'), 12)
    rec.reset()
    frames = [next(seq) for _ in range(6)]
    for i, f in enumerate(frames[:5]):
        assert len(rec.process(f['depth'], f['K'], stamp_ns=i * 33_333_333).persons) == 1
    (track,) = rec.tracker.tracks
    f = frames[5]
    d, lab = f['depth'], f['labels']
    rr, cc = np.nonzero((lab > 0) & (d > 0))
    side = cc > np.median(cc)
    pts = pixel_points(rr[side], cc[side], d[rr[side], cc[side]], f['K']).astype(np.float32)
    t = rec._clock(5 * 33_333_333)
    fit, ids = rec._move_held_body(pts, track, t, rec.fitter)
    assert np.linalg.norm(fit.vertices - f['vertices'], axis=1).mean() < 0.05
    assert fit.median_residual < 0.03 and ids.shape == (len(pts),)
    front = facing_camera(track.fit.vertices, rec.faces, rec.config.fit.icp_front_cos)
    assert front is not None and front[ids].mean() > 0.9
    track.keep_fit(fit, t, 5 * 33_333_333, tracked=False)
    assert rec._move_held_body(pts, track, t, rec.fitter) is None
