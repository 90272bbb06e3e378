"""Training samples for the correspondence network, rendered on the fly (no ROS).

Each sample: a random adult (shape, pose from synth.poses: the activity templates or the
broad pose mixture), placed 1-5 m from a random camera preset with any yaw and small
pitch/roll, a random background (floor, walls, clutter; optional), rendered by ray
casting directly into the network's S x S crop (the virtual camera of a jittered square
crop around the projected body, the same crop geometry net.preprocess uses at run time),
then a sensor noise model: by default the Kinect v1 model in crop pixels, or (with
`SampleConfig.sensors`) a random sensor preset of any class (structured light, stereo,
time of flight: synth.sensors) at a random strength and resolution, its pixel-sized
effects expressed in crop pixels. Targets: part labels (15 classes) and the normalised
canonical coordinates of each pixel's template vertex.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from smpl_depth_ros.body.parts import MIRROR, template_embedding
from smpl_depth_ros.net.preprocess import network_input, square_crop
from smpl_depth_ros.net.unet import INPUT_SIZE
from smpl_depth_ros.synth.camera import CAMERAS, Camera
from smpl_depth_ros.synth.noise import NoiseParams, apply_noise
from smpl_depth_ros.synth.poses import PoseSampler, placement, sample_shape
from smpl_depth_ros.synth.render import chair_under, render_body, sample_background
from smpl_depth_ros.synth.sensors import SENSORS, hair_vertices


@dataclass(frozen=True)
class SampleConfig:
    size: int = INPUT_SIZE
    noise: bool = True
    background: float = 0.85         # probability of background geometry
    depth_range: tuple[float, float] = (1.0, 5.0)
    crop_jitter: float = 0.08        # crop centre jitter (fraction of the side)
    crop_scale: tuple[float, float] = (0.95, 1.3)  # crop side / (1.15 x bbox side)
    truncate: float = 0.5            # probability of seeing the body as the sensor does:
                                     # the crop around its part inside the sensor image,
                                     # pixels outside that image empty (close range)
    head_turn_deg: float = 0.0       # PoseSampler's head turns (0: the templates' own)
    poses: str = 'templates'         # PoseSampler mode: 'templates' | 'broad'
    sensors: tuple[str, ...] = ()    # synth.sensors presets drawn per sample (uniformly
                                     # per class, then per preset); () = Kinect v1 noise
                                     # on every camera preset (the original protocol)
    strength: tuple[float, float] = (0.5, 2.0)  # noise strength, log-uniform
    rehearse: float = 0.0            # with `sensors`: probability that a sample comes from
                                     # the original protocol instead (template poses,
                                     # Kinect v1 noise on the camera presets), so a
                                     # fine-tune keeps what the shipped network learned
    resolution: tuple[float, float] = (0.5, 1.5)  # sensor image scale (640x480 preset:
                                     # 320x240 to 960x720), uniform
    chairs: float = 0.0              # probability that a sample is a person seated on a
                                     # chair (PoseSampler mode 'seated' and
                                     # synth.render.chair_under, in a room or alone)


def crop_noise_params(scale: float) -> NoiseParams:
    """Sensor noise expressed in crop pixels: pixel-sized effects shrink by `scale`
    (sensor pixels per crop pixel), so a crop sees what the sensor would have produced."""
    k = 1.0 / max(scale, 1.0)
    return NoiseParams(
        lateral_base_px=0.8 * k, lateral_angle_px=0.035 * k, lateral_max_px=max(3.0 * k, 1.0),
        lateral_band_px=int(round(2 * k)), edge_drop_prob=0.5 * k,
        edge_erode_px=int(2 * k), hole_radius_px=(1, max(1, int(round(3 * k)))),
        holes_per_frame=4.0 * k * k)


def training_crop(uv: np.ndarray, width: int, height: int, cfg: SampleConfig,
                  rng: np.random.Generator):
    """The square crop of a training sample around the body's projected vertices `uv`
    (V, 2) on a width x height sensor, jittered and scaled as cfg says.

    At run time a crop is cut around what the sensor sees of the body: at close range,
    only its part inside the image. With probability cfg.truncate (when the body leaves
    the image and a quarter of its box stays in it) the crop is built that way, and the
    caller empties the crop pixels outside the sensor image.

    Returns (Crop, truncated).
    """
    u0, v0 = uv.min(0)
    u1, v1 = uv.max(0)
    cu0, cv0 = max(u0, 0.0), max(v0, 0.0)
    cu1, cv1 = min(u1, width - 1.0), min(v1, height - 1.0)
    truncated = bool(rng.random() < cfg.truncate and (cu0, cv0, cu1, cv1) != (u0, v0, u1, v1)
                     and cu1 > cu0 and cv1 > cv0
                     and (cu1 - cu0) * (cv1 - cv0) >= 0.25 * (u1 - u0) * (v1 - v0))
    if truncated:
        u0, v0, u1, v1 = cu0, cv0, cu1, cv1
    side = max(u1 - u0, v1 - v0)
    s = rng.uniform(*cfg.crop_scale)
    jit = rng.uniform(-cfg.crop_jitter, cfg.crop_jitter, 2) * side
    cu, cv = (u0 + u1) / 2 + jit[0], (v0 + v1) / 2 + jit[1]
    half = side * s / 2
    return square_crop(cu - half, cv - half, cu + half, cv + half, size=cfg.size), truncated


class SampleMaker:
    """Makes (input, labels, coords, coord_mask) training tuples for one body model."""

    def __init__(self, body, cfg: SampleConfig = SampleConfig()):
        self.body = body
        self.cfg = cfg
        self.sampler = PoseSampler(body, head_turn_deg=cfg.head_turn_deg, mode=cfg.poses)
        self.faces = body.faces_numpy()
        self.parts = body.part_labels.cpu().numpy()
        emb = template_embedding(body.canonical_vertices(), self.parts)
        self.coords = emb[:, :3]
        self.cameras = [c for c in CAMERAS.values()]
        self.sensors = [SENSORS[n] for n in cfg.sensors]
        self.template_sampler = (PoseSampler(body, head_turn_deg=cfg.head_turn_deg)
                                 if cfg.rehearse > 0 else self.sampler)
        self.hair = hair_vertices(body) if self.sensors else None
        self.seated = PoseSampler(body, head_turn_deg=cfg.head_turn_deg, mode='seated') \
            if cfg.chairs > 0 else None

    def _sensor(self, rng):
        """A random sensor (a class uniformly, then one of its presets) at a random
        resolution, and a noise strength."""
        kinds = sorted({s.kind for s in self.sensors})
        k = kinds[rng.integers(len(kinds))]
        opts = [s for s in self.sensors if s.kind == k]
        sensor = opts[rng.integers(len(opts))]
        f = rng.uniform(*self.cfg.resolution)
        cam = sensor.camera
        cam = cam.scaled(max(16, round(cam.width * f)), max(16, round(cam.height * f)))
        lo, hi = np.log(self.cfg.strength[0]), np.log(self.cfg.strength[1])
        return sensor.with_camera(cam), float(np.exp(rng.uniform(lo, hi)))

    def __call__(self, rng: np.random.Generator):
        cfg, body = self.cfg, self.body
        sensor = strength = None
        original = not self.sensors or (cfg.rehearse > 0 and rng.random() < cfg.rehearse)
        if not original:
            sensor, strength = self._sensor(rng)
            cam: Camera = sensor.camera
            pose, root_tilt = self.sampler.sample_posed(rng)
            pose = pose[None]
        else:
            cam = self.cameras[rng.integers(len(self.cameras))]
            pose, root_tilt = self.template_sampler.sample(rng, 1), np.zeros(2)
        seated = cfg.chairs > 0 and rng.random() < cfg.chairs
        if seated:
            pose, root_tilt = self.seated.sample(rng, 1), np.zeros(2)
        shape = sample_shape(body, rng, 1)
        dlo, dhi = cfg.depth_range
        if sensor is not None:
            dlo = max(dlo, cam.min_range + 0.3)
            dhi = max(dlo + 0.1, min(dhi, cam.max_range - 0.3))
        z = rng.uniform(dlo, dhi)
        # Root inside the frustum (keep most of the body in view).
        x = rng.uniform(-0.35, 0.35) * z * cam.width / cam.fx
        y = rng.uniform(-0.2, 0.25) * z * cam.height / cam.fy
        yaw = rng.uniform(-np.pi, np.pi)
        pitch, roll = np.deg2rad(rng.uniform(-10, 10, 2)) + root_tilt
        go, tr = placement(body, shape[0], yaw, pitch, roll, np.array([x, y, z]))
        with torch.no_grad():
            out = body(torch.as_tensor(pose, dtype=body.dtype),
                       torch.as_tensor(shape, dtype=body.dtype),
                       torch.as_tensor(go, dtype=body.dtype)[None],
                       torch.as_tensor(tr, dtype=body.dtype)[None])
        V = out.vertices[0].cpu().numpy().astype(np.float64)
        uv = V[:, :2] / V[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
        crop, truncated = training_crop(uv, cam.width, cam.height, cfg, rng)
        Kc = crop.crop_K(cam.K)
        ccam = Camera(width=cfg.size, height=cfg.size, fx=Kc[0, 0], fy=Kc[1, 1],
                      cx=Kc[0, 2], cy=Kc[1, 2], name=cam.name + '_crop',
                      min_range=cam.min_range, max_range=cam.max_range)
        bg = None
        if rng.random() < cfg.background:
            bg = sample_background(rng, cam, out.joints[0, 0].cpu().numpy(), V)
        if seated:
            chair = chair_under(V, self.parts, np.array([0.0, -1.0, 0.0]), rng)
            if chair is not None:
                bg = chair if bg is None else bg + chair
        r = render_body(V, self.faces, self.parts, ccam, bg)
        depth, labels, vids = r.depth, r.labels, r.vertex_ids
        if cfg.noise and sensor is not None:
            dark = (vids >= 0) & self.hair[np.maximum(vids, 0)] if sensor.kind == 'tof' \
                else None
            nr = sensor.apply(depth, r.normals_cos, rng, strength, fx=Kc[0, 0],
                              pixel_size=crop.scale, dark=dark)
            depth = nr.depth
            labels = nr.take(labels, 0)
            vids = nr.take(vids, -1)
        elif cfg.noise:
            nr = apply_noise(depth, r.normals_cos, rng, crop_noise_params(crop.scale), fx=None)
            depth = nr.depth
            labels = nr.take(labels, 0)
            vids = nr.take(vids, -1)
        if truncated:
            outside = ~crop.sample_indices((cam.height, cam.width))[2]
            depth = np.where(outside, 0.0, depth).astype(depth.dtype)
            labels = np.where(outside, 0, labels).astype(labels.dtype)
            vids = np.where(outside, -1, vids).astype(vids.dtype)
        body_px = (labels > 0) & (depth > 0)
        med = float(np.median(depth[body_px])) if body_px.any() else z
        med += rng.normal(0, 0.03)  # the run-time median comes from a blob, not labels
        xin = network_input(depth, med)
        labels = np.where(xin[1] > 0, labels, 0).astype(np.int64)
        cm = (vids >= 0) & (labels > 0)
        coords = np.zeros((3, cfg.size, cfg.size), np.float32)
        coords[:, cm] = self.coords[vids[cm]].T
        if rng.random() < 0.5:  # mirror augmentation: flip image, swap left/right parts
            xin, labels, coords, cm = self._mirror(xin, labels, coords, cm)
        return xin, labels, coords, cm

    def _mirror(self, xin, labels, coords, cm):
        # A mirrored person is a (different) valid person seen mirrored: swap sides and
        # mirror the canonical x coordinate (the template is left/right symmetric).
        xin = xin[:, :, ::-1].copy()
        labels = MIRROR[labels[:, ::-1]]
        coords = coords[:, :, ::-1].copy()
        coords[0] = np.where(cm[:, ::-1], 1.0 - coords[0], 0.0)
        return xin, labels, coords, cm[:, ::-1].copy()


class SyntheticDataset(torch.utils.data.IterableDataset):
    """Endless stream of samples; each worker has its own seeded generator."""

    def __init__(self, body_factory, seed: int, cfg: SampleConfig = SampleConfig(),
                 length: int | None = None):
        self.body_factory = body_factory
        self.seed = seed
        self.cfg = cfg
        self.length = length

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        wid = info.id if info else 0
        torch.set_num_threads(1)
        maker = SampleMaker(self.body_factory(), self.cfg)
        rng = np.random.default_rng([self.seed, wid])
        n = 0
        while self.length is None or n < self.length:
            xin, labels, coords, cm = maker(rng)
            yield (torch.from_numpy(xin), torch.from_numpy(labels), torch.from_numpy(coords),
                   torch.from_numpy(cm))
            n += 1


def make_fixed_set(body, n: int, seed: int, cfg: SampleConfig = SampleConfig()):
    """A fixed validation set: stacked tensors (x, labels, coords, mask)."""
    maker = SampleMaker(body, cfg)
    rng = np.random.default_rng(seed)
    items = [maker(rng) for _ in range(n)]
    return tuple(torch.from_numpy(np.stack(t)) for t in zip(*items))
