"""The figure-producing commands run end to end and write the documented JSON keys."""
import json

import numpy as np
import pytest

from smpl_depth_ros.tools import benchmark, evaluate, synth_bag


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    path = str(tmp_path_factory.mktemp('bags') / 'tiny')
    assert synth_bag.main(['--out', path, '--frames', '3', '--seed', '11']) == 0
    return path


def test_evaluate_writes_table_ii_json(bag, tmp_path):
    out = tmp_path / 'eval.json'
    assert evaluate.main([bag, '--json', str(out), '--figures', str(tmp_path / 'fig'),
                          '--figure-frames', '0']) == 0
    res = json.loads(out.read_text())
    for key in ('pve_mm', 'pa_pve_mm', 'mpjpe_mm', 'miou', 'miou_net_res', 'miou_crop',
                'corr_err_cm_median',
                'net_ms_median', 'fit_ms_median', 'frames'):
        assert key in res, key
    assert res['frames'] == 3 and res['command'].startswith(f'evaluate {bag} --json')
    assert set(res['ablation']) == {'gt_joints+fit', 'single_unet+fit', 'double_unet+fit',
                                    'gt_corr+fit'}
    assert res['ablation']['gt_corr+fit']['pve_mm'] < 60
    for name, row in res['ablation'].items():  # the per-frame PVE behind each mean
        frames = row['pve_mm_frames']
        assert len(frames) == 3 - row['failures'] and frames[0][0] >= 0, name
        assert abs(np.mean([v for _, v in frames]) - row['pve_mm']) < 0.01, name
    assert 'pve_mm_frames' not in res  # the main row's are in its ablation entry
    # Per part: weighted by the parts' vertex counts, the part errors make the PVE.
    from smpl_depth_ros.body import load_body_model
    from smpl_depth_ros.body.parts import PART_NAMES
    counts = np.bincount(load_body_model('anny').part_labels.numpy(), minlength=15)[1:]
    for name, row in res['ablation'].items():
        parts = row['pve_mm_parts']
        assert list(parts) == list(PART_NAMES[1:]), name
        weighted = sum(c * parts[n] for c, n in zip(counts, PART_NAMES[1:])) / counts.sum()
        assert abs(weighted - row['pve_mm']) < 0.05, (name, weighted, row['pve_mm'])
    assert (tmp_path / 'fig' / 'fig3_0000.png').exists()


def test_evaluate_pipeline_parameters(bag, tmp_path, capsys):
    """-p NAME=VALUE reaches the pipeline (process_bag's names) and is recorded; a
    misspelt name is an error, not a silently ignored option."""
    out = tmp_path / 'eval.json'
    assert evaluate.main([bag, '--no-ablation', '--frames', '1', '--tracking',
                          '-p', 'tracking=false', '-p', 'fit.iterations=2',
                          '--json', str(out)]) == 0
    res = json.loads(out.read_text())
    assert res['params'] == {'tracking': False, 'fit.iterations': 2}
    assert res['tracking'] is False and res['frames'] == 1
    assert evaluate.main([bag, '-p', 'fit.iteratons=2']) == 2
    assert 'fit.iteratons' in capsys.readouterr().err


def test_benchmark_fit_writes_json(bag, tmp_path):
    out = tmp_path / 'fit.json'
    assert benchmark.main(['fit', bag, '--frames', '2', '--lbfgs-frames', '1',
                           '--json', str(out)]) == 0
    res = json.loads(out.read_text())
    for row in ('fast_cold', 'lbfgs_cold', 'init_only_cold', 'gt_joints_fast',
                'fast_cold_30pct_outliers'):
        for key in ('pve_mm', 'pa_pve_mm', 'mpjpe_mm', 'fit_ms_median', 'fit_ms_p95',
                    'frames'):
            assert key in res[row], (row, key)
    assert res['fast_cold']['pve_mm'] < 60
    assert res['command'] == f'benchmark fit {bag} --frames 2 --lbfgs-frames 1 --json {out}'


