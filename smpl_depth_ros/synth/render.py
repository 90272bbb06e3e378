"""Exact depth, part-label and correspondence rendering by ray casting (no ROS).

One ray per pixel centre through a pinhole camera (see synth.camera), first hit found
by Embree (embreex, the library behind `trimesh.ray.ray_pyembree`, called directly to
skip trimesh's per-call copies; `first_hits`), then the hit point is recomputed in
float64 on the hit triangle's plane, so depth is exact up to float64 rounding (Embree
works in float32 and only picks the triangle). Barycentrics of the hit come from
`trimesh.triangles.points_to_barycentric`. Depth is the optical-frame z of the hit, not
the ray length.

Background geometry (floor, walls, boxes; `Background`, `sample_background`; a chair
under a seated person, `chair_under`) is concatenated after the body triangles and cast
in the same pass, so the body occludes it and vice versa; background pixels get label 0
and vertex id -1.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import trimesh
import trimesh.triangles

try:  # Embree through embreex, the backend of trimesh.ray.ray_pyembree
    from embreex import rtcore_scene as _rtcore_scene
    from embreex.mesh_construction import TriangleMesh as _EmbreeTriangleMesh
    _embree = (_rtcore_scene, _EmbreeTriangleMesh)
except ImportError:  # pragma: no cover
    _embree = None

from smpl_depth_ros.body.parts import PART_NAMES
from smpl_depth_ros.synth.camera import Camera

# Background face kinds (Background.kinds).
FLOOR, WALL, BOX = 1, 2, 3


@dataclass
class RenderResult:
    """One rendered frame.

    Attributes:
        depth: (H, W) float32 z in metres, 0 where nothing was hit.
        labels: (H, W) uint8 body-part class (0 = background, including background
            geometry).
        vertex_ids: (H, W) int32 body template vertex of the hit triangle with the largest
            barycentric weight; -1 off the body.
        normals_cos: (H, W) float32 |cos| of the angle between the pixel ray and the hit
            triangle's normal (1 = facing the camera, 0 = grazing); 0 where no hit.
        face_ids: (H, W) int32 hit triangle: body faces are 0..F-1, background faces
            follow (F + index into Background.faces); -1 where no hit.
        num_rays: how many rays were cast.
    """

    depth: np.ndarray
    labels: np.ndarray
    vertex_ids: np.ndarray
    normals_cos: np.ndarray
    face_ids: np.ndarray
    num_rays: int = 0

    @property
    def body_mask(self) -> np.ndarray:
        """(H, W) bool, pixels that see the body."""
        return self.vertex_ids >= 0


@dataclass
class Background:
    """Static scene geometry in the camera optical frame.

    Attributes:
        vertices: (M, 3) float64 metres, optical frame.
        faces: (G, 3) int64 triangles into `vertices`.
        kinds: (G,) uint8 FLOOR, WALL or BOX per triangle.
        up: (3,) unit vector, the floor normal pointing up (optical frame).
        floor_offset: the floor is {p : p . up = floor_offset}; None when there is no floor.
    """

    vertices: np.ndarray
    faces: np.ndarray
    kinds: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, -1.0, 0.0]))
    floor_offset: float | None = None

    @staticmethod
    def empty() -> 'Background':
        return Background(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.uint8))

    def __add__(self, other: 'Background') -> 'Background':
        return Background(
            np.concatenate([self.vertices, other.vertices]),
            np.concatenate([self.faces, other.faces + len(self.vertices)]),
            np.concatenate([self.kinds, other.kinds]),
            self.up, self.floor_offset if self.floor_offset is not None else other.floor_offset)


@dataclass(frozen=True)
class BackgroundParams:
    """Random scene layout.

    Attributes:
        wall_prob: probability of a back wall behind the person.
        wall_gap: (min, max) metres from the person's root to the back wall.
        wall_yaw_deg: back-wall rotation about the vertical, uniform in +-this.
        side_wall_prob: probability of a second wall, perpendicular to the back wall.
        side_wall_offset: (min, max) lateral metres from the person to the side wall.
        wall_height: metres above the floor.
        num_boxes: (min, max) clutter boxes, inclusive.
        box_size: (min, max) box edge length in metres.
        box_min_distance: boxes stand at least this far in front of the camera (metres).
        max_occlusion: largest fraction of the person's image bbox a box in front of
            them may cover.
        min_camera_height: no floor (and no boxes) when the camera is lower than this
            above the floor (the floor would hide the person).
    """

    wall_prob: float = 0.9
    wall_gap: tuple[float, float] = (0.8, 3.0)
    wall_yaw_deg: float = 30.0
    side_wall_prob: float = 0.4
    side_wall_offset: tuple[float, float] = (1.0, 3.0)
    wall_height: float = 3.0
    num_boxes: tuple[int, int] = (0, 4)
    box_size: tuple[float, float] = (0.2, 0.8)
    box_min_distance: float = 1.5
    max_occlusion: float = 0.15
    min_camera_height: float = 0.1


def _quad(p0, p1, p2, p3, kind):
    v = np.stack([p0, p1, p2, p3]).astype(np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int64)
    return Background(v, f, np.full(2, kind, np.uint8))


def _box(center, right, fwd, up, size, yaw):
    """Box standing on `center` (a floor point), edges (sa, sb, height), yawed about up."""
    c, s = np.cos(yaw), np.sin(yaw)
    ea, eb = c * right + s * fwd, -s * right + c * fwd
    sa, sb, sh = size
    corners = np.array([center + i * sa / 2 * ea + j * sb / 2 * eb + k * sh * up
                        for k in (0, 1) for j in (-1, 1) for i in (-1, 1)])
    # corner index = 4k + 2j' + i'
    quads = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    faces = np.array([[q[0], q[1], q[2]] for q in quads] + [[q[0], q[2], q[3]] for q in quads])
    return Background(corners, faces, np.full(len(faces), BOX, np.uint8))


def _bbox_px(camera: Camera, points: np.ndarray):
    p = points[points[:, 2] > 1e-3]
    if len(p) == 0:
        return None
    uv = camera.project(p)
    return uv.min(0), uv.max(0)


def sample_background(rng: np.random.Generator, camera: Camera, person_root: np.ndarray,
                      person_vertices: np.ndarray | None = None, up: np.ndarray | None = None,
                      params: BackgroundParams = BackgroundParams(),
                      avoid: np.ndarray | None = None) -> Background:
    """A random floor / wall / clutter scene around a person.

    Args:
        rng: random generator.
        camera: the camera (its field of view and range size the geometry).
        person_root: (3,) the person's root joint, optical frame, metres.
        person_vertices: optional (V, 3) posed body; its lowest vertex along `up` sets the
            floor height (feet on the floor), and boxes avoid occluding it. Without it the
            floor is 0.95 m below the root.
        up: optional (3,) up direction in the optical frame (default (0, -1, 0), i.e. an
            upright camera); pass the person's up axis when the camera is tilted.
        params: layout parameters.
        avoid: optional (K, 3) more person positions (e.g. a sequence's root track) that
            boxes must keep clear of, like `person_root`.

    Returns:
        Background in the optical frame.
    """
    root = np.asarray(person_root, np.float64).reshape(3)
    up = np.array([0.0, -1.0, 0.0]) if up is None else np.asarray(up, np.float64).reshape(3)
    up = up / np.linalg.norm(up)
    fwd = np.array([0.0, 0.0, 1.0]) - up[2] * up
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    if person_vertices is not None:
        pv = np.asarray(person_vertices, np.float64)
        d = float((pv @ up).min())
    else:
        pv = None
        d = float(root @ up) - 0.95
    has_floor = d <= -params.min_camera_height  # camera (origin) above the floor

    def at(a, b, h=0.0):
        return d * up + a * right + b * fwd + h * up

    far = 1.5 * camera.max_range + 5.0
    ap, bp = float(root @ right), float(root @ fwd)
    keep = np.concatenate([root[None], np.asarray(avoid, np.float64).reshape(-1, 3)]
                          if avoid is not None else [root[None]])
    keep_ab = np.stack([keep @ right, keep @ fwd], 1)  # floor coordinates to keep clear
    scene = Background.empty()
    scene.up = up
    if has_floor:
        scene = scene + _quad(at(-far, -1.0), at(far, -1.0), at(far, far), at(-far, far), FLOOR)
        scene.floor_offset = d
    H = params.wall_height
    b_wall = None
    if rng.random() < params.wall_prob:
        gap = rng.uniform(*params.wall_gap)
        psi = np.deg2rad(rng.uniform(-params.wall_yaw_deg, params.wall_yaw_deg))
        b_wall = bp + gap
        t = np.array([np.cos(psi), np.sin(psi)])
        nrm = np.array([-t[1], t[0]])  # wall normal, towards +b (away from the camera)
        c = np.array([ap, b_wall])
        if c @ nrm < 0.5:  # the camera must be in front of the wall, like the person
            t, nrm = np.array([1.0, 0.0]), np.array([0.0, 1.0])
        e0, e1 = c - far * t, c + far * t
        scene = scene + _quad(at(*e0), at(*e1), at(*e1, H), at(*e0, H), WALL)
        if rng.random() < params.side_wall_prob:
            off = rng.uniform(*params.side_wall_offset)
            for side in rng.permutation([-1.0, 1.0]):
                s0 = c + side * off * t
                # camera and person on the same side of the side wall: no occlusion
                if (-s0 @ t) * side < -0.3 and ((ap, bp) - s0) @ t * side < 0:
                    s1 = s0 - far * nrm
                    scene = scene + _quad(at(*s0), at(*s1), at(*s1, H), at(*s0, H), WALL)
                    break
    if has_floor:
        bb = _bbox_px(camera, pv) if pv is not None else None
        person_far = float(pv[:, 2].max()) if pv is not None else root[2]
        tan_half = (camera.width / 2) / camera.fx
        b_max = (b_wall - 0.3) if b_wall is not None else min(camera.max_range, bp + 4.0)
        for _ in range(rng.integers(params.num_boxes[0], params.num_boxes[1] + 1)):
            for _try in range(20):
                size = rng.uniform(*params.box_size, size=3)
                b_min = params.box_min_distance
                b = rng.uniform(b_min, max(b_max, b_min + 0.5))
                a = rng.uniform(-1.0, 1.0) * b * tan_half
                half_diag = 0.5 * np.hypot(size[0], size[1])
                if np.hypot(*(keep_ab - (a, b)).T).min() < half_diag + 0.5:
                    continue  # would intersect the person
                box = _box(at(a, b), right, fwd, up, size, rng.uniform(0, np.pi))
                if bb is not None and box.vertices[:, 2].min() < person_far:
                    bx = _bbox_px(camera, box.vertices)
                    if bx is not None:
                        lo, hi = np.maximum(bx[0], bb[0]), np.minimum(bx[1], bb[1])
                        inter = np.prod(np.clip(hi - lo, 0, None))
                        area = np.prod(np.maximum(bb[1] - bb[0], 1.0))
                        if inter / area > params.max_occlusion:
                            continue
                scene = scene + box
                break
    return scene


_TORSO = PART_NAMES.index('torso')
_THIGHS = (PART_NAMES.index('upper_leg_l'), PART_NAMES.index('upper_leg_r'))
_SHINS = (PART_NAMES.index('lower_leg_l'), PART_NAMES.index('lower_leg_r'))
SEAT_PARTS = (_TORSO, *_THIGHS)  # torso and upper legs: what rests on a seat


def chair_under(vertices: np.ndarray, part_labels: np.ndarray, up: np.ndarray,
                rng: np.random.Generator) -> Background | None:
    """A chair under a seated body, or None when the body is not seated (a thigh
    within 40 deg of vertical, or the buttocks less than 0.15 m above the feet).

    The seat's top touches the lowest point of the torso and thighs, from just behind
    the buttocks to under the thighs (0.38-0.48 m deep, ending 0.12 m behind the knees'
    front, 0.42-0.52 m wide), on four legs down to the body's lowest point (the floor
    under its feet); a backrest behind the back (0.3-0.6 m high) two times in three.
    The chair faces the way the thighs point.

    Args:
        vertices: (V, 3) posed body, optical frame, metres.
        part_labels: (V,) part class per vertex (body.parts).
        up: (3,) the floor normal, pointing up.
        rng: random generator (sizes, the backrest).
    """
    v = np.asarray(vertices, np.float64)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    h = v @ up
    floor = float(h.min())
    torso = v[part_labels == _TORSO]
    thighs = v[np.isin(part_labels, _THIGHS)]
    if len(torso) == 0 or len(thighs) == 0:
        return None
    fwd = np.zeros(3)
    for thigh, shin in zip(_THIGHS, _SHINS):  # each thigh's long axis, towards its knee
        t, k = v[part_labels == thigh], v[part_labels == shin]
        if len(t) < 3 or len(k) == 0:
            return None
        axis = np.linalg.svd(t - t.mean(0), full_matrices=False)[2][0]
        axis *= np.sign(axis @ (k.mean(0) - t.mean(0))) or 1.0
        if abs(axis @ up) > 0.75:
            return None  # a thigh within 40 deg of vertical: not seated
        fwd += axis
    fwd -= (fwd @ up) * up
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    seat = v[np.isin(part_labels, SEAT_PARTS)]
    top = float((seat @ up).min()) - 0.003
    if top - floor < 0.15:
        return None
    low = seat[seat @ up < top + 0.25]  # the buttocks and the thighs' undersides
    back = float((low @ fwd).min())
    depth, width = rng.uniform(0.38, 0.48), rng.uniform(0.42, 0.52)
    a_mid = float(thighs.mean(0) @ right)
    b0 = back - 0.04
    depth = min(depth, float((thighs @ fwd).max()) - 0.12 - b0)  # behind the knees
    base = floor * up + a_mid * right + (b0 + depth / 2) * fwd
    thick, leg = 0.04, 0.035
    chair = _box(base + (top - thick - floor) * up, right, fwd, up, (width, depth, thick), 0.0)
    for i in (-1, 1):
        for j in (-1, 1):
            c = base + i * (width / 2 - leg) * right + j * (depth / 2 - leg) * fwd
            chair = chair + _box(c, right, fwd, up, (leg, leg, top - thick - floor), 0.0)
    if rng.random() < 2 / 3:
        spine = torso[torso @ up > top + 0.05]
        if len(spine):
            b_back = min(float((spine @ fwd).min()), back) - 0.01
            c = floor * up + a_mid * right + (b_back - 0.015) * fwd + (top - floor) * up
            chair = chair + _box(c, right, fwd, up, (width, 0.03, rng.uniform(0.3, 0.6)),
                                 0.0)
    chair.up = up
    return chair


def _check(vertices, faces, part_labels):
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f'vertices must be (V, 3), got {vertices.shape}')
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f'faces must be (F, 3), got {faces.shape}')
    if part_labels.shape != (vertices.shape[0],):
        raise ValueError(f'part_labels must be ({vertices.shape[0]},), got {part_labels.shape}')


def first_hits(vertices: np.ndarray, faces: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Index of the first triangle hit by rays from the origin, -1 for a miss.

    Uses the embreex scene directly (the library behind trimesh's `ray_pyembree`):
    trimesh's `intersects_first` adds about 70 ms of float64 copies and direction
    normalisation per 640x480 frame, three times the Embree query itself. Falls back to
    trimesh's generic intersector when embreex is not installed (much slower, and it
    needs the optional `rtree` package).

    Args:
        vertices: (V, 3) float64 metres.
        faces: (F, 3) int triangles.
        dirs: (N, 3) float32 ray directions (any length).

    Returns:
        (N,) int triangle index.
    """
    if _embree is not None:
        scene = _embree[0].EmbreeScene()
        _embree[1](scene=scene, vertices=np.ascontiguousarray(vertices, np.float32),
                   indices=np.ascontiguousarray(faces, np.int32))
        return scene.run(np.zeros_like(dirs), np.ascontiguousarray(dirs, np.float32))
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False, validate=False)
    return mesh.ray.intersects_first(np.zeros(dirs.shape), np.asarray(dirs, np.float64))


