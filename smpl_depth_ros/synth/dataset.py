"""Synthetic depth frames and sequences with exact ground truth (no ROS).

A frame is a posed body (synth.poses) placed 1-5 m in front of a camera, optionally in
a random room (synth.render.sample_background), ray-cast (synth.render) and optionally
corrupted by a sensor noise model (`SynthParams.sensor`: a `synth.sensors` preset; by
default the Kinect v1 structured-light model of synth.noise). Ground truth: per-pixel part labels
and template vertex ids (following the noisy depth: 0 / -1 where it is invalid), the
posed mesh and joints in the camera optical frame, and the body parameters.

Everything is a deterministic function of the `numpy.random.Generator` passed in. The
scene and the noise draw from their own sub-streams, so turning the background or the
noise off leaves the person unchanged for the same seed.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from smpl_depth_ros.body.base import BodyModel
from smpl_depth_ros.synth import noise as noise_mod
from smpl_depth_ros.synth import render as render_mod
from smpl_depth_ros.synth.camera import Camera
from smpl_depth_ros.synth.poses import (OPTICAL_FROM_CANONICAL, PoseSampler, placement,
                                        sample_shape)


@dataclass(frozen=True)
class SynthParams:
    """Scene sampling parameters.

    Attributes:
        depth_range: (min, max) root depth in metres (also kept 0.3 m inside the
            camera's range).
        tilt_deg: pitch and roll are uniform in +-tilt_deg (a tilted camera).
        camera_height: (min, max) camera height above the floor in metres, used to place
            the person vertically when that keeps the body in view.
        seq_key_every: frames between root / yaw keyframes in sequences.
        seq_step_m: largest root move between two sequence keyframes (metres).
        seq_yaw_step_deg: largest yaw change between two sequence keyframes.
        pose_key_every: frames between pose keyframes in sequences.
        noise: structured-light noise parameters (used when `sensor` is None).
        sensor: a `synth.sensors.Sensor` whose noise model replaces `noise` (any class:
            structured light, stereo, time of flight), at `strength` (1 = nominal).
        background: scene layout parameters.
        chairs: with a background, a seated body gets a chair under it
            (`synth.render.chair_under`; pose mode 'seated').
    """

    depth_range: tuple[float, float] = (1.0, 5.0)
    tilt_deg: float = 10.0
    camera_height: tuple[float, float] = (0.4, 2.2)
    seq_key_every: int = 45
    seq_step_m: float = 1.0
    seq_yaw_step_deg: float = 60.0
    pose_key_every: int = 15
    noise: noise_mod.NoiseParams = field(default_factory=noise_mod.NoiseParams)
    sensor: object = None
    strength: float = 1.0
    background: render_mod.BackgroundParams = field(
        default_factory=render_mod.BackgroundParams)
    chairs: bool = False


def root_depth_range(camera: Camera, p: SynthParams) -> tuple[float, float]:
    lo = max(p.depth_range[0], camera.min_range + 0.3)
    hi = min(p.depth_range[1], camera.max_range - 0.3)
    if hi < lo:
        raise ValueError(f'depth range {p.depth_range} does not fit camera range '
                         f'[{camera.min_range}, {camera.max_range}]')
    return lo, hi


def _forward(body: BodyModel, pose, shape, go, transl) -> tuple[np.ndarray, np.ndarray]:
    kw = dict(dtype=body.dtype, device=body.device)
    with torch.no_grad():
        out = body(torch.as_tensor(pose, **kw)[None], torch.as_tensor(shape, **kw)[None],
                   torch.as_tensor(go, **kw)[None], torch.as_tensor(transl, **kw)[None])
    return (out.vertices[0].cpu().numpy().astype(np.float64),
            out.joints[0].cpu().numpy().astype(np.float64))


def _up_axis(body: BodyModel, global_orient: np.ndarray) -> np.ndarray:
    """The body's canonical up axis in the camera frame."""
    C = body.canonical_rotation.cpu().numpy().astype(np.float64)
    R = Rotation.from_rotvec(np.asarray(global_orient, np.float64)).as_matrix()
    return R @ C.T @ np.array([0.0, 1.0, 0.0])


def _view_interval(camera: Camera, verts: np.ndarray, axis: int) -> tuple[float, float]:
    """Offsets along x (axis 0) or y (axis 1) that keep every vertex inside the image."""
    f, c, n = ((camera.fx, camera.cx, camera.width) if axis == 0
               else (camera.fy, camera.cy, camera.height))
    z = np.maximum(verts[:, 2], 1e-3)
    lo = (-0.5 - c) * z / f - verts[:, axis]
    hi = (n - 0.5 - c) * z / f - verts[:, axis]
    return float(lo.max()), float(hi.min())


def _pick(rng, lo: float, hi: float, pref: tuple[float, float] | None = None) -> float:
    """Uniform in [lo, hi] (intersected with pref when they overlap); the midpoint when
    the interval is empty (the body does not fit: centre it)."""
    r = rng.random()  # always drawn: the stream does not depend on the branch
    if hi < lo:
        mid = 0.5 * (lo + hi)
        return float(np.clip(mid, *pref)) if pref is not None else mid
    if pref is not None:
        a, b = max(lo, pref[0]), min(hi, pref[1])
        if a <= b:
            return a + r * (b - a)
        return hi if pref[0] > hi else lo  # the view end nearest to the preference
    return lo + r * (hi - lo)


def _height_interval(verts: np.ndarray, up: np.ndarray, x: float,
                     heights: tuple[float, float]) -> tuple[float, float]:
    """y offsets giving a camera height (above the lowest vertex along up) in `heights`."""
    m = float((verts @ up).min())
    # h = -(m + x up_x + y up_y) ; up_y < 0 for an upright-ish person
    uy = up[1] if abs(up[1]) > 1e-6 else -1e-6
    a = (-heights[0] - m - x * up[0]) / uy
    b = (-heights[1] - m - x * up[0]) / uy
    return min(a, b), max(a, b)


def _render(camera: Camera, verts, faces, parts, scene: render_mod.Background | None,
            noise: bool, p: SynthParams, noise_rng: np.random.Generator, hair=None):
    """Ray-cast the mesh(es), clip to the camera's range and apply the sensor noise model:
    (depth, depth_clean, labels, vertex_ids). `hair`: optional (V,) bool of the vertices
    a time-of-flight sensor sees as dark."""
    r = render_mod.render_body(verts, faces, parts, camera, scene)
    inrange = (r.depth >= camera.min_range) & (r.depth <= camera.max_range)
    clean = np.where(inrange, r.depth, 0).astype(np.float32)
    labels = np.where(inrange, r.labels, 0).astype(np.uint8)
    vids = np.where(inrange, r.vertex_ids, -1).astype(np.int32)
    if not noise:
        return clean, clean, labels, vids
    if p.sensor is not None:
        dark = None
        if p.sensor.kind == 'tof' and hair is not None:
            dark = (vids >= 0) & hair[np.maximum(vids, 0)]
        nr = p.sensor.apply(clean, r.normals_cos, noise_rng, p.strength, fx=camera.fx,
                            dark=dark)
    else:
        nr = noise_mod.apply_noise(clean, r.normals_cos, noise_rng, p.noise, fx=camera.fx)
    ok = (nr.depth >= camera.min_range) & (nr.depth <= camera.max_range)
    depth = np.where(ok, nr.depth, 0).astype(np.float32)
    labels = np.where(ok, nr.take(labels, 0), 0).astype(np.uint8)
    vids = np.where(ok, nr.take(vids, -1), -1).astype(np.int32)
    return depth, clean, labels, vids


def _finish(body: BodyModel, camera: Camera, verts, joints, pose, shape, go, transl,
            scene: render_mod.Background | None, noise: bool, p: SynthParams,
            noise_rng: np.random.Generator) -> dict:
    hair = None
    if noise and p.sensor is not None and p.sensor.kind == 'tof':
        from smpl_depth_ros.synth.sensors import hair_vertices
        hair = hair_vertices(body)
    depth, clean, labels, vids = _render(camera, verts, body.faces_numpy(),
                                         body.part_labels.cpu().numpy(), scene, noise, p,
                                         noise_rng, hair)
    return dict(depth=depth, depth_clean=clean, labels=labels, vertex_ids=vids,
                vertices=verts.astype(np.float32), joints=joints.astype(np.float32),
                pose=np.asarray(pose, np.float32), shape=np.asarray(shape, np.float32),
                global_orient=np.asarray(go, np.float32),
                transl=np.asarray(transl, np.float32), K=camera.K)


def make_frame(body: BodyModel, sampler: PoseSampler, rng: np.random.Generator,
               camera: Camera, noise: bool = True, background: bool = True,
               params: SynthParams | None = None) -> dict:
    """One independent synthetic frame.

    The root depth is uniform in the depth range, yaw uniform in [-pi, pi), pitch/roll
    within +-tilt_deg; x and y are drawn where the whole body stays in the image (centred
    when it cannot), preferring a plausible camera height above the feet.

    Args:
        body: body model.
        sampler: pose sampler for that body.
        rng: random generator.
        camera: intrinsics, image size and valid range.
        noise: apply the sensor noise model.
        background: add a random floor / walls / boxes.
        params: sampling parameters (default SynthParams()).

    Returns:
        dict with depth (H, W) float32 metres (0 invalid), depth_clean (H, W) float32
        (noise-free, range-clipped), labels (H, W) uint8, vertex_ids (H, W) int32 (-1
        empty), vertices (V, 3) float32 and joints (J, 3) float32 (camera optical frame,
        metres), pose (P, 3), shape (S,), global_orient (3,), transl (3,) float32 and
        K (3, 3) float64.
    """
    p = params or SynthParams()
    scene_seed, noise_seed = rng.integers(0, 2**63 - 1, 2)
    shape = sample_shape(body, rng)[0]
    pose, root_tilt = sampler.sample_posed(rng)
    yaw = rng.uniform(-np.pi, np.pi)
    pitch, roll = np.deg2rad(rng.uniform(-p.tilt_deg, p.tilt_deg, 2))
    z = rng.uniform(*root_depth_range(camera, p))
    go, transl = placement(body, shape, yaw, pitch + root_tilt[0], roll + root_tilt[1],
                           np.array([0.0, 0.0, z]))
    verts, joints = _forward(body, pose, shape, go, transl)
    # the room's up: the camera tilt's, not a lying body's
    up = _up_axis(body, go if not root_tilt.any() else
                  placement(body, shape, yaw, pitch, roll, np.zeros(3))[0])
    x = _pick(rng, *_view_interval(camera, verts, 0))
    y = _pick(rng, *_view_interval(camera, verts, 1),
              pref=_height_interval(verts, up, x, p.camera_height))
    shift = np.array([x, y, 0.0])
    verts, joints, transl = verts + shift, joints + shift, transl + shift
    scene = None
    if background:
        scene = render_mod.sample_background(np.random.default_rng(scene_seed), camera,
                                             joints[0], verts, up, p.background)
        if p.chairs:
            chair = render_mod.chair_under(verts, body.part_labels.cpu().numpy(), up,
                                           np.random.default_rng([scene_seed, 1]))
            scene = scene if chair is None else scene + chair
    return _finish(body, camera, verts, joints, pose, shape, go, transl, scene, noise, p,
                   np.random.default_rng(noise_seed))


def _ease(keys: np.ndarray, frames: int, every: int) -> np.ndarray:
    """Cosine interpolation between keyframes placed every `every` frames."""
    out = []
    for f in range(frames):
        k, r = divmod(f, every)
        s = 0.5 - 0.5 * np.cos(np.pi * r / every)
        out.append((1 - s) * keys[k] + s * keys[k + 1])
    return np.asarray(out)


def make_sequence(body: BodyModel, sampler: PoseSampler, rng: np.random.Generator,
                  camera: Camera, frames: int, noise: bool = True, background: bool = True,
                  params: SynthParams | None = None) -> Iterator[dict]:
    """A smooth sequence: one person, one static camera and room, `frames` frames.

    Poses follow `PoseSampler.sequence`; the root glides between random ground positions
    and yaws (keyframes every `seq_key_every` frames, cosine-eased) with the lowest
    vertex kept on the floor; camera tilt and body shape are fixed.

    Args:
        body, sampler, rng, camera, noise, background, params: as for `make_frame`.
        frames: number of frames.

    Yields:
        Frame dicts as returned by `make_frame`, lazily (one render per `next`).
    """
    p = params or SynthParams()
    scene_seed, noise_seed = rng.integers(0, 2**63 - 1, 2)
    noise_rng = np.random.default_rng(noise_seed)
    shape = sample_shape(body, rng)[0]
    poses = sampler.sequence(rng, frames, p.pose_key_every)
    pitch, roll = np.deg2rad(rng.uniform(-p.tilt_deg, p.tilt_deg, 2))
    zlo, zhi = root_depth_range(camera, p)
    nk = frames // p.seq_key_every + 2
    keys = np.zeros((nk, 3))  # x, z, yaw
    for k in range(nk):
        if k == 0:
            z, yaw = rng.uniform(zlo, zhi), rng.uniform(-np.pi, np.pi)
        else:
            z = float(np.clip(keys[k - 1, 1] + rng.uniform(-1, 1) * p.seq_step_m, zlo, zhi))
            yaw = keys[k - 1, 2] + np.deg2rad(rng.uniform(-1, 1) * p.seq_yaw_step_deg)
        half = 0.35  # keep roughly a body half-width inside the image
        lo = -(camera.cx + 0.5) * z / camera.fx + half
        hi = (camera.width - 0.5 - camera.cx) * z / camera.fx - half
        x = _pick(rng, lo, hi)
        if k > 0:  # limit the step
            x = float(np.clip(x, keys[k - 1, 0] - p.seq_step_m, keys[k - 1, 0] + p.seq_step_m))
        keys[k] = (x, z, yaw)
    track = _ease(keys, frames, p.seq_key_every)

    C = body.canonical_rotation.cpu().numpy().astype(np.float64)
    tilt = Rotation.from_euler('xz', [pitch, roll]).as_matrix()  # about canonical x, z
    up = OPTICAL_FROM_CANONICAL @ tilt @ np.array([0.0, 1.0, 0.0])
    _, t0 = placement(body, shape, 0.0, 0.0, 0.0, np.zeros(3))  # transl = root - h0
    floor = None
    scene = None
    for f in range(frames):
        x, z, yaw = track[f]
        R = OPTICAL_FROM_CANONICAL @ tilt @ Rotation.from_euler('y', yaw).as_matrix() @ C
        go = Rotation.from_matrix(R).as_rotvec()
        rel, jrel = _forward(body, poses[f], shape, go, t0)  # root at the origin
        m = float((rel @ up).min())
        if floor is None:  # first frame: the camera height that keeps the body in view
            y0 = _pick(rng, *_view_interval(camera, rel + [x, 0.0, z], 1),
                       pref=_height_interval(rel + [x, 0.0, z], up, 0.0, p.camera_height))
            floor = float(((rel + [x, y0, z]) @ up).min())
        y = (floor - m - x * up[0] - z * up[2]) / up[1]
        root = np.array([x, y, z])
        verts, joints, transl = rel + root, jrel + root, t0 + root
        if background and scene is None:
            track_xyz = np.stack([track[:, 0], np.full(frames, y), track[:, 1]], 1)
            scene = render_mod.sample_background(np.random.default_rng(scene_seed), camera,
                                                 root, verts, up, p.background,
                                                 avoid=track_xyz)
        yield _finish(body, camera, verts, joints, poses[f], shape, go, transl, scene,
                      noise, p, noise_rng)


def make_multi_sequence(body: BodyModel, sampler: PoseSampler, rng: np.random.Generator,
                        camera: Camera, frames: int, persons: int, noise: bool = True,
                        background: bool = True, params: SynthParams | None = None,
                        rate: float = 30.0) -> Iterator[dict]:
    """Several people walking across one static camera's view, `frames` frames.

    Each person keeps to a lane at its own depth (lanes at least 0.6 m apart, from where
    whole bodies fit in the view to 4.5 m, so nobody walks through anybody), walks along
    it at 0.3-0.9 m/s facing roughly where it goes, and moves its limbs as
    `PoseSampler.sequence`; neighbouring lanes run in opposite directions, so people cross
    in front of each other (occlusions), and start or end outside the view (people
    entering and leaving). One floor under everybody, the camera 0.85-1.05 m above it;
    camera tilt and shapes are fixed per sequence. With frames=1 this is one scene.

    Args:
        body, sampler, rng, camera, noise, background, params: as for `make_sequence`.
        frames: number of frames; persons: number of people (>= 1).
        rate: frames per second (the walking speed's clock).

    Yields:
        Frame dicts with depth, depth_clean, labels, vertex_ids (the person's own vertex),
        K as `make_frame`, and per person (N = persons, in a fixed order; person k has the
        ground-truth ID k + 1): vertices (N, V, 3), joints (N, J, 3), pose (N, P, 3),
        shape (N, S), global_orient (N, 3), transl (N, 3), person_index (H, W) int8 (the
        person seen at each valid pixel, -1 none) and visible (N,) int32 pixel counts.
    """
    p = params or SynthParams()
    if persons < 1:
        raise ValueError('persons must be >= 1')
    scene_seed, noise_seed = rng.integers(0, 2**63 - 1, 2)
    noise_rng = np.random.default_rng(noise_seed)
    zlo, zhi = root_depth_range(camera, p)
    # Nearest lane: where the view holds 1.05 m above and below the camera (whole bodies
    # in view for a camera at about hip height).
    near = 1.05 * camera.fy / max(min(camera.cy, camera.height - camera.cy), 1.0)
    zlo = max(zlo, near)
    zhi = max(zlo + 0.6 * (persons - 1), min(zhi, 4.5))
    lanes = np.linspace(zlo, zhi, persons) if persons > 1 else np.array([(zlo + zhi) / 2])
    gap = (zhi - zlo) / max(persons - 1, 1)
    lanes = lanes + rng.uniform(-0.2, 0.2, persons) * min(gap - 0.6, 0.5) if persons > 1 \
        else lanes
    lanes = rng.permutation(lanes)
    pitch, roll = np.deg2rad(rng.uniform(-p.tilt_deg, p.tilt_deg, 2) * 0.5)
    tilt = Rotation.from_euler('xz', [pitch, roll]).as_matrix()
    up = OPTICAL_FROM_CANONICAL @ tilt @ np.array([0.0, 1.0, 0.0])
    height = rng.uniform(0.85, 1.05)
    C = body.canonical_rotation.cpu().numpy().astype(np.float64)
    t = np.arange(frames) / rate
    sign = 1.0 if rng.random() < 0.5 else -1.0
    people = []
    for k in range(persons):
        shape = sample_shape(body, rng)[0]
        poses = sampler.sequence(rng, frames, p.pose_key_every)
        z = float(lanes[k])
        half = (camera.width / 2) / camera.fx * z  # half the view's width at the lane
        direction = sign * (1.0 if k % 2 == 0 else -1.0)  # neighbouring lanes cross
        speed = rng.uniform(0.3, 0.9)
        x0 = -direction * rng.uniform(0.2, 1.15) * half  # in view, or entering it
        yaw = direction * np.pi / 2 + np.deg2rad(rng.uniform(-50, 50))
        _, t0 = placement(body, shape, 0.0, 0.0, 0.0, np.zeros(3))
        people.append(dict(shape=shape, poses=poses, z=z, x=x0 + direction * speed * t,
                           yaw=yaw, t0=t0))
    faces1 = body.faces_numpy()
    parts1 = body.part_labels.cpu().numpy()
    V = body.num_vertices
    faces = np.concatenate([faces1 + k * V for k in range(persons)])
    parts = np.tile(parts1, persons)
    scene = None
    for f in range(frames):
        verts_all, out = [], {k: [] for k in ('vertices', 'joints', 'pose', 'shape',
                                              'global_orient', 'transl')}
        for pp in people:
            R = OPTICAL_FROM_CANONICAL @ tilt @ Rotation.from_euler('y', pp['yaw']).as_matrix() @ C
            go = Rotation.from_matrix(R).as_rotvec()
            rel, jrel = _forward(body, pp['poses'][f], pp['shape'], go, pp['t0'])
            x, z = float(pp['x'][f]), pp['z']
            m = float((rel @ up).min())
            y = (-height - m - x * up[0] - z * up[2]) / up[1]  # lowest vertex on the floor
            root = np.array([x, y, z])
            verts_all.append(rel + root)
            for key, val in (('vertices', rel + root), ('joints', jrel + root),
                             ('pose', pp['poses'][f]), ('shape', pp['shape']),
                             ('global_orient', go), ('transl', pp['t0'] + root)):
                out[key].append(np.asarray(val, np.float32))
        verts = np.concatenate(verts_all)
        if background and scene is None:
            roots = np.stack([np.stack([pp['x'], np.zeros(frames), np.full(frames, pp['z'])], 1)
                              for pp in people]).reshape(-1, 3)
            centre = np.array([0.0, 0.0, float(np.max(lanes))])  # the room beyond
            scene = render_mod.sample_background(np.random.default_rng(scene_seed), camera,
                                                 centre, verts, up, p.background,
                                                 avoid=roots)
        depth, clean, labels, vids = _render(camera, verts, faces, parts, scene, noise, p,
                                             noise_rng)
        who = np.where(vids >= 0, vids // V, -1).astype(np.int8)
        frame = {k: np.stack(v) for k, v in out.items()}
        frame.update(depth=depth, depth_clean=clean, labels=labels,
                     vertex_ids=np.where(vids >= 0, vids % V, -1).astype(np.int32),
                     person_index=who, K=camera.K,
                     visible=np.bincount(who[who >= 0].astype(np.int64),
                                         minlength=persons).astype(np.int32))
        yield frame
