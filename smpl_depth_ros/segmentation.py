"""A reconstructed person's pixels and their body-part labels in the full image (no ROS).

`paste_labels` writes one person's labels into the frame's label images: the network's
labels as they are, and with segmentation 'model' (the default) those of the fitted mesh
(`model_labels`): each pixel takes the part of its nearest fitted surface sample
(`LabelSurface`), and pixels the network called background join the person near the mesh.
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


def paste_labels(labels_full, network_full, crop, lab, depth, K, vertices,
                 surface: LabelSurface, *, segmentation: str, margin_m: float,
                 keep_network_m: float) -> np.ndarray:
    """Write this person's labels into the full image and return its (H, W) mask.

    The person's pixels are the valid ones in its crop window within NEAR_RANGE of its
    median depth, others' blobs excluded (`crop`: its net.preprocess.Crop; `depth` and
    `K`: the frame's). `network_full` gets the network's labels
    (nearest-neighbour from the crop `lab`) where they say body. With segmentation
    'model' (the default) `labels_full` gets, on those pixels and on the ones within
    `margin_m` (model_label_margin_m) of the fitted mesh `vertices` (body the network
    missed: a hand, an arm's edge), the part of the nearest fitted vertex: the fit, which
    draws on all the frame's pixels and the body's shape, puts part borders where the
    body has them (val_s2: mIoU 0.761 -> 0.858; the network's labels are kept beside
    them). `keep_network_m`: model_label_keep_network_m (see `model_labels`).
    """
    H, W = labels_full.shape
    u0, v0 = max(int(np.floor(crop.u0)), 0), max(int(np.floor(crop.v0)), 0)
    u1 = min(int(np.ceil(crop.u0 + crop.scale * crop.size)), W)
    v1 = min(int(np.ceil(crop.v0 + crop.scale * crop.size)), H)
    m = np.zeros((H, W), bool)
    if u1 <= u0 or v1 <= v0:
        return m
    i = np.clip(((np.arange(v0, v1) + 0.5 - crop.v0) / crop.scale).astype(np.int64), 0,
                crop.size - 1)
    j = np.clip(((np.arange(u0, u1) + 0.5 - crop.u0) / crop.scale).astype(np.int64), 0,
                crop.size - 1)
    v = lab[np.ix_(i, j)]
    dw = depth[v0:v1, u0:u1]
    region = (dw > 0) & (np.abs(dw - crop.median_depth) < NEAR_RANGE)
    if crop.exclude is not None:
        region &= ~crop.exclude[v0:v1, u0:u1]
    keep = (v > 0) & region
    network_full[v0:v1, u0:u1][keep] = v[keep]
    if segmentation == 'model':
        keep, v = model_labels(region, keep, v, dw, K, u0, v0, vertices, surface,
                               crop.planes, margin_m, keep_network_m)
        labels_full[v0:v1, u0:u1][keep] = v[keep]
    m[v0:v1, u0:u1] = keep
    return m


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
