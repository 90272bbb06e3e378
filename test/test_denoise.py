"""The noise-adaptive, edge-preserving depth smoothing (denoise) on frames with the
sensor noise models' per-pixel and correlated noise."""
from dataclasses import replace

import numpy as np
import pytest

from smpl_depth_ros import sensor_noise as sn
from smpl_depth_ros.denoise import MAX_RADIUS, SMOOTH_FROM, radius_map, smooth
from smpl_depth_ros.synth.sensors import SENSORS


def _step_scene(z_near, z_far, shape=(240, 320), seed=0, sigma=None):
    """A box at z_near in front of a wall at z_far (both fronto-parallel), each pixel
    with independent Gaussian noise of the D435 preset's sigma at its depth (or
    `sigma(z)`), some pixels invalid."""
    rng = np.random.default_rng(seed)
    clean = np.full(shape, z_far, np.float32)
    clean[60:180, 100:220] = z_near
    nm = sigma or sn.preset_noise('realsense_d435')
    d = (clean + rng.normal(0.0, 1.0, shape) * nm(clean)).astype(np.float32)
    d[rng.random(shape) < 0.05] = 0.0
    return d, clean


def test_per_pixel_noise_is_averaged_and_depth_edges_are_kept():
    """A D435 at 3.5 m (sigma 4.6 cm, 2.1x a Kinect v1's): the noise on each surface
    falls to what the thresholds were tuned for, every pixel stays on its own side of a
    0.6 m depth edge, and the invalid pixels stay invalid."""
    nm = sn.preset_noise('realsense_d435')
    d, clean = _step_scene(3.5, 4.1)
    out = smooth(d, nm)
    valid = d > 0
    assert ((out > 0) == valid).all()
    inner = np.zeros_like(valid)
    inner[64:176, 104:216] = True  # the box, away from its edge
    wall = valid & (np.abs(clean - 4.1) < 1e-6)
    wall[50:190, 90:230] = False
    for m, z in ((inner & valid, 3.5), (wall, 4.1)):
        raw, smoothed = (d - clean)[m].std(), (out - clean)[m].std()
        assert smoothed < 0.6 * raw, (z, raw, smoothed)
        assert smoothed < sn.EXCESS_OVER * sn.kinect_v1_sigma(z) * 1.2, (z, smoothed)
    # the box's rim: averaged with its own side only, nearer its true depth than before;
    # far fewer pixels than before a quarter of the step off
    edge = valid & ~inner & (clean < 4.0)
    assert np.abs(out - clean)[edge].mean() < 0.7 * np.abs(d - clean)[edge].mean()
    assert (np.abs(out - clean)[valid] > 0.15).sum() < 0.5 * (np.abs(d - clean)[valid] > 0.15).sum()


def test_quiet_sensors_are_left_as_they_are():
    """A Kinect v1 or time-of-flight camera has no excess noise: the very array comes
    back; so it does without a noise model (sensor 'none', nothing measured yet)."""
    d, _ = _step_scene(2.5, 3.5, sigma=sn.preset_noise('kinect_v1'))
    for name in ('kinect_v1', 'azure_kinect_nfov', 'kinect_v2'):
        assert smooth(d, sn.preset_noise(name)) is d, name
        assert not radius_map(d, sn.preset_noise(name)).any(), name
    assert smooth(d, None) is d and smooth(d, sn.NoiseModel()) is d
    # a noise estimate a little above the defaults' (the scatter of a Kinect's own
    # estimate) is left alone too; from SMOOTH_FROM times it on, the pixels are smoothed
    k1 = sn.preset_noise('kinect_v1')
    for gain, smoothed in ((1.2, False), (SMOOTH_FROM + 0.05, True)):
        nm = replace(k1, sigma=tuple(gain * sn.EXCESS_OVER * s for s in k1.sigma))
        assert (smooth(d, nm) is not d) == smoothed, gain


def test_the_window_grows_with_the_excess_noise():
    """The radius follows sigma / (EXCESS_OVER x Kinect v1's sigma): none nearby, wider
    with depth and with a noisier unit of the same camera, never above 3."""
    nm = sn.preset_noise('realsense_d435')
    noisier = replace(nm, sigma=tuple(3 * s for s in nm.sigma))
    z = np.array([[1.0, 2.0, 3.0, 4.0, 6.0, 0.0]], np.float32)
    r, r3 = radius_map(z, nm)[0], radius_map(z, noisier)[0]
    assert r[-1] == 0 and r3[-1] == 0  # invalid
    assert (np.diff(r3[:5]) >= 0).all() and (r3 >= r).all() and r3.max() == MAX_RADIUS
    assert r3[3] > r[3] >= 1 and r[0] <= 1


def test_stereo_noise_of_the_model_is_reduced_on_a_plane():
    """The D435 noise model's own frames (correlated over the matching window, a quarter
    of the variance per pixel), at twice its strength, 3.5 m: the scatter about the
    plane falls."""
    s = SENSORS['realsense_d435']
    H, W = s.camera.height, s.camera.width
    clean = np.full((H, W), 3.5, np.float32)
    r = s.apply(clean, np.ones_like(clean), np.random.default_rng(3), strength=2.0)
    nm = replace(sn.preset_noise('realsense_d435', s.camera.K),
                 sigma=tuple(2 * v for v in sn.preset_noise('realsense_d435',
                                                             s.camera.K).sigma))
    out = smooth(r.depth, nm)
    v = r.depth > 0
    assert (out - clean)[v].std() < 0.85 * (r.depth - clean)[v].std()


def test_a_stereo_person_through_noisier_disparity_is_reconstructed():
    """test/data/stereo_d435_noisy.npz: a D435 person at 3.0-3.5 m through per-pixel
    disparity noise of 0.15 px (about twice the preset's). With the default smoothing
    the body is found near the truth; without it no fit explains the candidates."""
    from smpl_depth_ros.config import PipelineConfig
    from smpl_depth_ros.pipeline import Reconstructor
    from smpl_depth_ros.types import InputError
    f = np.load('test/data/stereo_d435_noisy.npz')
    depth = f['depth_mm'] / 1000.0
    rec = Reconstructor(PipelineConfig(tracking=False, device='cpu'))
    persons = rec.process(depth, f['K']).persons
    assert len(persons) == 1 and rec.noise.kind == 'stereo'
    err = np.linalg.norm(persons[0].vertices - f['vertices'], axis=1).mean()
    assert err < 0.06, err
    raw = Reconstructor(PipelineConfig(tracking=False, device='cpu', denoise=False),
                        body=rec.body)
    with pytest.raises(InputError):
        raw.process(depth, f['K'])
