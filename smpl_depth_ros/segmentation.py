"""A reconstructed person's pixels and their body-part labels in the full image (no ROS).

A person's window of the frame (`label_window`) gets the network's labels as they are
(`paste_network_labels`) and, with segmentation 'model' (the default), those of the fitted
mesh (`paste_model_labels`, `model_labels`): each pixel takes the part of its nearest
fitted surface sample (`LabelSurface`), and pixels the network called background join the
person near the mesh.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from smpl_depth_ros.net.preprocess import NEAR_RANGE, pixel_points

PLANE_M = 0.02  # 'model' labels: pixels this near a scene plane (the floor under a foot)
                # are not taken into the person by the margin (val_s2 mIoU 0.847 -> 0.856)
MODEL_LABEL_POINTS = 8000  # segmentation 'model': pixels labelled per person, at most ~
SAME_SURFACE_M = 0.03  # ... the others take their cell's part when this close in depth
_CORNER = 0.6  # barycentric weight of a triangle's corner samples (0.5 / 0.7: worse)
_CORNER_BARY = np.array([[_CORNER, (1 - _CORNER) / 2, (1 - _CORNER) / 2],
                         [(1 - _CORNER) / 2, _CORNER, (1 - _CORNER) / 2],
                         [(1 - _CORNER) / 2, (1 - _CORNER) / 2, _CORNER]])


@dataclass(frozen=True)
class LabelSurface:
    """Where a body model's surface is sampled for segmentation 'model', and the part of
    each sample (made once per body model, `from_body`).

    The fitted surface is sampled at its vertices and at 3 points per triangle near its
    corners, each sample labelled with its corner's part, so the nearest sample follows
    the parts' borders on the surface (each triangle split by its largest barycentric
    weight, as the renderer labels pixels) better than the nearest vertex (val_s2, true
    meshes: 0.933 -> 0.955).

    Attributes:
        vertex_ids: (N,) the valid vertices (the first N samples).
        faces: (F, 3) the faces of valid vertices only (3 samples each, after those).
        parts: (N + 3F,) the part of each sample.
        part_ids: part -> (n,) indices of its samples.
    """

    vertex_ids: np.ndarray
    faces: np.ndarray
    parts: np.ndarray
    part_ids: list

    @classmethod
    def from_body(cls, body) -> 'LabelSurface':
        parts = body.part_labels.cpu().numpy()
        valid = body.valid_vertices.cpu().numpy()
        vertex_ids = np.flatnonzero(valid)
        faces = body.faces_numpy()
        faces = faces[valid[faces].all(1)]
        labels = np.concatenate([parts[vertex_ids], parts[faces].reshape(-1)])
        return cls(vertex_ids, faces, labels,
                   [np.flatnonzero(labels == p) for p in range(int(parts.max()) + 1)])

    def samples(self, vertices: np.ndarray) -> np.ndarray:
        """(N + 3F, 3) the samples of a fitted mesh (`vertices`: (V, 3))."""
        return np.concatenate([vertices[self.vertex_ids], np.einsum(
            'sk,fkd->fsd', _CORNER_BARY, vertices[self.faces]).reshape(-1, 3)])


@dataclass
class LabelWindow:
    """One person's window of the frame (its crop's box, clipped to the image), with
    the pixels that may be theirs (`region`: valid, within NEAR_RANGE of the crop's
    median depth, others' blobs excluded), the network's labels there (`net`,
    nearest-neighbour from the crop) and its body pixels among them (`fg`)."""

    u0: int
    v0: int
    u1: int
    v1: int
    region: np.ndarray
    net: np.ndarray
    fg: np.ndarray

    def full(self, window_mask: np.ndarray, shape) -> np.ndarray:
        """(H, W) bool: `window_mask` placed in the frame."""
        m = np.zeros(shape, bool)
        m[self.v0:self.v1, self.u0:self.u1] = window_mask
        return m


def label_window(crop, lab: np.ndarray, depth: np.ndarray) -> LabelWindow:
    """The `LabelWindow` of a person whose crop (`crop`: its net.preprocess.Crop) the
    network labelled `lab` (S, S), in the frame's `depth`."""
    H, W = depth.shape
    u0, v0 = max(int(np.floor(crop.u0)), 0), max(int(np.floor(crop.v0)), 0)
    u1 = max(min(int(np.ceil(crop.u0 + crop.scale * crop.size)), W), u0)
    v1 = max(min(int(np.ceil(crop.v0 + crop.scale * crop.size)), H), v0)
    i = np.clip(((np.arange(v0, v1) + 0.5 - crop.v0) / crop.scale).astype(np.int64), 0,
                crop.size - 1)
    j = np.clip(((np.arange(u0, u1) + 0.5 - crop.u0) / crop.scale).astype(np.int64), 0,
                crop.size - 1)
    v = lab[np.ix_(i, j)]
    dw = depth[v0:v1, u0:u1]
    region = (dw > 0) & (np.abs(dw - crop.median_depth) < NEAR_RANGE)
    if crop.exclude is not None:
        region &= ~crop.exclude[v0:v1, u0:u1]
    return LabelWindow(u0, v0, u1, v1, region, v, (v > 0) & region)


def paste_network_labels(network_full: np.ndarray, win: LabelWindow) -> np.ndarray:
    """Write the network's labels of a person's body pixels into the frame's
    `network_full` and return the (H, W) mask of those pixels."""
    network_full[win.v0:win.v1, win.u0:win.u1][win.fg] = win.net[win.fg]
    return win.full(win.fg, network_full.shape)


def paste_model_labels(labels_full: np.ndarray, win: LabelWindow, depth: np.ndarray,
                       K: np.ndarray, vertices: np.ndarray, surface: LabelSurface, planes,
                       *, margin_m: float, keep_network_m: float) -> np.ndarray:
    """Segmentation 'model' (the default): write a person's labels from their fitted
    mesh `vertices` into `labels_full` and return the (H, W) mask of their pixels: the
    window's body pixels, and the ones of its region within `margin_m`
    (model_label_margin_m) of the mesh (body the network missed: a hand, an arm's edge),
    each with the part of the nearest fitted surface: the fit, which draws on all the
    frame's pixels and the body's shape, puts part borders where the body has them
    (val_s2: mIoU 0.761 -> 0.858). `planes`: the crop's scene planes;
    `keep_network_m`: model_label_keep_network_m (both: see `model_labels`)."""
    if not win.region.any():
        return win.full(win.region, labels_full.shape)
    dw = depth[win.v0:win.v1, win.u0:win.u1]
    keep, v = model_labels(win.region, win.fg, win.net, dw, K, win.u0, win.v0, vertices,
                           surface, planes, margin_m, keep_network_m)
    labels_full[win.v0:win.v1, win.u0:win.u1][keep] = v[keep]
    return win.full(keep, labels_full.shape)


def model_labels(region, fg, net, dw, K, u0, v0, vertices, surface: LabelSurface, planes,
                 margin_m: float, keep_network_m: float):
    """(mask, labels) of a window from the fitted mesh: `fg` pixels and the `region`
    ones within `margin_m` (model_label_margin_m) of a fitted vertex, each with the part
    of its nearest vertex, except where the network's part `net` has a vertex within
    `keep_network_m` (model_label_keep_network_m) as near (at a part border the fit is
    not sharper than that). The margin does not reach within PLANE_M of a scene plane in
    `planes` (Crop.planes): a foot's sole is within it of the floor it stands on (the
    network's body pixels there are kept: measured worse without). `dw`: the window's
    depth, its top-left pixel (u0, v0) of the image of intrinsics K.

    Large windows are labelled on a sub-grid of about MODEL_LABEL_POINTS pixels
    first; a pixel then takes the label of the four cells around it when they agree
    and its depth is on their surface, and is labelled on its own otherwise (part
    borders and silhouettes stay exact, at a bounded cost).
    """
    if planes:
        rr, cc = np.nonzero(region & ~fg)
        pts = pixel_points(rr + v0, cc + u0, dw[rr, cc], K)
        on = np.zeros(len(rr), bool)
        for pl in planes:
            on |= np.abs(pts @ pl[:3] - pl[3]) <= PLANE_M
        region = region.copy()
        region[rr[on], cc[on]] = False
    # One tree over the surface samples, and one per part as needed, shared by both
    # passes; built unbalanced (half the time to build, the same nearest samples: on 120
    # persons of multi_s31 the labels were identical, 13.0 -> 11.6 ms a person).
    samples = surface.samples(vertices)
    tree, part_trees = cKDTree(samples, balanced_tree=False, compact_nodes=False), {}

    def label(rr, cc):
        return label_pixels(rr, cc, dw, fg, net, K, u0, v0, surface, samples, tree,
                            part_trees, margin_m, keep_network_m)
    st = max(1, int(np.ceil(np.sqrt(np.count_nonzero(region) / MODEL_LABEL_POINTS))))
    if st == 1:
        rr, cc = np.nonzero(region)
        out = np.zeros(fg.shape, np.uint8)
        out[rr, cc] = label(rr, cc)
        return out > 0, out
    h, w = region.shape
    rr, cc = np.nonzero(region[::st, ::st])
    coarse = np.zeros(((h + st - 1) // st, (w + st - 1) // st), np.uint8)  # 0: none
    coarse[rr, cc] = label(rr * st, cc * st)
    # A pixel between four cells that carry the same label (0: not the person's, or
    # no depth), on their surface, takes it (agreement found on the sub-grid).
    pad = np.pad(coarse, ((0, 1), (0, 1)), mode='edge')
    agree = (coarse == pad[1:, :-1]) & (coarse == pad[:-1, 1:]) & (coarse == pad[1:, 1:])

    def up(a):
        return np.repeat(np.repeat(a, st, 0), st, 1)[:h, :w]
    c = up(coarse)
    same = up(agree) & (np.abs(dw - up(dw[::st, ::st])) < SAME_SURFACE_M)
    out = np.where(same & region, c, 0).astype(np.uint8)
    rr, cc = np.nonzero(region & ~same)
    out[rr, cc] = label(rr, cc)
    return out > 0, out


def label_pixels(rr, cc, dw, fg, net, K, u0, v0, surface: LabelSurface, samples, tree,
                 part_trees: dict, margin_m: float, keep_network_m: float) -> np.ndarray:
    """(N,) part of the window pixels (rr, cc) from the fitted mesh (0: not the
    person's); see `model_labels`. `samples`: the fitted surface's label samples
    (`LabelSurface.samples`), `tree` over them; `part_trees`: part -> KD-tree of its
    samples, filled as needed."""
    margin = float(margin_m)
    pts = pixel_points(rr + v0, cc + u0, dw[rr, cc], K)
    isfg = fg[rr, cc]
    part = np.zeros(len(pts), np.int64)
    if isfg.any():
        q = pts[isfg]
        dist, idx = tree.query(q)
        pf = surface.parts[idx]
        nf = net[rr[isfg], cc[isfg]].astype(np.int64)
        keep_net = float(keep_network_m)
        if keep_net > 0:
            for p in np.unique(nf[pf != nf]):
                vi = surface.part_ids[p]
                m = np.flatnonzero((nf == p) & (pf != nf))
                if len(vi) and len(m):
                    if p not in part_trees:
                        part_trees[p] = cKDTree(samples[vi], balanced_tree=False,
                                                compact_nodes=False)
                    dp = part_trees[p].query(q[m])[0]
                    pf[m[dp <= dist[m] + keep_net]] = p
        part[isfg] = pf
    rest = np.flatnonzero(~isfg)
    if margin > 0 and len(rest):
        lo, hi = samples.min(0) - margin, samples.max(0) + margin
        q = pts[rest]
        rest = rest[np.all((q > lo) & (q < hi), axis=1)]
        if len(rest):
            dist, idx = tree.query(pts[rest], distance_upper_bound=margin)
            ok = np.isfinite(dist)
            part[rest[ok]] = surface.parts[idx[ok]]
    return part
