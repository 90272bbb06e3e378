"""`reconstruct_image`: reconstruct every person in one depth image (16-bit PNG in mm).

    python -m smpl_depth_ros.tools.reconstruct_image DEPTH.png --fx 525 --fy 525 \\
        --cx 319.5 --cy 239.5 --max-persons 6 --out results/real

Prints per-person fit quality as JSON (median distance from the person's observed points
to the fitted surface; no ground truth needed) and saves a picture: depth, segmentation,
and the fitted meshes rendered from the camera.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np


def point_to_surface(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                     samples: int = 200_000) -> np.ndarray:
    """Distance of each point to the mesh surface, via a dense surface sampling (about
    3 mm spacing on a body, so distances are accurate to ~1 mm) and a KD-tree."""
    import trimesh
    from scipy.spatial import cKDTree
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    surf, _ = trimesh.sample.sample_surface_even(mesh, samples, seed=0)
    return cKDTree(surf).query(points, workers=-1)[0]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='reconstruct_image', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('depth_png')
    ap.add_argument('--fx', type=float, default=525.0)
    ap.add_argument('--fy', type=float, default=525.0)
    ap.add_argument('--cx', type=float, default=319.5)
    ap.add_argument('--cy', type=float, default=239.5)
    ap.add_argument('--scale', type=float, default=0.001, help='metres per PNG unit')
    ap.add_argument('--max-persons', type=int, default=6)
    ap.add_argument('--depth-max', type=float, default=8.0)
    ap.add_argument('--out', default='out/real')
    args = ap.parse_args(argv)

    from PIL import Image

    from smpl_depth_ros.body.parts import labels_to_rgb
    from smpl_depth_ros.config import PipelineConfig
    from smpl_depth_ros.pipeline import Reconstructor
    from smpl_depth_ros.tools.figures import render_mesh
    from smpl_depth_ros.tools.render_panel import colorize_depth

    depth = np.asarray(Image.open(args.depth_png)).astype(np.float32) * args.scale
    K = np.array([[args.fx, 0, args.cx], [0, args.fy, args.cy], [0, 0, 1.0]])
    rec = Reconstructor(PipelineConfig(device='cpu', tracking=False,
                                       max_persons=args.max_persons,
                                       depth_max=args.depth_max))
    res = rec.process(depth, K)
    faces = rec.body.faces_numpy()
    parts = rec.body.part_labels.cpu().numpy()
    persons = []
    meshes = np.zeros(depth.shape + (3,), np.uint8)
    for k, p in enumerate(res.persons):
        r, c = np.nonzero(p.mask)
        z = depth[r, c]
        pts = np.stack([(c - K[0, 2]) * z / K[0, 0], (r - K[1, 2]) * z / K[1, 1], z], 1)
        d = point_to_surface(pts, p.vertices, faces)
        persons.append(dict(index=k, pixels=int(len(pts)), bbox=list(p.bbox),
                            median_point_to_surface_mm=float(np.median(d) * 1000),
                            p90_point_to_surface_mm=float(np.percentile(d, 90) * 1000),
                            root_m=[round(float(x), 3) for x in p.joints[0]]))
        img = render_mesh(p.vertices, faces, parts, K, depth.shape)
        m = img.sum(-1) > 0
        meshes[m] = img[m]
    os.makedirs(args.out, exist_ok=True)
    tiles = [colorize_depth(depth), labels_to_rgb(res.labels), meshes]
    H, W = depth.shape
    pic = Image.new('RGB', (3 * W + 8, H), 'white')
    for k, t in enumerate(tiles):
        pic.paste(Image.fromarray(t), (k * (W + 4), 0))
    path = os.path.join(args.out, 'reconstruction.png')
    pic.save(path)
    out = dict(image=args.depth_png, persons=persons, picture=path,
               timings_ms={k: round(v, 1) for k, v in res.timings_ms.items()})
    with open(os.path.join(args.out, 'reconstruction.json'), 'w') as f:
        json.dump(out, f, indent=1)
    print(json.dumps(out))
    return 0


if __name__ == '__main__':
    sys.exit(main())