def test_benchmark_net_writes_json(tmp_path):
    out = tmp_path / 'net.json'
    assert benchmark.main(['net', '--repeats', '3', '--json', str(out)]) == 0
    res = json.loads(out.read_text())
    for kind in ('double', 'single', 'double_bfloat16', 'single_bfloat16'):
        for key in ('net_ms_median', 'net_ms_p95', 'net_tta_ms_median', 'net_tta_ms_p95',
                    'lookup_ms_median', 'params'):
            assert res[kind][key] > 0, (kind, key)
    assert isinstance(res['bfloat16_units'], bool)


def test_benchmark_empty_times_frames_with_nobody_in_them(tmp_path):
    """`benchmark empty`: sweep subjects blanked out, timed with and without the last
    look; the frames are rendered, so they have a room with blobs in it."""
    out = tmp_path / 'empty.json'
    assert benchmark.main(['empty', '--sensors', 'kinect_v1', '--frames', '2',
                           '--json', str(out)]) == 0
    res = json.loads(out.read_text())
    for key in ('second_network', 'without_second_network'):
        assert res[key]['frames'] == 2 and res[key]['frame_ms_median'] > 0
        assert 0 <= res[key]['persons_reported'] <= 2


def test_mocap_retargeting_recovers_a_known_pose_and_the_shipped_poses_load(tmp_path):
    """export_mocap_poses on a clip made from anny itself (a known pose's joints written
    into the mocap skeleton's slots): the retargeted pose is the one that made it; and the
    shipped poses (data/mocap_poses_anny.npz) load into PoseSampler(mode='mocap'), within
    the joint limits, mirrored at random."""
    import torch

    from smpl_depth_ros.body import load_body_model
    from smpl_depth_ros.synth.poses import PoseSampler
    from smpl_depth_ros.tools import export_mocap_poses as emp
    body = load_body_model('anny', dtype=torch.float64)
    sampler = PoseSampler(body, mode='broad')
    rng = np.random.default_rng(5)
    canon = np.stack([sampler.sample_canonical(rng) for _ in range(3)])
    p = body.zero_params(3)
    p['pose'] = torch.as_tensor(canon @ sampler.C, dtype=body.dtype)
    with torch.no_grad():
        joints = body(**p).joints.numpy() @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    clip = np.zeros((3, len(emp.MOCAP_JOINTS), 3), np.float32)  # z up, as the mocap
    names = list(body.joint_names)
    for ours, theirs in emp.JOINT_MAP.items():
        clip[:, emp.MOCAP_JOINTS.index(theirs)] = joints[:, names.index(ours)]
    folder = tmp_path / 'holosoma_retargeting' / 'demo_data' / 'climb' / 'mocap_climb_seq_0'
    folder.mkdir(parents=True)
    np.save(folder / 'mocap_climb_seq_0_joint_positions_f0-3.npy', clip)
    out = emp.retarget(emp.clip_files(str(tmp_path)), body, every=1, max_residual_m=0.05)
    assert out['poses'].shape == (3, len(names) - 1, 3) and (out['residual_m'] < 0.01).all()
    # Joint positions do not fix a bone's twist about its own axis: compare the bodies
    # (mean shape, no global rotation) the poses make, not their rotation vectors.
    def mesh(c):
        q = body.zero_params(len(c))
        q['pose'] = torch.as_tensor(np.asarray(c, np.float64) @ sampler.C, dtype=body.dtype)
        with torch.no_grad():
            return body(**q).vertices.numpy()
    # (Nor the pelvis' pitch: anny's spine1 joint sits at the pelvis, so hips and spine
    # can take it up. Each retargeted body is still nearest its own source's.)
    got, true = mesh(out['poses']), mesh(canon)
    pve = np.linalg.norm(got[:, None] - true[None], axis=-1).mean(-1)  # (retargeted, source)
    assert (pve.argmin(1) == np.arange(3)).all() and np.diag(pve).max() < 0.1, pve
    shipped = PoseSampler(body, mode='mocap')
    assert len(shipped.mocap) > 1000
    draws = np.stack([shipped.sample_canonical(rng) for _ in range(50)])
    lo, hi = shipped.limits[..., 0], shipped.limits[..., 1]
    assert ((draws >= lo - 1e-9) & (draws <= hi + 1e-9)).all()
    assert np.degrees(np.linalg.norm(draws, axis=-1)).mean() > 10  # not the rest pose


