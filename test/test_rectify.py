"""Lens distortion: the models, the maps between a lens's own image and a pinhole one, and
the pipeline on an Azure Kinect's own (distorted) depth images."""
import numpy as np
import pytest

from smpl_depth_ros.rectify import Lens, Rectifier, distort, named_rectified, undistort
from smpl_depth_ros.synth.sensors import LENSES

AZURE = LENSES['azure_kinect']
K_NFOV = np.array([[504.0, 0, 320.0], [0, 504.0, 288.0], [0, 0, 1]])


def test_models_against_their_formulas():
    x, y = np.array([0.5]), np.array([-0.25])
    r2 = 0.3125
    # plumb_bob: radial 1 + k1 r^2 + k2 r^4 + k3 r^6, tangential p1, p2 (OpenCV)
    k1, k2, p1, p2, k3 = 0.1, -0.02, 0.001, -0.002, 0.003
    xd, yd = distort(x, y, 'plumb_bob', [k1, k2, p1, p2, k3])
    rad = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    assert xd[0] == pytest.approx(0.5 * rad + 2 * p1 * 0.5 * -0.25 + p2 * (r2 + 2 * 0.25))
    assert yd[0] == pytest.approx(-0.25 * rad + p1 * (r2 + 2 * 0.0625) + 2 * p2 * 0.5 * -0.25)
    # rational_polynomial with k4..k6 = 0 is plumb_bob; with them, the radial term divides
    same = distort(x, y, 'rational_polynomial', [k1, k2, p1, p2, k3, 0, 0, 0])
    assert np.allclose(same, (xd, yd))
    xr, _ = distort(x, y, 'rational_polynomial', [k1, 0, 0, 0, 0, 0.2, 0, 0])
    assert xr[0] == pytest.approx(0.5 * (1 + k1 * r2) / (1 + 0.2 * r2))
    # equidistant: r_d = theta (1 + k1 theta^2 + ...), theta = atan(r)
    xe, ye = distort(x, y, 'equidistant', [0.05, 0, 0, 0])
    th = np.arctan(np.sqrt(r2))
    assert np.hypot(xe, ye)[0] == pytest.approx(th * (1 + 0.05 * th ** 2))
    assert ye[0] / xe[0] == pytest.approx(-0.5)
    # the published Azure Kinect lens: the image side (x = 0.63) 11 % nearer the centre
    xa, _ = distort(np.array([0.635]), np.array([0.0]), *AZURE)
    assert 0.87 < xa[0] / 0.635 < 0.90
    with pytest.raises(ValueError, match='not supported'):
        distort(x, y, 'kannala_brandt_9', [0.1])


@pytest.mark.parametrize('model,D', [AZURE, ('plumb_bob', (-0.3, 0.1, 0.001, 0.0005, -0.02)),
                                     ('equidistant', (-0.01, 0.02, -0.01, 0.002))])
def test_undistort_inverts_distort(model, D):
    g = np.linspace(-0.6, 0.6, 25)
    x, y = np.meshgrid(g, g)
    xu, yu, err = undistort(*distort(x, y, model, D), model, D)
    assert np.abs(xu - x).max() < 1e-9 and np.abs(yu - y).max() < 1e-9 and err.max() < 1e-9


def test_a_plane_seen_through_the_lens_is_flat_once_rectified():
    """A tilted plane 2-3 m away, ray-cast through every raw pixel of an Azure Kinect
    lens: back-projected with K alone its points bend off the plane by centimetres;
    rectified and back-projected with the pinhole image's K they lie on it within the
    pixel grid's rounding; labels go back onto the raw pixels they came from."""
    w, h = 640, 576
    rect = Rectifier.for_camera(K_NFOV, *AZURE, (w, h))
    assert rect.shape[0] > h and rect.shape[1] > w  # the whole raw image is kept
    assert (rect.back >= 0).all()
    n, c = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0]), 2.5
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y, _ = undistort((uu - 320.0) / 504.0, (vv - 288.0) / 504.0, *AZURE)
    raw = (c / (n[0] * x + n[1] * y + n[2])).astype(np.float32)  # depth Z of each ray

    def off_plane(depth, K):
        rr, cc = np.nonzero(depth > 0)
        z = depth[rr, cc]
        p = np.stack([(cc - K[0, 2]) * z / K[0, 0], (rr - K[1, 2]) * z / K[1, 1], z], 1)
        return np.abs(p @ n - c)
    assert np.percentile(off_plane(raw, K_NFOV), 90) > 0.05
    flat = rect.rectify(raw)
    assert (flat > 0).mean() > 0.7
    # nearest-neighbour resampling moves a point by at most half a pixel along the plane
    assert np.percentile(off_plane(flat, rect.K), 99) < 0.01
    labels = (np.arange(h * w) % 251 + 1).reshape(h, w).astype(np.uint8)
    assert np.array_equal(rect.to_raw(rect.rectify(labels)), labels)
    rows, cols = np.nonzero(flat > 0)
    r0, c0 = rect.raw_pixels(rows, cols)
    assert np.array_equal(raw[r0, c0], flat[rows, cols])