def render_body(vertices: np.ndarray, faces: np.ndarray, part_labels: np.ndarray,
                camera: Camera, background: Background | None = None) -> RenderResult:
    """Ray-cast a body mesh (and optional background) into depth, labels, vertex ids.

    Without a background only pixels inside the body's projected bounding box are cast.

    Args:
        vertices: (V, 3) posed body, camera optical frame, metres.
        faces: (F, 3) int triangles.
        part_labels: (V,) int part class per vertex (1..14).
        camera: intrinsics and image size.
        background: optional scene geometry, optical frame.

    Returns:
        RenderResult with (H, W) images.
    """
    V = np.asarray(vertices, np.float64)
    Fb = np.asarray(faces, np.int64)
    part_labels = np.asarray(part_labels)
    _check(V, Fb, part_labels)
    H, W = camera.height, camera.width
    depth = np.zeros((H, W), np.float32)
    labels = np.zeros((H, W), np.uint8)
    vids = np.full((H, W), -1, np.int32)
    ncos = np.zeros((H, W), np.float32)
    fids = np.full((H, W), -1, np.int32)
    empty = RenderResult(depth, labels, vids, ncos, fids, 0)

    has_bg = background is not None and len(background.faces) > 0
    if has_bg:
        allv = np.concatenate([V, background.vertices])
        allf = np.concatenate([Fb, background.faces + len(V)])
        u0, v0, u1, v1 = 0, 0, W, H
    else:
        allv, allf = V, Fb
        if len(Fb) == 0:
            return empty
        used = V[np.unique(Fb)]
        if (used[:, 2] <= 1e-3).any():  # behind or at the camera: bbox is unbounded
            u0, v0, u1, v1 = 0, 0, W, H
        else:
            uv = camera.project(used)
            lo, hi = np.floor(uv.min(0)) - 1, np.ceil(uv.max(0)) + 2
            u0, v0 = (int(np.clip(x, 0, n)) for x, n in zip(lo, (W, H)))
            u1, v1 = (int(np.clip(x, 0, n)) for x, n in zip(hi, (W, H)))
            if u1 <= u0 or v1 <= v0:
                return empty
    nu, nv = u1 - u0, v1 - v0
    xs = (np.arange(u0, u1) - camera.cx) / camera.fx  # ray direction (x, y, 1)
    ys = (np.arange(v0, v1) - camera.cy) / camera.fy
    dirs = np.empty((nv, nu, 3), np.float32)
    dirs[..., 0] = xs[None, :]
    dirs[..., 1] = ys[:, None]
    dirs[..., 2] = 1.0
    dirs = dirs.reshape(-1, 3)
    # Per-triangle plane: normal n (unnormalised) and n . p0.
    corners = allv[allf]
    fn = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    fc = np.einsum('ij,ij->i', fn, corners[:, 0])
    fnorm = np.linalg.norm(fn, axis=1)
    tri = first_hits(allv, allf, dirs)
    tri = tri.reshape(nv, nu)
    hit = tri >= 0
    tc = np.where(hit, tri, 0)
    x, y = xs[None, :], ys[:, None]
    dn = fn[:, 0][tc] * x + fn[:, 1][tc] * y + fn[:, 2][tc]
    with np.errstate(divide='ignore', invalid='ignore'):
        t = fc[tc] / dn  # exact float64 ray parameter; d_z = 1 so t is the depth z
        cos = np.abs(dn) / (fnorm[tc] * np.sqrt(x * x + y * y + 1.0))
    hit &= np.isfinite(t) & (t > 0) & (np.abs(dn) > 1e-12 * fnorm[tc])
    win = (slice(v0, v1), slice(u0, u1))
    depth[win] = np.where(hit, t, 0.0)
    ncos[win] = np.where(hit, cos, 0.0)
    fids[win] = np.where(hit, tri, -1)
    rows, cols = np.nonzero(hit & (tri < len(Fb)))
    if len(rows):
        tb = tri[rows, cols].astype(np.int64)
        tz = t[rows, cols]
        pts = np.stack([xs[cols] * tz, ys[rows] * tz, tz], 1)
        bary = trimesh.triangles.points_to_barycentric(corners[tb], pts)
        vid = Fb[tb, np.argmax(bary, axis=1)]
        vids[rows + v0, cols + u0] = vid
        labels[rows + v0, cols + u0] = part_labels[vid]
    return RenderResult(depth, labels, vids, ncos, fids, len(dirs))