def test_box_lifting_clips_are_retargeted_with_the_body_tilt(tmp_path):
    """An OMOMO box-lifting clip (holosoma's .pt layout: a (frames, 591) tensor, the 52
    SMPL-H joints in columns 162-317, z up) made from anny bodies bent forward and leaning
    sideways: read with weights_only, retargeted, and the pose with its recovered whole-body
    tilt (pitch, roll) rebuilds each body; the shipped file holds both motions (the
    climbers upright), and the mocap sampler draws bent bodies from it."""
    import torch
    from scipy.spatial.transform import Rotation

    from smpl_depth_ros.body import load_body_model
    from smpl_depth_ros.synth.poses import PoseSampler, _rot
    from smpl_depth_ros.tools import export_mocap_poses as emp
    body = load_body_model('anny', dtype=torch.float64)
    sampler = PoseSampler(body, mode='templates')
    C = body.canonical_rotation.numpy()
    rng = np.random.default_rng(8)
    canon = np.stack([sampler.sample_canonical(rng) for _ in range(3)])
    tilts = np.array([[0.6, 0.0], [-0.3, 0.25], [0.0, -0.4]])  # (pitch, roll), radians

    def bodies(poses, tilt):  # canonical world (y up), no heading
        q = body.zero_params(len(poses))
        q['pose'] = torch.as_tensor(np.asarray(poses, np.float64) @ C)
        q['global_orient'] = torch.as_tensor(np.stack([Rotation.from_matrix(
            _rot(0, p) @ _rot(2, r) @ C).as_rotvec() for p, r in tilt]))
        with torch.no_grad():
            out = body(**q)
        return out.joints.numpy(), out.vertices.numpy()
    joints, true = bodies(canon, tilts)
    rows = np.zeros((3, 591), np.float32)
    slots = rows[:, emp.SMPLH_COLUMNS].reshape(3, 52, 3)
    names = list(body.joint_names)
    for ours, theirs in emp.SMPLH_MAP.items():
        slots[:, emp.SMPLH_JOINTS.index(theirs)] = joints[:, names.index(ours)] \
            @ emp.WORLD_FROM_CANONICAL.T
    rows[:, emp.SMPLH_COLUMNS] = slots.reshape(3, -1)
    folder = tmp_path / 'holosoma_retargeting' / 'demo_data' / 'OMOMO_new'
    folder.mkdir(parents=True)
    torch.save(torch.from_numpy(rows), folder / 'sub1_largebox_001.pt')
    files = emp.clip_files(str(tmp_path))
    assert [m for m, _ in files] == ['box lifting']
    out = emp.retarget(files, body, every=1, max_residual_m=0.05)
    assert out['poses'].shape == (3, len(names) - 1, 3) and (out['residual_m'] < 0.01).all()
    assert list(out['clip_motion']) == ['box lifting']
    _, got = bodies(out['poses'], out['root'])
    _, upright = bodies(out['poses'], np.zeros((3, 2)))
    pve = np.linalg.norm(got[:, None] - true[None], axis=-1).mean(-1)  # (retargeted, source)
    assert (pve.argmin(1) == np.arange(3)).all() and np.diag(pve).max() < 0.1, pve
    # without the tilt, the bent and leaning bodies are not rebuilt
    assert np.linalg.norm(upright - true, axis=-1).mean(-1)[:2].min() > 2 * np.diag(pve).max()
    shipped = PoseSampler(body, mode='mocap')
    assert sorted(shipped.motions) == ['box lifting', 'climbing']
    assert min(len(m) for m in shipped.motions.values()) > 100
    tilt = {k: np.abs(shipped.mocap_root[m]).max() for k, m in shipped.motions.items()}
    assert tilt['climbing'] == 0 and np.degrees(tilt['box lifting']) > 15
    drawn = {}
    for _ in range(60):
        root = shipped.sample_with_root(rng)[1]
        drawn.setdefault(shipped.last_motion, []).append(np.abs(root).max())
    assert sorted(drawn) == ['box lifting', 'climbing'] and max(drawn['climbing']) == 0
    assert np.degrees(max(drawn['box lifting'])) > 15  # bent over, as lifted
