"""Person tracks and stable IDs: the Tracker's association rules, and the Reconstructor on
synthetic multi-person sequences (make_multi_sequence) with ground-truth identities."""
import numpy as np
import pytest

from smpl_depth_ros.config import PipelineConfig
from smpl_depth_ros.evaluation import TrackScore
from smpl_depth_ros.pipeline import Reconstructor
from smpl_depth_ros.synth.camera import get_camera
from smpl_depth_ros.synth.dataset import make_multi_sequence
from smpl_depth_ros.synth.poses import PoseSampler
from smpl_depth_ros.tracking import Tracker


def _step(tracker, positions, t, masks=None):
    """One frame: match the positions, create tracks for new ones, record them seen.
    Returns the IDs in the order of `positions`."""
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    masks = masks or [None] * len(positions)
    tracker.expire(t)
    ids = []
    for p, tr, m in zip(positions, tracker.match(positions, masks, t), masks):
        tr = tr or tracker.new(p, t)
        Tracker.seen(tr, p, t, m)
        ids.append(tr.id)
    return ids


def test_two_people_crossing_keep_their_ids():
    """Two people walking towards each other at 1 m/s on lanes 0.3 m apart in depth:
    where they pass, each is nearer to the other's old position than a frame-to-frame
    nearest neighbour could tell; the predicted positions keep the IDs."""
    tr = Tracker(timeout_s=1.0, gate_m=0.5)
    first = None
    for f in range(90):
        t = f / 30
        a = [-1.5 + t, 0.0, 3.0]
        b = [1.5 - t, 0.0, 3.3]
        order = [a, b] if f % 2 else [b, a]  # candidates come in any order
        ids = _step(tr, order, t)
        ids = ids if f % 2 else ids[::-1]
        first = first or ids
        assert ids == first
    assert sorted(first) == [1, 2]


def test_an_occlusion_gap_keeps_the_id_a_long_absence_does_not():
    tr = Tracker(timeout_s=1.0, gate_m=0.5)
    for f in range(10):
        assert _step(tr, [[0.03 * f, 0.0, 2.0]], f / 30) == [1]
    # unseen for 0.6 s while walking on: the same person
    t = 9 / 30 + 0.6
    assert _step(tr, [[0.27 + 0.9 * 0.6, 0.0, 2.0]], t) == [1]
    # then gone for 2 s (> timeout): whoever appears there is new, and IDs are not reused
    assert _step(tr, [[0.8, 0.0, 2.0]], t + 2.0) == [2]
    tr.clear()
    assert _step(tr, [[0.8, 0.0, 2.0]], t + 2.1) == [3]


def test_time_running_backwards_drops_the_tracks():
    tr = Tracker()
    assert _step(tr, [[0.0, 0.0, 2.0]], 100.0) == [1]
    assert _step(tr, [[0.0, 0.0, 2.0]], 50.0) == [2]


def test_a_person_half_hidden_behind_another_keeps_its_own_track():
    """The blob of the person in front covers all the pixels the one behind had: by
    intersection over union it is still the front person's track."""
    H, W = 60, 80
    front, behind = np.zeros((H, W), bool), np.zeros((H, W), bool)
    front[10:60, 20:50] = True
    behind[15:45, 45:55] = True
    tr = Tracker()
    ids = _step(tr, [[0.0, 0.0, 2.0], [0.4, 0.0, 3.0]], 0.0, [front, behind])
    grown = np.zeros((H, W), bool)
    grown[10:60, 22:56] = True  # the front person moved over the other one's pixels
    matched = tr.match(np.array([[0.05, 0.0, 2.0]]), [grown], 1 / 30)
    assert matched[0].id == ids[0]


def test_a_person_far_from_every_track_is_new():
    tr = Tracker(gate_m=0.5)
    assert _step(tr, [[0.0, 0.0, 2.0]], 0.0) == [1]
    assert _step(tr, [[0.0, 0.0, 2.0], [1.5, 0.0, 3.0]], 1 / 30) == [1, 2]


@pytest.fixture(scope='module')
def rec3():
    return Reconstructor(PipelineConfig(device='cpu', max_persons=3))


