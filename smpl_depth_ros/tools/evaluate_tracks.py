"""`evaluate_tracks`: multi-person detection, IDs and accuracy on a `synth_bag --persons` bag.

    evaluate_tracks BAG [--frames N] [--json out.json] [-p NAME=VALUE ...]

Runs the pipeline over the bag as the node would (tracking on, `max_persons` = the
bag's number of people unless `-p max_persons=` says otherwise) and scores it with
`evaluation.TrackScore`: recall, precision, ID switches (per 100 person-frames found),
MOTA, per-person PVE (mm, camera frame, no alignment), IDs used, and the frame rate;
with `--per-frame`, also every true person's outcome in every frame (`TrackScore.records`,
the JSON's `records`: which person-frames a change gains or loses).
A true person counts as one to find when at least `--min-visible` of its pixels are in
view (default 1,500 at 640x480, scaled by the image area).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='evaluate_tracks', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('bag')
    ap.add_argument('--gt', default=None, help='ground truth (default <bag>.gt.npz)')
    ap.add_argument('--frames', type=int, default=0, help='first N frames (0 = all)')
    ap.add_argument('--device', default='cpu')
    ap.add_argument('--min-visible', type=int, default=None, metavar='PIXELS')
    ap.add_argument('-p', '--param', action='append', default=[], metavar='NAME=VALUE')
    ap.add_argument('--json', default=None, help='write the figures here')
    ap.add_argument('--per-frame', action='store_true',
                    help="also write each person-frame's outcome (JSON 'records')")
    args = ap.parse_args(argv)

    import torch
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    from smpl_depth_ros.bagio import iter_depth_bag
    from smpl_depth_ros.config import PipelineConfig
    from smpl_depth_ros.evaluation import TrackScore, write_json
    from smpl_depth_ros import params as P
    from smpl_depth_ros.pipeline import Reconstructor
    from smpl_depth_ros.tools.synth_bag import gt_path
    from smpl_depth_ros.types import InputError

    path = args.gt or gt_path(args.bag)
    if not os.path.exists(path):
        print(f'evaluate_tracks: ground truth {path} not found', file=sys.stderr)
        return 2
    gt = dict(np.load(path, allow_pickle=False))
    if 'person_ids' not in gt:
        print('evaluate_tracks: the bag has one person (write it with synth_bag --persons N)',
              file=sys.stderr)
        return 2
    n_persons = len(gt['person_ids'])
    cfg = PipelineConfig(backend=str(gt['body_model']), device=args.device,
                         max_persons=n_persons)
    try:
        cfg = P.from_params(P.parse_overrides(args.param), base=cfg)[0]
    except P.ParamError as e:
        print(f'evaluate_tracks: error: {e}', file=sys.stderr)
        return 2
    rec = Reconstructor(cfg)
    W, H = int(gt['width']), int(gt['height'])
    min_vis = args.min_visible if args.min_visible is not None else \
        int(round(1500 * W * H / (640 * 480)))
    score = TrackScore(min_vis)
    stamps = list(gt['stamps'])
    n, failures, times = 0, 0, []
    t_all = time.perf_counter()
    for stamp, depth, K in iter_depth_bag(args.bag):
        if args.frames and n >= args.frames:
            break
        i = stamps.index(stamp)
        n += 1
        t0 = time.perf_counter()
        try:
            persons = rec.process(depth, K, stamp_ns=int(stamp)).persons
        except InputError:
            persons, failures = [], failures + 1
        times.append(time.perf_counter() - t0)
        score.add([p.track_id for p in persons],
                  np.array([p.joints[0] for p in persons]).reshape(-1, 3),
                  [p.vertices for p in persons], gt['person_ids'],
                  gt['joints'][i][:, 0], gt['vertices'][i], gt['visible'][i])
    out = dict(bag=os.path.abspath(args.bag), frames=n, persons=n_persons,
               frames_without_person=failures, min_visible_pixels=min_vis,
               max_persons=cfg.max_persons, **score.summary(),
               frame_ms_median=float(np.median(times) * 1e3) if times else float('nan'),
               frame_ms_p95=float(np.percentile(times, 95) * 1e3) if times else float('nan'),
               seconds=round(time.perf_counter() - t_all, 1))
    if args.per_frame:
        out['records'] = score.records
    write_json(out, args.json, 'evaluate_tracks ' + ' '.join(argv if argv is not None
                                                             else sys.argv[1:]))
    return 0


if __name__ == '__main__':
    sys.exit(main())
