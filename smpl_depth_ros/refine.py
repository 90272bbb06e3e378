"""ICP refinement of a person's correspondences on its fitted mesh (no ROS).

After the Eq. 2 fit, each of its pixels takes the nearest vertex of the fitted mesh inside
the part the network predicted (`refine_correspondences`), and the pixels the network left
out join where they lie on the mesh (`near_surface_pixels`); the pipeline refits to both.
Both match pixels to vertices facing the camera only (`facing_camera`), as does the rigid
ICP (`rigid_icp`) that moves a tracked person's last body onto what is seen of them.
`depth_gap` scores how well a fitted mesh explains a blob's points, whatever network gave
the correspondences.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from smpl_depth_ros.fit.rig import facing_camera, kabsch  # noqa: F401  (re-exported)
from smpl_depth_ros.net.preprocess import pixel_points
from smpl_depth_ros.segmentation import PLANE_M


@dataclass(frozen=True)
class SurfaceParts:
    """A body model's mesh as the refinement needs it (made once per body model,
    `from_body`).

    Attributes:
        faces: (F, 3) the mesh's triangles.
        part_of_vertex: (V,) the body part of each vertex.
        valid_vertex_ids: (N,) the vertices a pixel can see (body.valid_vertices).
        part_vertices: part -> (n,) its valid vertices.
    """

    faces: np.ndarray
    part_of_vertex: np.ndarray
    valid_vertex_ids: np.ndarray
    part_vertices: list

    @classmethod
    def from_body(cls, body) -> 'SurfaceParts':
        parts = body.part_labels.cpu().numpy()
        valid = body.valid_vertices.cpu().numpy()
        return cls(body.faces_numpy(), parts, np.flatnonzero(valid),
                   [np.flatnonzero((parts == p) & valid) for p in range(int(parts.max()) + 1)])


GAP_CAP_M = 0.1  # depth_gap: a point's distance counts up to this (an outlier's no more)
_GAP_BARY = np.array([[1, 1, 1], [4, 1, 1], [1, 4, 1], [1, 1, 4]], np.float64)
_GAP_BARY /= _GAP_BARY.sum(1, keepdims=True)  # depth_gap: 4 points in each triangle


def depth_gap(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> float:
    """How far a person's points lie from a fitted mesh: the mean over `points` (N, 3) of
    the distance to the nearest of four points in each triangle of the mesh (`vertices`,
    `faces`), each capped at GAP_CAP_M (metres). It needs no correspondences, so it
    compares fits made from two networks' on the same blob (`both_networks`): a limb
    fitted where no pixel is, or a pixel no limb reaches, raises it. Coarse and fast, for
    the pipeline; `tools.reconstruct_image.point_to_surface` measures the same distance
    densely (200,000 samples), for evaluation."""
    if not len(points):
        return GAP_CAP_M
    tri = vertices[faces].astype(np.float64)  # (F, 3, 3)
    samples = np.einsum('sk,fkd->fsd', _GAP_BARY, tri).reshape(-1, 3)
    dist, _ = cKDTree(samples).query(points, distance_upper_bound=GAP_CAP_M)
    return float(np.minimum(dist, GAP_CAP_M).mean())


def refine_correspondences(pts, vids, vertices, surface: SurfaceParts,
                           front: np.ndarray | None) -> np.ndarray:
    """ICP step inside the predicted part: each point takes the nearest vertex of the
    fitted mesh among the vertices of its Eq. 2 vertex's part (the network decides
    the part, the geometry the exact vertex) that face the camera (`front`, see
    `facing_camera`; None: any; a part with fewer than 3 of them offers all its
    vertices). A pixel sees the front of the surface; the nearest vertex of a thin
    fitted limb or of a silhouette can be one on its far side (val_s2 32.8 -> 32.5 mm,
    val seq_s5 single frames 21.7 -> 21.4)."""
    pp = surface.part_of_vertex[vids]
    out = np.array(vids, np.int64)
    for p in np.unique(pp):
        vi = surface.part_vertices[p]
        if front is not None and front[vi].sum() >= 3:
            vi = vi[front[vi]]
        if not len(vi):
            continue
        m = pp == p
        out[m] = vi[cKDTree(vertices[vi]).query(pts[m])[1]]
    return out


def near_surface_pixels(d, K, vertices, r, c, crop, surface: SurfaceParts,
                        front: np.ndarray | None, margin: float):
    """Pixels the network did not give the person that lie within `margin` (metres:
    fit.icp_margin_m, widened for a noisy sensor) of its fitted mesh (a hand, the edge
    of an arm the network called background), with their nearest fitted vertex facing
    the camera (`front`, see `facing_camera`; None: any): (N, 3) float32 points, (N,)
    vertex ids. Looked for around the mesh's projection into the depth image `d` (K);
    `r, c` are the person's pixels already in the fit; other candidates' blobs and the
    scene planes of `crop` (PLANE_M, the floor under a foot) are left out. Matched to
    any vertex, a pixel can take one on the far side of a thin limb or a silhouette, as
    in the ICP step (val_s2 32.5 -> 31.9 mm, val seq_s5 single frames 21.4 -> 21.0)."""
    margin = float(margin)
    none = np.zeros((0, 3), np.float32), np.zeros(0, np.int64)
    ids = surface.valid_vertex_ids
    V = vertices[ids]
    if margin <= 0 or not len(V) or V[:, 2].min() <= 0:
        return none
    H, W = d.shape
    uv = V @ K.T
    uv = uv[:, :2] / uv[:, 2:]
    u0, v0 = np.clip(np.floor(uv.min(0)).astype(int) - 2, 0, (W, H))
    u1, v1 = np.clip(np.ceil(uv.max(0)).astype(int) + 3, 0, (W, H))
    if u1 <= u0 or v1 <= v0:
        return none
    win = d[v0:v1, u0:u1]
    cand = (win > V[:, 2].min() - margin) & (win < V[:, 2].max() + margin)
    inside = (r >= v0) & (r < v1) & (c >= u0) & (c < u1)
    cand[r[inside] - v0, c[inside] - u0] = False
    if crop.exclude is not None:
        cand &= ~crop.exclude[v0:v1, u0:u1]
    rr, cc = np.nonzero(cand)
    P = pixel_points(rr + v0, cc + u0, win[rr, cc], K)
    for pl in crop.planes:
        P = P[np.abs(P @ pl[:3] - pl[3]) > PLANE_M]
    if not len(P):
        return none
    if front is not None and front[ids].sum() >= 3:
        ids = ids[front[ids]]
        V = vertices[ids]
    dist, idx = cKDTree(V).query(P, distance_upper_bound=margin)
    ok = np.isfinite(dist)
    return P[ok].astype(np.float32), ids[idx[ok]]


def rigid_icp(points: np.ndarray, vertices: np.ndarray, front: np.ndarray | None,
              iterations: int = 20, max_points: int = 2000, start=None):
    """The rigid motion (R, t) that best lays a body's mesh `vertices` (V, 3), its
    camera-facing ones (`front`, None: all) matched, onto `points` (N, 3): point-to-vertex
    ICP, each round keeping the pairs within 2.5 times the median distance (at least
    2 cm). Returns (R, t, vertex_ids): every point's nearest facing vertex at the end."""
    ids = np.flatnonzero(front) if front is not None else np.arange(len(vertices))
    src = np.asarray(vertices, np.float64)[ids]
    tree = cKDTree(src)
    pts = np.asarray(points, np.float64)
    sub = pts[::max(1, int(np.ceil(len(pts) / max_points)))]
    R, t = np.eye(3), np.zeros(3) if start is None else np.asarray(start, np.float64)
    for _ in range(iterations):
        dist, j = tree.query((sub - t) @ R)  # the points in the mesh's frame
        keep = dist <= max(2.5 * float(np.median(dist)), 0.02)
        R2, t2 = kabsch(src[j[keep]], sub[keep], np.ones(int(keep.sum())))
        done = np.abs(R2 - R).max() < 1e-5 and np.abs(t2 - t).max() < 1e-5
        R, t = R2, t2
        if done:
            break
    return R, t, ids[tree.query((pts - t) @ R)[1]]