def benchmark_render(body=None, sizes=((320, 240), (640, 480)), repeats: int = 5,
                     seed: int = 0) -> dict[str, dict[str, float]]:
    """Frames per second of `render_body` (anny body at 2.5 m), body only and with a
    sampled background, per image size.

    Returns:
        {'WxH': {'body': fps, 'background': fps, 'body_rays': rays}}.
    """
    from smpl_depth_ros.synth.camera import CAMERAS
    if body is None:
        from smpl_depth_ros.body.anny_model import AnnyBody
        body = AnnyBody()
    import torch
    from smpl_depth_ros.synth import poses
    rng = np.random.default_rng(seed)
    shape = poses.sample_shape(body, rng)[0]
    go, tr = poses.placement(body, shape, 0.3, 0.0, 0.0, np.array([0.0, 0.1, 2.5]))
    with torch.no_grad():
        out = body(torch.zeros(1, body.num_pose_joints, 3), torch.as_tensor(shape)[None],
                   torch.as_tensor(go)[None], torch.as_tensor(tr)[None])
    verts = out.vertices[0].numpy()
    faces = body.faces_numpy()
    labels = body.part_labels.numpy()
    res = {}
    for w, h in sizes:
        cam = CAMERAS['kinect_v1'].scaled(w, h)
        bg = sample_background(rng, cam, out.joints[0, 0].numpy(), verts)
        row = {}
        for key, b in (('body', None), ('background', bg)):
            r = render_body(verts, faces, labels, cam, b)  # warm-up
            t0 = time.perf_counter()
            for _ in range(repeats):
                r = render_body(verts, faces, labels, cam, b)
            row[key] = repeats / (time.perf_counter() - t0)
            row[f'{key}_rays'] = float(r.num_rays)
        res[f'{w}x{h}'] = row
    return res