def test_pipeline_tracks_two_people_with_stable_ids_and_joint_confidence(rec3):
    body = rec3.body
    frames = list(make_multi_sequence(body, PoseSampler(body), np.random.default_rng(5),
                                      get_camera('kinect_v1'), 10, 2))
    assert all(f['vertices'].shape == (2, body.num_vertices, 3) for f in frames)
    assert (frames[0]['visible'] > 2000).all()
    rec3.reset()
    score = TrackScore(min_visible=1500)
    for n, f in enumerate(frames):
        res = rec3.process(f['depth'], f['K'], stamp_ns=(1 + n) * 33_333_333)
        ids = [p.track_id for p in res.persons]
        assert len(set(ids)) == len(ids) and min(ids) >= 1
        for p in res.persons:
            assert p.joint_confidence.shape == (len(body.joint_names),)
            assert ((p.joint_confidence >= 0) & (p.joint_confidence <= 1)).all()
            assert p.joint_confidence[0] > 0.3  # the pelvis is always seen
        score.add(ids, np.array([p.joints[0] for p in res.persons]).reshape(-1, 3),
                  [p.vertices for p in res.persons], np.array([1, 2]),
                  f['joints'][:, 0], f['vertices'], f['visible'])
    s = score.summary()
    assert s['recall'] >= 0.9 and s['precision'] == 1.0, s
    assert s['id_switches'] == 0 and s['ids_used'] == 2, s
    assert s['pve_mm'] < 60, s


def test_joint_confidence_follows_support_and_residuals():
    from smpl_depth_ros.pipeline import joint_adjacency, joint_confidence
    parents = np.array([-1, 0, 1, 0])  # root, hip, knee; spine
    A = joint_adjacency(parents)
    assert A.tolist() == [[1, 1, 0, 1], [1, 1, 0, 0], [0, 1, 1, 0], [1, 0, 0, 1]]
    seg = np.array([0, 1, 2, 3])  # vertex i on segment i
    vids = np.array([1] * 60 + [2] * 3)  # many good points on the thigh, 3 on the shin
    res = np.r_[np.full(60, 0.01), np.full(3, 0.01)]
    c = joint_confidence(seg, vids, res, A)
    assert c[1] > 0.9 and c[0] > 0.9  # hip: thigh points; root: its child's
    assert c[2] > 0.9                   # knee: thigh and shin meet there
    assert c[3] == 0                    # spine: nothing seen
    far = joint_confidence(seg, vids, np.full(63, 0.2), A)
    assert far[1] < 0.01                # points the fit does not explain


def test_track_score_counts_misses_false_positives_and_switches():
    V = np.zeros((5, 3))
    sc = TrackScore(min_visible=100)
    g = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 3.0]])
    sc.add([7, 8], g, [V, V], [1, 2], g, [V, V], [500, 500])  # both found
    sc.add([8], g[:1], [V], [1, 2], g, [V, V], [500, 500])    # 1 switched to 8, 2 missed
    sc.add([9], [[5.0, 0, 5]], [V], [1, 2], g, [V, V], [500, 50])  # 1 missed, a FP;
    s = sc.summary()                                           # 2 need not be found
    assert (s['hits'], s['misses'], s['false_positives'], s['id_switches']) == (3, 2, 1, 1)
    assert s['persons_to_find'] == 5 and abs(s['mota'] - (1 - 4 / 5)) < 1e-9
    # Every person-frame's outcome: [frame, true id, pixels, outcome, predicted id, PVE].
    assert sc.records == [[0, 1, 500, 'hit', 7, 0.0], [0, 2, 500, 'hit', 8, 0.0],
                          [1, 1, 500, 'hit', 8, 0.0], [1, 2, 500, 'miss', -1, None],
                          [2, 1, 500, 'miss', -1, None], [2, 2, 50, 'optional', -1, None],
                          [2, -1, 0, 'false', 9, None]]
    assert sum(r[3] == 'hit' for r in sc.records) == s['hits']


def test_the_held_body_is_the_last_tracked_fit_while_recent():
    """Track.held_body: the last tracked fit (not a cold one, nor a body moved into
    place), at the mean of the shape samples, while at most max_age_s old."""
    from smpl_depth_ros.fit.fitter import FitResult
    from smpl_depth_ros.types import BodyParams

    def fit(x):
        p = BodyParams(pose=np.zeros((2, 3), np.float32), shape=np.full(3, x, np.float32),
                       global_orient=np.zeros(3, np.float32), transl=np.full(3, x, np.float32))
        return FitResult(params=p, vertices=None, joints=None, residuals=None,
                         data_term=0.0, energy=0.0, iterations=0, time_ms=0.0,
                         solver='fast', warm=False)
    tr = Tracker().new(np.zeros(3), 0.0)
    tr.keep_fit(fit(1.0), 0.0, None, tracked=False)
    assert tr.held_body(0.0, 0.5) is None  # a cold fit
    tr.keep_fit(fit(2.0), 0.1, None, tracked=True)
    tr.keep_fit(fit(3.0), 0.2, None, tracked=True, moved=True)
    params, t = tr.held_body(0.3, 0.5)
    assert t == 0.1 and params.transl[0] == 2.0
    tr.add_shape_sample(np.full(3, 5.0))
    assert tr.held_body(0.3, 0.5)[0].shape[0] == 5.0
    assert tr.held_body(0.7, 0.5) is None  # too old
    tr.keep_fit(fit(4.0), 0.8, None, tracked=False)
    assert tr.held_body(0.8, 0.5) is None
