"""render_panel: one synthetic frame as a PNG panel (depth | part labels | embedding).

    render_panel --out panel.png [--seed 3] [--camera kinect_v1] [--no-noise]
    render_panel --out panel.png --gt /tmp/synth.gt.npz --index 10

Depth is colour-mapped (near = bright yellow, far = dark blue, invalid = black), parts use
`body.parts.labels_to_rgb`, and the embedding panel shows, per body pixel, the
normalised canonical coordinates of its ground-truth template vertex as RGB (the first
three dimensions of the paper's 6-D embedding). With --gt, the depth comes from the bag
next to the sidecar when it exists, else it is re-rendered (noise-free) from the stored
vertices. PIL only.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

# Control points of a perceptually ordered colour map (viridis-like, dark -> bright).
_CMAP = np.array([[68, 1, 84], [65, 68, 135], [42, 120, 142], [34, 168, 132],
                  [122, 209, 81], [253, 231, 37]], np.float64)


def colorize_depth(depth: np.ndarray, lo: float | None = None,
                   hi: float | None = None) -> np.ndarray:
    """(H, W) metres -> (H, W, 3) uint8; near is bright, invalid (<= 0) is black."""
    valid = depth > 0
    if not valid.any():
        return np.zeros(depth.shape + (3,), np.uint8)
    lo = float(depth[valid].min()) if lo is None else lo
    hi = float(depth[valid].max()) if hi is None else hi
    s = 1.0 - np.clip((depth - lo) / max(hi - lo, 1e-6), 0, 1)  # near = 1
    x = s * (len(_CMAP) - 1)
    i = np.minimum(x.astype(int), len(_CMAP) - 2)
    f = (x - i)[..., None]
    rgb = (1 - f) * _CMAP[i] + f * _CMAP[i + 1]
    rgb[~valid] = 0
    return rgb.astype(np.uint8)


def embedding_rgb(vertex_ids: np.ndarray, embedding: np.ndarray) -> np.ndarray:
    """(H, W) vertex ids (-1 empty) + (V, >=3) embedding -> (H, W, 3) uint8."""
    col = (np.clip(embedding[:, :3], 0, 1) * 255).astype(np.uint8)
    out = col[np.maximum(vertex_ids, 0)]
    out[vertex_ids < 0] = 0
    return out


def make_panel(depth: np.ndarray, labels: np.ndarray, vertex_ids: np.ndarray,
               embedding: np.ndarray, titles=('depth', 'part labels', 'embedding')):
    """PIL image: the three (H, W) views side by side with a title strip."""
    from PIL import Image, ImageDraw

    from smpl_depth_ros.body.parts import labels_to_rgb
    tiles = [colorize_depth(depth), labels_to_rgb(labels), embedding_rgb(vertex_ids, embedding)]
    H, W = depth.shape
    pad, top = 4, 16
    img = Image.new('RGB', (3 * W + 4 * pad, H + top + pad), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    for k, (tile, title) in enumerate(zip(tiles, titles)):
        x = pad + k * (W + pad)
        img.paste(Image.fromarray(tile), (x, top))
        draw.text((x + 2, 2), title, fill=(0, 0, 0))
    return img


def build_parser() -> argparse.ArgumentParser:
    from smpl_depth_ros.synth.camera import CAMERAS
    ap = argparse.ArgumentParser(prog='render_panel', description=__doc__.split('\n')[0])
    ap.add_argument('--out', default='panel.png')
    ap.add_argument('--gt', default=None, help='a synth_bag .gt.npz; shows frame --index')
    ap.add_argument('--index', type=int, default=0)
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--camera', default='kinect_v1', choices=sorted(CAMERAS))
    ap.add_argument('--no-noise', action='store_true')
    ap.add_argument('--no-background', action='store_true')
    ap.add_argument('--backend', default=None, choices=['anny', 'smpl'],
                    help='body model (default anny, or the one named in --gt)')
    ap.add_argument('--model-path', default=None)
    return ap


def _from_gt(args, body):
    gt = np.load(args.gt)
    n = len(gt['stamps'])
    if not 0 <= args.index < n:
        raise SystemExit(f'render_panel: --index {args.index} outside 0..{n - 1}')
    i = args.index
    labels, vids = gt['labels'][i], gt['vertex_ids'][i]
    depth = None
    bag = args.gt[:-len('.gt.npz')] if args.gt.endswith('.gt.npz') else None
    if bag and os.path.isdir(bag):
        from smpl_depth_ros.bagio import iter_depth_bag
        stamp = int(gt['stamps'][i])
        for s, d, _K in iter_depth_bag(bag):
            if s == stamp:
                depth = d
                break
    if depth is None:
        from smpl_depth_ros.synth.camera import Camera
        from smpl_depth_ros.synth.render import render_body
        K = gt['K']
        cam = Camera(int(gt['width']), int(gt['height']), K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        depth = render_body(gt['vertices'][i], gt['faces'], body.part_labels.cpu().numpy(),
                            cam).depth
    return depth, labels, vids


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from smpl_depth_ros.body import load_body_model
    from smpl_depth_ros.body.parts import template_embedding

    backend = args.backend
    if backend is None and args.gt:
        backend = str(np.load(args.gt)['body_model'])
    try:
        body = load_body_model(backend or 'anny', args.model_path)
    except (FileNotFoundError, ValueError) as e:
        print(f'render_panel: {e}', file=sys.stderr)
        return 2
    if args.gt:
        depth, labels, vids = _from_gt(args, body)
    else:
        from smpl_depth_ros.synth import dataset
        from smpl_depth_ros.synth.camera import get_camera
        from smpl_depth_ros.synth.poses import PoseSampler
        fr = dataset.make_frame(body, PoseSampler(body), np.random.default_rng(args.seed),
                                get_camera(args.camera), noise=not args.no_noise,
                                background=not args.no_background)
        depth, labels, vids = fr['depth'], fr['labels'], fr['vertex_ids']
    emb = template_embedding(body.canonical_vertices(), body.part_labels.cpu().numpy())
    make_panel(depth, labels, vids, emb).save(args.out)
    print(json.dumps({'out': args.out, 'size': [int(depth.shape[1]), int(depth.shape[0])],
                      'body_pixels': int((vids >= 0).sum())}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
