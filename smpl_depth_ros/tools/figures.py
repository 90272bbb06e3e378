"""Paper-style figures (PIL only): Fig. 3 (depth, segmentation, regressed colours,
correspondences, fitted mesh from two viewpoints) and Fig. 4 (per-vertex error heat-map)."""
from __future__ import annotations

import os

import numpy as np

from smpl_depth_ros.body.parts import labels_to_rgb, template_embedding


def _shade(depth: np.ndarray) -> np.ndarray:
    """Depth render -> grey shading from depth gradients (a cheap normal shading)."""
    valid = depth > 0
    gy, gx = np.gradient(np.where(valid, depth, np.nan))
    n = np.stack([-np.nan_to_num(gx) * 200, -np.nan_to_num(gy) * 200, np.ones_like(depth)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    s = np.clip(n @ np.array([0.3, -0.4, 0.87]), 0, 1)
    img = (60 + 195 * s).astype(np.uint8)
    img[~valid] = 0
    return np.stack([img] * 3, -1)


def render_mesh(vertices, faces, part_labels, K, shape, rotate_deg: float = 0.0,
                vertex_colors=None):
    """Render a mesh from the camera (or orbited about its centroid's vertical axis)."""
    from smpl_depth_ros.synth.camera import Camera
    from smpl_depth_ros.synth.render import render_body
    V = np.asarray(vertices, np.float64)
    if rotate_deg:
        c = V.mean(0)
        a = np.deg2rad(rotate_deg)
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        V = (V - c) @ R.T + c
    cam = Camera(width=shape[1], height=shape[0], fx=K[0, 0], fy=K[1, 1], cx=K[0, 2],
                 cy=K[1, 2])
    r = render_body(V, faces, part_labels, cam)
    if vertex_colors is None:
        return _shade(r.depth)
    img = vertex_colors[np.maximum(r.vertex_ids, 0)]
    img[r.vertex_ids < 0] = 0
    return img


def error_colors(err_m: np.ndarray, max_m: float = 0.1) -> np.ndarray:
    """Per-vertex error -> blue (0) .. red (max_m) uint8 colours."""
    t = np.clip(err_m / max_m, 0, 1)[:, None]
    return (255 * ((1 - t) * np.array([0.1, 0.3, 1.0]) + t * np.array([1.0, 0.1, 0.1]))
            ).astype(np.uint8)


def _strip(tiles, titles):
    from PIL import Image, ImageDraw
    H, W = tiles[0].shape[:2]
    img = Image.new('RGB', (len(tiles) * (W + 4), H + 16), 'white')
    d = ImageDraw.Draw(img)
    for k, (t, name) in enumerate(zip(tiles, titles)):
        img.paste(Image.fromarray(t), (k * (W + 4), 16))
        d.text((k * (W + 4) + 2, 2), name, fill='black')
    return img


def save_figures(out_dir, index, body, depth, K, res, gt_vertices=None, canon=None):
    """Write fig3_<index>.png (and fig4_<index>.png with ground truth) into out_dir."""
    from smpl_depth_ros.tools.render_panel import colorize_depth
    os.makedirs(out_dir, exist_ok=True)
    p = res.persons[0]
    faces = body.faces_numpy()
    parts = body.part_labels.cpu().numpy()
    canon = body.canonical_vertices() if canon is None else canon
    emb = template_embedding(canon, parts)
    corr = np.zeros(depth.shape + (3,), np.uint8)
    corr[p.pixels[:, 0], p.pixels[:, 1]] = (emb[p.vertex_ids, :3] * 255).astype(np.uint8)
    ecol = (emb[:, :3] * 255).astype(np.uint8)
    tiles = [colorize_depth(depth), labels_to_rgb(res.labels), corr,
             render_mesh(p.vertices, faces, parts, K, depth.shape, vertex_colors=ecol),
             render_mesh(p.vertices, faces, parts, K, depth.shape),
             render_mesh(p.vertices, faces, parts, K, depth.shape, rotate_deg=90)]
    titles = ['depth', 'segmentation', 'correspondences (Eq. 2)', 'fitted mesh (template colours)',
              'fitted mesh', 'fitted mesh, side']
    _strip(tiles, titles).save(os.path.join(out_dir, f'fig3_{index:04d}.png'))
    if gt_vertices is not None:
        err = np.linalg.norm(p.vertices - gt_vertices, axis=1)
        col = error_colors(err)
        tiles = [render_mesh(p.vertices, faces, parts, K, depth.shape, vertex_colors=col),
                 render_mesh(p.vertices, faces, parts, K, depth.shape, rotate_deg=90,
                             vertex_colors=col)]
        _strip(tiles, [f'per-vertex error (blue 0 .. red 100 mm), mean {err.mean()*1000:.0f} mm',
                       'side']).save(os.path.join(out_dir, f'fig4_{index:04d}.png'))
