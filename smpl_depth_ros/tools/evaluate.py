"""`evaluate`: the full pipeline on a synthetic bag + its `.gt.npz`, paper Table I/II style.

    evaluate BAG [--frames 200] [--tracking] [--json out.json] [--figures DIR]
                 [-p NAME=VALUE ...]   # pipeline parameters, as for process_bag

Rows (paper Table II ablation, same frames):
  gt_joints+fit      fit to the ground-truth 3D joints only (row 1)
  single_unet+fit    single U-Net correspondences (no segmentation prior) + fit
  double_unet+fit    the shipped pipeline (double U-Net + fit)
  gt_corr+fit        ground-truth pixel-to-vertex correspondences + fit
Metrics: pve_mm (paper Eq. 5: all vertices, camera frame, no alignment), pa_pve_mm
(after a similarity Procrustes), mpjpe_mm, miou (14 parts, pixels valid in the depth,
full image resolution: a person 1 m away weighs 9x one 3 m away), miou_net_res (the
same pixels, each frame's weighted by (128 / the true person's box side)^2: every
frame's person counts by its area at the network's input resolution), miou_crop (at the
network's own 128x128 resolution: the ground truth sampled into the crop it saw, on the
pixels its input holds; the upsampled labels are blocky at sensor resolution, where even
the ground truth sent through a crop and back scores ~0.87): all three of the
network's own labels; miou_model / miou_model_net_res: the same for the published
segmentation (segmentation 'model', the default: labels from the fitted mesh),
corr_err_cm_median (canonical T-pose distance between the predicted and the true vertex),
net_ms / fit_ms medians, failures (frames where no person was reconstructed; excluded
from the means and counted), false_persons (persons reported whose pelvis lies over
0.5 m from the true one: with `-p max_persons=3`, boxes taken for people; the person
scored is the one nearest the truth), frames_with_false_persons. Every ablation row also
lists its per-frame PVE, `pve_mm_frames`: [frame index in the bag, mm] (what makes a
mean: the tail of hard frames), and `pve_mm_parts`: the mean error of each part's
vertices (the PVE weighs a part by its vertex count: anny's hands hold 224 of its 1,229
vertices, the head 320).
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from smpl_depth_ros import evaluation as ev
from smpl_depth_ros.evaluation import write_json


def _load_gt(bag: str, gt_path: str | None):
    from smpl_depth_ros.tools.synth_bag import gt_path as default_gt
    path = gt_path or default_gt(bag)
    if not os.path.exists(path):
        raise SystemExit(f'evaluate: ground truth {path} not found (write bags with synth_bag)')
    return dict(np.load(path, allow_pickle=False))


def _row():
    return dict(pve=[], pa=[], mpjpe=[], fit_ms=[], net_ms=[], corr=[], failures=0, idx=[],
                parts=[], false_persons=0, frames_with_false_persons=0,
                conf=np.zeros((15, 15), np.int64), conf_net=np.zeros((15, 15)),
                conf_crop=np.zeros((15, 15), np.int64),
                conf_model=np.zeros((15, 15), np.int64), conf_model_net=np.zeros((15, 15)))


def _summ(r, frames):
    f = lambda v: float(np.mean(v) * 1000) if v else float('nan')  # noqa: E731
    out = dict(pve_mm=f(r['pve']), pa_pve_mm=f(r['pa']), mpjpe_mm=f(r['mpjpe']),
               pve_mm_median=float(np.median(r['pve']) * 1000) if r['pve'] else float('nan'),
               fit_ms_median=float(np.median(r['fit_ms'])) if r['fit_ms'] else float('nan'),
               frames=frames, failures=r['failures'], false_persons=r['false_persons'],
               frames_with_false_persons=r['frames_with_false_persons'],
               # Per-frame PVE (mm) with the frame index in the bag: the tail of the mean.
               pve_mm_frames=[[int(i), round(float(v) * 1000, 2)]
                              for i, v in zip(r['idx'], r['pve'])])
    if r['parts']:
        from smpl_depth_ros.body.parts import PART_NAMES
        m = np.nanmean(np.stack(r['parts']), 0) * 1000
        out['pve_mm_parts'] = {n: round(float(v), 2) for n, v in zip(PART_NAMES[1:], m)}
    if r['net_ms']:
        out['net_ms_median'] = float(np.median(r['net_ms']))
    if r['corr']:
        out['corr_err_cm_median'] = float(np.median(np.concatenate(r['corr'])) * 100)
    if r['conf'].sum():
        out['miou'] = ev.miou(r['conf'])
        out['miou_net_res'] = ev.miou(r['conf_net'])
    if r['conf_crop'].sum():
        out['miou_crop'] = ev.miou(r['conf_crop'])
    if r['conf_model'].sum():
        out['miou_model'] = ev.miou(r['conf_model'])
        out['miou_model_net_res'] = ev.miou(r['conf_model_net'])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='evaluate', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('bag')
    ap.add_argument('--gt', default=None, help='ground truth (default <bag>.gt.npz)')
    ap.add_argument('--frames', type=int, default=0, help='first N frames (0 = all)')
    ap.add_argument('--tracking', action='store_true', help='warm-start across frames')
    ap.add_argument('--no-ablation', action='store_true')
    ap.add_argument('--device', default='cpu')
    ap.add_argument('--weights', default='',
                    help='double U-Net weights to evaluate (default: the shipped ones)')
    ap.add_argument('--flip-tta', action='store_true',
                    help='flip test-time augmentation (PipelineConfig.flip_tta) for both '
                    'networks')
    ap.add_argument('-p', '--param', action='append', default=[], metavar='NAME=VALUE',
                    help="pipeline parameter (repeatable, process_bag's names), e.g. "
                    '-p shape_sample_every=0 -p fit.tangent_weight=1.0')
    ap.add_argument('--json', default=None, help='write the figures here')
    ap.add_argument('--figures', default=None, help='write Fig. 3/4-style PNGs here')
    ap.add_argument('--figure-frames', default='0', help='comma-separated frame indices')
    args = ap.parse_args(argv)

    import torch
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    from smpl_depth_ros.bagio import iter_depth_bag
    from smpl_depth_ros.config import PipelineConfig
    from smpl_depth_ros.fit import Fitter
    from smpl_depth_ros.net.infer import default_weights
    from smpl_depth_ros.net.unet import INPUT_SIZE
    from smpl_depth_ros.pipeline import Reconstructor
    from smpl_depth_ros.types import InputError

    from smpl_depth_ros import params as P

    gt = _load_gt(args.bag, args.gt)
    cfg = PipelineConfig(backend=str(gt['body_model']), device=args.device,
                         tracking=args.tracking, weights_path=args.weights,
                         flip_tta=args.flip_tta, max_persons=1)  # the bag's one person
    try:
        overrides = P.parse_overrides(args.param)
        cfg = P.from_params(overrides, base=cfg)[0]
    except P.ParamError as e:
        print(f'evaluate: error: {e}', file=sys.stderr)
        return 2
    rec = Reconstructor(cfg)
    body = rec.body
    canon = body.canonical_vertices()
    part_of = body.part_labels.cpu().numpy()
    recs = {'double_unet+fit': rec}
    if not args.no_ablation:
        recs['single_unet+fit'] = Reconstructor(
            cfg.with_overrides(weights_path=default_weights(body.name, 'single')), body=body)
    fitter = Fitter(body, cfg.fit)
    rows = {k: _row() for k in (['gt_joints+fit', 'single_unet+fit'] if not args.no_ablation
                                else []) + ['double_unet+fit'] + (
        [] if args.no_ablation else ['gt_corr+fit'])}
    stamps = list(gt['stamps'])
    fig_frames = {int(i) for i in args.figure_frames.split(',') if i != ''}
    prev_gt = {}
    n = 0
    for stamp, depth, K in iter_depth_bag(args.bag):
        if args.frames and n >= args.frames:
            break
        i = stamps.index(stamp)
        V, J = gt['vertices'][i], gt['joints'][i]
        glab, gvid = gt['labels'][i], gt['vertex_ids'][i]
        valid = depth > 0
        n += 1
        # The person's box side in pixels (the truth's, not a prediction's: a tiny wrong
        # candidate must not weigh the frame's every missed pixel 100x).
        gr, gc = np.nonzero(glab > 0)
        side = max(np.ptp(gr) + 1, np.ptp(gc) + 1) if len(gr) else INPUT_SIZE
        net_weight = (INPUT_SIZE / side) ** 2
        for name, r in recs.items():
            row = rows[name]
            try:
                res = r.process(depth, K, stamp_ns=int(stamp))
            except InputError:
                row['failures'] += 1
                continue
            off = [float(np.linalg.norm(q.joints[0] - J[0])) for q in res.persons]
            p = res.persons[int(np.argmin(off))]  # the bag's person (max_persons > 1)
            false = sum(o > 0.5 for o in off)
            row['false_persons'] += false
            row['frames_with_false_persons'] += bool(false)
            row['idx'].append(n - 1)
            row['pve'].append(ev.pve(p.vertices, V))
            row['parts'].append(ev.part_errors(p.vertices, V, part_of))
            row['pa'].append(ev.pa_pve(p.vertices, V))
            row['mpjpe'].append(ev.mpjpe(p.joints, J))
            row['fit_ms'].append(res.timings_ms['fit'])
            row['net_ms'].append(res.timings_ms['network'])
            gt_lab = np.where(valid, glab, 0)
            pred_lab = np.where(valid, res.network_labels, 0)  # the network's own
            row['conf'] += ev.confusion(pred_lab, gt_lab)
            row['conf_net'] += ev.confusion(pred_lab, gt_lab, weight=net_weight)
            for q in res.persons:  # at the network's own resolution
                row['conf_crop'] += ev.crop_confusion(q.crop, q.crop_labels, depth, glab)
            if res.labels is not res.network_labels:  # segmentation 'model': published
                model_lab = np.where(valid, res.labels, 0)
                row['conf_model'] += ev.confusion(model_lab, gt_lab)
                row['conf_model_net'] += ev.confusion(model_lab, gt_lab, weight=net_weight)
            g = gvid[p.pixels[:, 0], p.pixels[:, 1]]
            ok = g >= 0
            row['corr'].append(np.linalg.norm(canon[p.vertex_ids[ok]] - canon[g[ok]], axis=1))
            if name == 'double_unet+fit' and (n - 1) in fig_frames and args.figures:
                from smpl_depth_ros.tools.figures import save_figures
                save_figures(args.figures, n - 1, body, depth, K, res, V, canon)
        if not args.no_ablation:
            # GT correspondences + fit.
            m = (gvid >= 0) & valid
            rr, cc = np.nonzero(m)
            z = depth[rr, cc]
            pts = np.stack([(cc - K[0, 2]) * z / K[0, 0], (rr - K[1, 2]) * z / K[1, 1], z], 1)
            init = prev_gt.get('corr') if args.tracking else None
            fr = fitter.fit(pts.astype(np.float32), gvid[m], init=init)
            prev_gt['corr'] = fr.params
            row = rows['gt_corr+fit']
            row['idx'].append(n - 1)
            row['pve'].append(ev.pve(fr.vertices, V))
            row['parts'].append(ev.part_errors(fr.vertices, V, part_of))
            row['pa'].append(ev.pa_pve(fr.vertices, V))
            row['mpjpe'].append(ev.mpjpe(fr.joints, J))
            row['fit_ms'].append(fr.time_ms)
            init = prev_gt.get('joints') if args.tracking else None
            fj = fitter.fit_joints(J, init=init)
            prev_gt['joints'] = fj.params
            row = rows['gt_joints+fit']
            row['idx'].append(n - 1)
            row['pve'].append(ev.pve(fj.vertices, V))
            row['parts'].append(ev.part_errors(fj.vertices, V, part_of))
            row['pa'].append(ev.pa_pve(fj.vertices, V))
            row['mpjpe'].append(ev.mpjpe(fj.joints, J))
            row['fit_ms'].append(fj.time_ms)
        if sys.stderr.isatty():
            d = rows['double_unet+fit']['pve']
            print(f'\r{n} frames, double pve {np.mean(d) * 1000 if d else float("nan"):.1f} mm',
                  end='', file=sys.stderr)
    if sys.stderr.isatty():
        print(file=sys.stderr)
    table = {k: _summ(v, n) for k, v in rows.items()}
    main_row = table['double_unet+fit']
    main_summary = {k: v for k, v in main_row.items() if k != 'pve_mm_frames'}
    out = dict(main_summary, bag=args.bag, tracking=cfg.tracking, device=args.device,
               weights=args.weights or 'shipped', flip_tta=cfg.flip_tta,
               params=overrides,
               body_model=body.name, ablation=table)
    print(f'{"method":18s} {"PVE mm":>8s} {"PVE p50":>8s} {"PA-PVE":>8s} {"MPJPE":>8s} '
          f'{"mIoU":>6s} '
          f'{"mIoU@net":>8s} {"mIoU@128":>8s} {"mIoU fit":>8s} '
          f'{"corr cm":>8s} {"net ms":>7s} {"fit ms":>7s} {"fail":>5s}')
    for k, v in table.items():
        print(f'{k:18s} {v["pve_mm"]:8.1f} {v["pve_mm_median"]:8.1f} {v["pa_pve_mm"]:8.1f} '
              f'{v["mpjpe_mm"]:8.1f} '
              f'{v.get("miou", float("nan")):6.3f} {v.get("miou_net_res", float("nan")):8.3f} '
              f'{v.get("miou_crop", float("nan")):8.3f} '
              f'{v.get("miou_model", float("nan")):8.3f} '
              f'{v.get("corr_err_cm_median", float("nan")):8.2f} '
              f'{v.get("net_ms_median", float("nan")):7.1f} {v["fit_ms_median"]:7.1f} '
              f'{v["failures"]:5d}')
    write_json(out, args.json, ' '.join(['evaluate', *(sys.argv[1:] if argv is None else argv)]))
    return 0


if __name__ == '__main__':
    sys.exit(main())
