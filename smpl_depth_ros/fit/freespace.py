"""Free space: what a depth image says about where the body is not (no ROS).

A body vertex that projects onto a pixel whose measured depth lies well beyond it would
have been seen there instead: the sensor looked through that spot. So a vertex is either
observed, hidden behind something nearer, or outside the image. Correspondences only
constrain the parts that are seen; this constrains the unseen ones too: an arm out of
sight must be behind the body or out of frame, not in front of the wall the sensor sees.

`FreeSpace.targets` gives, for every vertex in free space beside the person, the
nearest point (at the vertex's own depth) of the region where it could hide; the fitter
pulls it there. Where a vertex can hide depends on its depth: behind anything measured
nearer than it (in layers of `margin` from the person's depth back), so a leg reaching
back beyond the person's depth hides at its own pixels even when a depth jump cut them
off the person's blob (over a far background with no floor, the leg was otherwise
dragged onto the body: validation frames 26.8 -> 15.2 mm).

A vertex in front of the person's own surface is left alone: pushing it
back along its ray was measured to hurt (val_s2 44.0 -> 50.8 mm) - a hand fitted a few
centimetres beside the observed hand lands on the chest's pixels, and the right move
is sideways, not behind the chest.

Solid scene planes (`planes`: the floor a person stands on, a wall they lean on) bound
the body too: a vertex beyond such a plane is inside it - occlusion cannot explain it -
and is pulled onto the plane (val_s2: a crouching leg fitted 35 cm into the floor).
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from smpl_depth_ros.fit.rig import facing_camera

MAX_LAYER = 8  # FreeSpace: depth layers beyond this one share its hiding places
SEE_THROUGH_FRONT_COS = -0.3  # see_through_share: vertices facing the camera at least this


class FreeSpace:
    """Free space of one depth image around one person.

    Args:
        depth: (H, W) metres; 0/NaN = no measurement (which hides nothing and reveals
            nothing: such pixels count as places a vertex could hide).
        K: (3, 3) intrinsics.
        ref_depth: the person's depth (e.g. the median of their points): pixels measured
            nearer than ref_depth + margin are where the person can hide; a vertex k
            margins beyond it can also hide where the sensor measured up to k margins
            farther (`_hiding`).
        margin: a vertex counts as seen through when the measurement lies more than this
            beyond it (sensor noise, flying pixels at silhouettes).
        tolerance_px: vertices this close to a hiding pixel are left alone (silhouette
            erosion and edge noise of the sensor).
        stride: the hiding region's distance transform is computed every `stride` pixels.
        box: optional (u0, v0, u1, v1) pixel window around the person: only there is
            free space looked for, and hiding places (the rest of the image is not
            looked at), for speed.
        planes: solid planes the body cannot pass, (4,) arrays (n, offset) with the body
            on the side n . x > offset (preprocess.Crop.planes, those with the person's
            points on the camera's side: see `supporting_planes`).
        plane_tolerance: metres a vertex may lie beyond a plane before it is pulled
            (sensor noise of the plane, soft tissue at the contact).
        own: optional (H, W) bool, the person's own pixels (their blob): never free
            space, whatever their depth. A hand held well behind or before the body is
            beyond ref_depth + margin; without this, the vertices on its rim, which
            project a pixel outside its silhouette onto the wall behind, would be pulled
            to the torso. A sensor that erodes silhouettes (most do) hides them anyway;
            on exact depth the true mesh had 24 such vertices a frame, pulled 11 cm.
    """

    def __init__(self, depth: np.ndarray, K: np.ndarray, ref_depth: float,
                 margin: float = 0.1, tolerance_px: float = 2.0, stride: int = 2,
                 box: tuple[float, float, float, float] | None = None,
                 planes=(), plane_tolerance: float = 0.03, own: np.ndarray | None = None):
        self.depth = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0, posinf=0.0,
                                   neginf=0.0)
        self.K = np.asarray(K, np.float64)
        self.ref_depth = float(ref_depth)
        self.margin = margin
        self.tolerance_px = tolerance_px
        self.stride = stride
        H, W = self.depth.shape
        if box is None:
            box = (0, 0, W, H)
        # The window, on the stride grid.
        s = stride
        self._u0, self._v0 = max(int(box[0]) // s, 0) * s, max(int(box[1]) // s, 0) * s
        self._u1, self._v1 = min(int(np.ceil(box[2])), W), min(int(np.ceil(box[3])), H)
        self._nearest = {}  # distance transform per depth layer, computed on first need
        self.planes = [np.asarray(p, np.float64) for p in planes]
        self.plane_tolerance = plane_tolerance
        self.own = own

    def _hiding(self, layer: int = 0):
        """(distance, row, col) on the stride grid: each cell's distance to, and nearest,
        cell where a vertex in depth layer `layer` could hide (outside the image counts).
        Layer k holds the vertices from ref_depth + k * margin on (k = 0: all nearer ones
        too); they can hide behind whatever was measured nearer than that + margin, so a
        limb reaching back beyond the person's depth is a hiding place for its own
        vertices, even when a depth jump has cut it off the person's blob."""
        if layer not in self._nearest:
            s = self.stride
            d = self.depth[self._v0:self._v1:s, self._u0:self._u1:s]
            hide = (d <= 0) | (d <= self.ref_depth + (layer + 1) * self.margin)
            if self.own is not None:
                hide |= self.own[self._v0:self._v1:s, self._u0:self._u1:s]
            # Beyond the image a vertex is hidden; beyond the window, merely not looked at.
            H, W = self.depth.shape
            hide = np.pad(hide, 1, constant_values=False)
            hide[0, :], hide[-1, :] = self._v0 == 0, self._v1 >= H
            hide[:, 0], hide[:, -1] = self._u0 == 0, self._u1 >= W
            if not hide.any():  # nowhere to hide in view: nothing to pull towards
                self._nearest[layer] = (np.zeros(hide[1:-1, 1:-1].shape),) * 3
                return self._nearest[layer]
            dist, (iy, ix) = ndimage.distance_transform_edt(~hide, return_indices=True)
            self._nearest[layer] = (dist[1:-1, 1:-1] * s, (iy[1:-1, 1:-1] - 1) * s + self._v0,
                                    (ix[1:-1, 1:-1] - 1) * s + self._u0)
        return self._nearest[layer]

    def targets(self, verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vertices in free space and where to pull them.

        Args:
            verts: (V, 3) camera-frame vertices.

        Returns:
            (ids (M,), targets (M, 3)): each target lies at its vertex's depth, on the
            nearest pixel where the vertex would be hidden; for a vertex beyond a solid
            plane, its projection onto the plane.
        """
        ids, tgt = self._seen_through(verts)
        for pl in self.planes:
            sd = verts @ pl[:3] - pl[3]
            inside = np.flatnonzero(sd < -self.plane_tolerance)
            inside = inside[~np.isin(inside, ids)]
            if len(inside):
                ids = np.concatenate([ids, inside])
                tgt = np.concatenate([tgt, verts[inside] - sd[inside, None] * pl[:3]])
        return ids, tgt

    def _seen_through(self, verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The vertices in free space and their hiding places (see `targets`)."""
        K, d = self.K, self.depth
        z = verts[:, 2]
        zs = np.where(z > 1e-3, z, 1.0)
        u = np.floor(K[0, 0] * verts[:, 0] / zs + K[0, 2] + 0.5).astype(np.int64)
        v = np.floor(K[1, 1] * verts[:, 1] / zs + K[1, 2] + 0.5).astype(np.int64)
        ids = np.flatnonzero((z > 1e-3) & (u >= self._u0) & (u < self._u1) & (v >= self._v0)
                             & (v < self._v1))
        ids = ids[d[v[ids], u[ids]] > z[ids] + self.margin]
        if not len(ids):
            return ids, np.zeros((0, 3))
        zt = z[ids]
        layer = np.clip(np.floor((zt - self.ref_depth) / self.margin), 0,
                        MAX_LAYER).astype(np.int64)
        s = self.stride
        gy, gx = (v[ids] - self._v0) // s, (u[ids] - self._u0) // s
        # Layer 0's hiding places are every layer's: a deeper layer's own distance
        # transform is needed only for its vertices still out of them.
        dist, ty, tx = (a[gy, gx] for a in self._hiding(0))
        deep = (layer > 0) & (dist > self.tolerance_px)
        for k in np.unique(layer[deep]):
            sel = deep & (layer == k)
            dist[sel], ty[sel], tx[sel] = (a[gy[sel], gx[sel]] for a in self._hiding(int(k)))
        far = dist > self.tolerance_px  # 0 in front of the person: left alone
        ids, ty, tx, zt = ids[far], ty[far], tx[far], zt[far]
        tgt = np.stack([(tx - K[0, 2]) * zt / K[0, 0], (ty - K[1, 2]) * zt / K[1, 1], zt], 1)
        return ids, tgt


def see_through_share(verts: np.ndarray, faces: np.ndarray, depth: np.ndarray, K: np.ndarray,
                      margin: float, front_cos: float = SEE_THROUGH_FRONT_COS) -> float:
    """The share of a fitted mesh's camera-facing vertices (inside the image, on a valid
    pixel) at which the sensor measured more than `margin` beyond the vertex: the share of
    the body's visible side that stands where the sensor looked through it. A person's
    fit leaves a few per cent (silhouette pixels, a limb a few centimetres off; at most
    0.26 on the validation bags, the worst being half hidden behind someone); a body
    made up for a box or a piece of wall sticks out of it (0.25-0.9 on the boxes of a
    single-person sequence).

    Args:
        verts: (V, 3) camera-frame vertices; faces: (F, 3) the mesh's triangles.
        depth: (H, W) metres, 0 = no measurement (such pixels are not counted).
        K: (3, 3) intrinsics.
        margin: metres (the fit's free_space_margin, widened for sensor noise).
        front_cos: a vertex faces the camera when the cosine of its normal and the view
            ray is below this.
    """
    v = np.asarray(verts, np.float64)
    v = v[facing_camera(v, faces, front_cos) & (v[:, 2] > 1e-3)]
    H, W = depth.shape
    u = np.floor(K[0, 0] * v[:, 0] / v[:, 2] + K[0, 2] + 0.5).astype(np.int64)
    r = np.floor(K[1, 1] * v[:, 1] / v[:, 2] + K[1, 2] + 0.5).astype(np.int64)
    inside = (u >= 0) & (u < W) & (r >= 0) & (r < H)
    d = depth[r[inside], u[inside]]
    valid = d > 0
    if not valid.any():
        return 0.0
    return float(np.mean(d[valid] > v[inside, 2][valid] + margin))


def supporting_planes(planes, points: np.ndarray, tolerance: float = 0.03,
                      max_fraction: float = 0.01) -> list:
    """The scene planes (n, offset) a person's observed `points` (N, 3) lie in front of
    (at most `max_fraction` of them more than `tolerance` beyond): the floor under them,
    a wall behind them. A table top with the legs seen below it is not one; legs hidden
    entirely under a table would be taken for legs in the floor (no table is told from
    a floor by its plane alone)."""
    pts = np.asarray(points, np.float64)
    return [p for p in planes
            if len(pts) and np.mean(pts @ p[:3] - p[3] < -tolerance) <= max_fraction]