def test_lens_rules():
    assert Rectifier.for_camera(K_NFOV, 'plumb_bob', np.zeros(5), (640, 576)) is None
    with pytest.raises(ValueError, match='not supported'):
        Rectifier.for_camera(K_NFOV, 'fov', [0.9], (640, 576))
    assert not named_rectified('/k4a/depth/image_raw')
    assert named_rectified('/camera/depth/image_rect_raw')
    assert named_rectified('/camera/depth/image_rect/')
    raw, rect = Lens(*AZURE, K_NFOV, rectified=False), Lens(*AZURE, K_NFOV, rectified=True)
    assert raw.undo('auto') and not rect.undo('auto')
    assert rect.undo('always') and not raw.undo('never')
    assert not Lens('plumb_bob', np.zeros(5), K_NFOV).undo('always')


def test_azure_kinect_raw_depth_is_reconstructed_once_undistorted():
    """Frames of the Azure Kinect NFOV preset made the lens's own images (as its driver's
    depth/image_raw; the validation sweep's subjects at 2-3 m): taken as pinhole, every
    body comes out bent and shifted; undistorted (`undistort` 'auto', the default, for a
    topic not named rect) they are near the pinhole frames' accuracy, with the published
    mask on the raw image's body pixels."""
    from smpl_depth_ros.body import load_body_model
    from smpl_depth_ros.config import PipelineConfig
    from smpl_depth_ros.evaluation import pve
    from smpl_depth_ros.pipeline import Reconstructor
    from smpl_depth_ros.synth.poses import PoseSampler
    from smpl_depth_ros.synth.sensors import SENSORS
    from smpl_depth_ros.tools.sweep import sweep_frames
    body = load_body_model('anny')
    frames = list(sweep_frames(body, PoseSampler(body), SENSORS['azure_kinect_nfov'], 2.0,
                               3.0, 3, 202, lens='azure_kinect'))
    undone = Reconstructor(PipelineConfig(tracking=False, device='cpu', max_persons=1),
                           body=body)
    kept = Reconstructor(PipelineConfig(tracking=False, device='cpu', max_persons=1,
                                        undistort='never'), body=body)
    good, bad = [], []
    for fr in frames:
        assert fr['lens'].undo('auto') and fr['depth'].shape == (576, 640)
        res = undone.process(fr['depth'], fr['K'], lens=fr['lens'])
        p = res.persons[0]
        good.append(pve(p.vertices, fr['vertices']))
        bad.append(pve(kept.process(fr['depth'], fr['K'], lens=fr['lens']).persons[0]
                       .vertices, fr['vertices']))
        assert res.labels.shape == fr['depth'].shape and p.mask.shape == fr['depth'].shape
        truth = fr['labels'] > 0
        assert (p.mask & truth).sum() / (p.mask | truth).sum() > 0.7
        assert (fr['depth'][p.pixels[:, 0], p.pixels[:, 1]] > 0).all()
    assert all(g < b for g, b in zip(good, bad)), (good, bad)
    assert np.mean(good) < 0.025 and np.mean(bad) > 1.5 * np.mean(good), (good, bad)


def test_a_rectified_image_of_a_distorted_camera_is_seen_through_P():
    """A depth image whose camera_info has a non-zero D but whose topic's name says rect
    (image_proc's output) is not resampled: the pipeline takes P's intrinsics for it, as
    ROS consumers of rectified images do."""
    from smpl_depth_ros.config import PipelineConfig
    from smpl_depth_ros.pipeline import Reconstructor
    f = np.load('test/data/val_s2_frame63.npz')
    depth, K = f['depth_mm'] / 1000.0, f['K']
    rec = Reconstructor(PipelineConfig(tracking=False, device='cpu'))
    want = rec.process(depth, K).persons[0].vertices
    wrong_K = K * [[1.3], [1.3], [1.0]]  # the raw image's K: not the rectified one's
    lens = Lens('plumb_bob', np.array([-0.3, 0.1, 0.0, 0.0, 0.0]), K, rectified=True)
    det = rec.detect(depth, wrong_K, lens=lens)
    assert det.rectifier is None and np.array_equal(det.K, K)
    np.testing.assert_allclose(rec.reconstruct(det).persons[0].vertices, want, atol=1e-5)
