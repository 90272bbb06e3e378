"""`sweep`: accuracy and recall per depth sensor and distance (sensor sweep protocol).

    sweep --json results/sweep_test.json --plot results/sweep_test.png \\
          [--sensors all] [--bins 1.0 5.0 0.5] [--frames 10] [--seed 101] \\
          [--poses templates|broad|mocap] [--lens azure_kinect] [--strength S] \\
          [--noise FIELD=VALUE ...] [-p NAME=VALUE ...]

For every sensor preset (synth.sensors: its camera and noise model) and every depth bin,
the same `--frames` subjects (shape, pose, yaw: frame i draws from the generator seeded
(seed, i), so only the placement differs between sensors and bins) are rendered with a
random room, corrupted by the sensor's noise and reconstructed, single frame, with one
Reconstructor per sensor (its `sensor` parameter 'auto' unless `-p sensor=...`: it
learns the noise from the frames it sees, as a live node would). Per sensor and bin:
the share of frames reconstructed, PVE mean / median (paper Eq. 5, no alignment), the
symmetric surface distance (`evaluation.surface_distance`: topology-free, both surfaces
sampled by area, median and mean), and the mIoU of the published segmentation; also the
sensor's measured noise model; with `--poses mocap`, each frame's PVE per motion
(climbing, box lifting) too, summarised per sensor. Bins beyond a sensor's range (kept
0.3 m inside it) are left out. JSON out, and a PNG with PVE and recall against distance,
one line per sensor.
Validation and test sweeps differ only by `--seed`. `--lens` makes every frame the image
of a lens-distorted camera, as its driver publishes it (`sweep_frames`). `--strength`
scales every noise model; `--noise` sets a field of the presets' noise models (those that
have it: `synth.sensors.StereoParams`, `TofParams`, `noise.NoiseParams`), e.g. `--noise
white_share=1 --noise subpixel_sigma_px=0.15`: a stereo unit noisier than the preset,
its error per pixel (an independent simulator's formula, sigma = z^2 sigma_d / (f b)).
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from smpl_depth_ros import evaluation as ev


def sweep_frames(body, sampler, sensor, lo, hi, n, seed, strength=1.0, lens=None):
    """The sweep's `n` frames of one sensor and depth bin [lo, hi] (frame i from the
    generator seeded (seed, i)): synth.dataset.make_frame dicts.

    With `lens` (a synth.sensors.LENSES name) each frame is rendered on the pinhole image
    the lens's `rectify.Rectifier` makes, with the sensor's noise, then made the lens's
    own image (its depth and labels; K stays the sensor's), and carries the
    `rectify.Lens` a driver's camera_info would give (key 'lens')."""
    from dataclasses import replace

    from smpl_depth_ros.synth import dataset
    cam, rect, lens_of = sensor.camera, None, None
    if lens:
        from smpl_depth_ros.rectify import Lens, Rectifier
        from smpl_depth_ros.synth.sensors import LENSES
        model, D = LENSES[lens]
        rect = Rectifier.for_camera(cam.K, model, D, (cam.width, cam.height))
        lens_of = Lens(model, np.asarray(D), cam.K)
        cam = replace(cam, width=rect.shape[1], height=rect.shape[0], cx=rect.K[0, 2],
                      cy=rect.K[1, 2], name=f'{cam.name}_pinhole')
        sensor = sensor.with_camera(cam)
    p = dataset.SynthParams(sensor=sensor, strength=strength,
                            chairs=sampler.mode == 'seated')
    p = replace(p, depth_range=(lo, hi))
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        fr = dataset.make_frame(body, sampler, rng, cam, params=p)
        if rect is not None:
            fr.update(depth=rect.to_raw(fr['depth']), labels=rect.to_raw(fr['labels']),
                      K=lens_of.P, lens=lens_of)
        yield fr


def run_sweep(sensors, bins, frames, seed, poses, overrides, strength=1.0, progress=None,
              lens=None, noise=None):
    """The sweep's rows: one dict per (sensor, bin) with its metrics (see module doc);
    `lens`: see `sweep_frames`; `noise`: noise-model fields set on every preset that has
    them (`Sensor.with_noise`)."""
    from smpl_depth_ros.body import load_body_model
    from smpl_depth_ros.config import PipelineConfig
    from smpl_depth_ros.params import from_params
    from smpl_depth_ros.pipeline import Reconstructor
    from smpl_depth_ros.synth.poses import PoseSampler
    from smpl_depth_ros.synth.sensors import SENSORS
    from smpl_depth_ros.types import InputError

    base = PipelineConfig(tracking=False, max_persons=1)  # each frame's one person
    cfg = from_params(overrides, base=base)[0]
    body = load_body_model(cfg.backend, cfg.model_path or None)
    sampler = PoseSampler(body, mode=poses)
    faces = body.faces_numpy()
    rows = []
    for name in sensors:
        sensor = SENSORS[name].with_noise(**(noise or {}))
        rec = Reconstructor(cfg, body=body)
        cam = sensor.camera
        for lo, hi in bins:
            a, b = max(lo, cam.min_range + 0.3), min(hi, cam.max_range - 0.3)
            if b < a + 0.05:
                continue
            pve, sd_med, sd_mean, fails = [], [], [], []
            motions = []  # mode 'mocap': (motion, PVE or None) per frame
            conf = np.zeros((15, 15), np.int64)
            t0 = time.perf_counter()
            for k, fr in enumerate(sweep_frames(body, sampler, sensor, a, b, frames, seed,
                                           strength, lens)):
                try:
                    res = rec.process(fr['depth'], fr['K'], lens=fr.get('lens'))
                except InputError as e:
                    fails.append(e.reason)
                    conf += ev.confusion(np.zeros_like(fr['labels']), fr['labels'])
                    motions.append((sampler.last_motion, None))
                    continue
                p = res.persons[0]
                pve.append(ev.pve(p.vertices, fr['vertices']))
                motions.append((sampler.last_motion, pve[-1]))
                m, mean = ev.surface_distance(p.vertices, faces, fr['vertices'], faces,
                                              n=2000, seed=k)
                sd_med.append(m)
                sd_mean.append(mean)
                valid = fr['depth'] > 0
                conf += ev.confusion(np.where(valid, res.labels, 0),
                                     np.where(valid, fr['labels'], 0))
            mm = lambda v, f: round(float(f(v)) * 1e3, 1) if v else None  # noqa: E731
            row = dict(sensor=name + (f'+{lens}' if lens else ''), kind=sensor.kind,
                       bin=[lo, hi], depth=[round(a, 2), round(b, 2)],
                       frames=frames, reconstructed=round(len(pve) / frames, 3),
                       pve_mm=mm(pve, np.mean), pve_mm_median=mm(pve, np.median),
                       surface_mm_median=mm(sd_med, np.median),
                       surface_mm_mean=mm(sd_mean, np.mean),
                       miou=round(ev.miou(conf), 3), failures=sorted(set(fails)),
                       noise=rec.noise.as_dict(),
                       seconds=round(time.perf_counter() - t0, 1))
            if poses == 'mocap':
                # each motion's frames: PVE (mm), None where nobody was reconstructed
                row['motions'] = {m: [None if v is None else round(v * 1e3, 1)
                                      for k, v in motions if k == m]
                                  for m in sorted({k for k, _ in motions})}
            rows.append(row)
            if progress:
                progress(row)
    return rows


def summarise(rows) -> dict:
    """Per sensor over all its bins: mean reconstructed share, frame-weighted PVE mean,
    worst bin, and the targets' verdicts (>= 98 % reconstructed in every bin from 1.0 to
    4.5 m; PVE mean <= 35 mm over 1.0-4.5 m; no bin above 50 mm)."""
    out = {}
    for name in dict.fromkeys(r['sensor'] for r in rows):
        rs = [r for r in rows if r['sensor'] == name and r['bin'][1] <= 4.5 + 1e-9]
        if not rs:
            continue
        n_ok = [r['reconstructed'] * r['frames'] for r in rs]
        pv = [(r['pve_mm'], k) for r, k in zip(rs, n_ok) if r['pve_mm'] is not None]
        mean = (sum(p * k for p, k in pv) / sum(k for _, k in pv)) if pv else None
        worst = max((p for p, _ in pv), default=None)
        out[name] = dict(
            bins=len(rs), reconstructed_min=min(r['reconstructed'] for r in rs),
            reconstructed_mean=round(float(np.mean([r['reconstructed'] for r in rs])), 3),
            pve_mm=None if mean is None else round(mean, 1), pve_mm_worst_bin=worst,
            surface_mm_median=round(float(np.median([r['surface_mm_median'] for r in rs
                                                     if r['surface_mm_median'] is not None]
                                                    or [np.nan])), 1),
            recall_target_met=all(r['reconstructed'] >= 0.98 for r in rs),
            pve_target_met=mean is not None and mean <= 35 and worst <= 50)
        if any('motions' in r for r in rs):
            # per motion (mode 'mocap'): share reconstructed and PVE mean over its frames
            out[name]['motions'] = {}
            for m in sorted({m for r in rs for m in r.get('motions', {})}):
                v = [x for r in rs for x in r.get('motions', {}).get(m, [])]
                ok = [x for x in v if x is not None]
                out[name]['motions'][m] = dict(
                    frames=len(v), reconstructed=round(len(ok) / len(v), 3),
                    pve_mm=round(float(np.mean(ok)), 1) if ok else None,
                    pve_mm_median=round(float(np.median(ok)), 1) if ok else None)
    return out


def plot(rows, path: str, title: str = '') -> None:
    """PVE (mm) and share reconstructed against distance, one line per sensor (PIL)."""
    from PIL import Image, ImageDraw
    names = list(dict.fromkeys(r['sensor'] for r in rows))
    palette = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40),
               (148, 103, 189), (140, 86, 75), (227, 119, 194), (127, 127, 127),
               (188, 189, 34), (23, 190, 207), (0, 0, 0), (120, 200, 120)]
    W, H, pad, leg = 1100, 420, 50, 210
    img = Image.new('RGB', (W, H), 'white')
    d = ImageDraw.Draw(img)
    zs = [0.5 * (r['bin'][0] + r['bin'][1]) for r in rows] or [1, 5]
    z0, z1 = min(zs) - 0.25, max(zs) + 0.25
    pw = (W - leg - 3 * pad) // 2
    pvmax = max([r['pve_mm'] for r in rows if r['pve_mm'] is not None] + [60.0])
    panels = [('PVE mean (mm)', lambda r: r['pve_mm'], 0.0, min(pvmax * 1.05, 300.0)),
              ('share reconstructed', lambda r: r['reconstructed'], 0.0, 1.0)]
    for pi, (label, get, lo, hi) in enumerate(panels):
        x0 = pad + pi * (pw + pad)
        y0, y1 = pad, H - pad
        d.rectangle([x0, y0, x0 + pw, y1], outline='black')
        d.text((x0, 10), label + (f' - {title}' if title and pi == 0 else ''), fill='black')
        for t in range(5):
            v = lo + (hi - lo) * t / 4
            y = y1 - (y1 - y0) * t / 4
            d.line([x0 - 4, y, x0, y], fill='black')
            d.text((x0 - 44, y - 6), f'{v:.0f}' if hi > 2 else f'{v:.2f}', fill='black')
        for z in np.arange(np.ceil(z0), z1, 1.0):
            x = x0 + pw * (z - z0) / (z1 - z0)
            d.line([x, y1, x, y1 + 4], fill='black')
            d.text((x - 8, y1 + 8), f'{z:.0f} m', fill='black')
        if pi == 0:
            for ref in (35.0, 50.0):
                if ref < hi:
                    y = y1 - (y1 - y0) * (ref - lo) / (hi - lo)
                    d.line([x0, y, x0 + pw, y], fill=(200, 200, 200))
        else:
            y = y1 - (y1 - y0) * (0.98 - lo) / (hi - lo)
            d.line([x0, y, x0 + pw, y], fill=(200, 200, 200))
        for ni, name in enumerate(names):
            col = palette[ni % len(palette)]
            pts = []
            for r in rows:
                if r['sensor'] != name or get(r) is None:
                    continue
                z = 0.5 * (r['bin'][0] + r['bin'][1])
                v = min(max(get(r), lo), hi)
                pts.append((x0 + pw * (z - z0) / (z1 - z0), y1 - (y1 - y0) * (v - lo) / (hi - lo)))
            if len(pts) > 1:
                d.line(pts, fill=col, width=2)
            for x, y in pts:
                d.ellipse([x - 3, y - 3, x + 3, y + 3], fill=col)
    for ni, name in enumerate(names):
        col = palette[ni % len(palette)]
        y = pad + 18 * ni
        d.line([W - leg, y + 6, W - leg + 20, y + 6], fill=col, width=3)
        d.text((W - leg + 26, y), name, fill='black')
    img.save(path)


def build_parser() -> argparse.ArgumentParser:
    from smpl_depth_ros.synth.poses import MODES
    ap = argparse.ArgumentParser(prog='sweep', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--sensors', default='all',
                    help="comma-separated synth.sensors presets, or 'all'")
    ap.add_argument('--bins', type=float, nargs=3, default=[1.0, 5.0, 0.5],
                    metavar=('FROM', 'TO', 'STEP'), help='root depth bins (metres)')
    ap.add_argument('--frames', type=int, default=10, help='subjects per sensor and bin')
    ap.add_argument('--seed', type=int, default=101)
    ap.add_argument('--poses', default='templates', choices=MODES)
    ap.add_argument('--strength', type=float, default=1.0, help='noise strength')
    ap.add_argument('--lens', default=None, help="a synth.sensors.LENSES name: the frames "
                    "are that lens's own (distorted) images, with its camera_info lens")
    ap.add_argument('--noise', action='append', default=[], metavar='FIELD=VALUE',
                    help='set a field of the presets\' noise models (those that have it), '
                    'e.g. white_share=1')
    ap.add_argument('--json', default=None)
    ap.add_argument('--plot', default=None, help='PNG of PVE and recall against distance')
    ap.add_argument('-p', '--param', action='append', default=[], metavar='NAME=VALUE',
                    help='pipeline parameter (as for process_bag)')
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from smpl_depth_ros.params import ParamError, parse_overrides
    from smpl_depth_ros.synth.sensors import LENSES, SENSORS
    names = list(SENSORS) if args.sensors == 'all' else [
        n for n in args.sensors.split(',') if n]
    bad = [n for n in names if n not in SENSORS]
    if bad or not names:
        print(f'sweep: unknown sensors {bad}; presets: {sorted(SENSORS)}', file=sys.stderr)
        return 2
    if args.lens and args.lens not in LENSES:
        print(f'sweep: unknown lens {args.lens!r}; presets: {sorted(LENSES)}',
              file=sys.stderr)
        return 2
    noise = {}
    for item in args.noise:
        key, sep, value = item.partition('=')
        try:
            noise[key] = int(value) if value.lstrip('-').isdigit() else float(value)
        except ValueError:
            sep = ''
        if not sep or not any(hasattr(SENSORS[n].params, key) for n in names):
            print(f'sweep: --noise {item!r}: FIELD=number, a field of the noise model of '
                  'at least one sensor swept', file=sys.stderr)
            return 2
    f, t, s = args.bins
    if not (0 < f < t and s > 0) or args.frames < 1:
        print('sweep: --bins needs 0 < FROM < TO and STEP > 0; --frames >= 1',
              file=sys.stderr)
        return 2
    edges = np.round(np.arange(f, t + 1e-9, s), 3)
    bins = [(float(a), float(b)) for a, b in zip(edges[:-1], edges[1:])]
    try:
        overrides = parse_overrides(args.param)
        t0 = time.perf_counter()
        rows = run_sweep(names, bins, args.frames, args.seed, args.poses, overrides,
                         args.strength, lens=args.lens, noise=noise,
                         progress=lambda r: print(
                             f"{r['sensor']:26s} {r['depth'][0]:.1f}-{r['depth'][1]:.1f} m "
                             f"rec {r['reconstructed']:.2f} pve {r['pve_mm']} surf "
                             f"{r['surface_mm_median']} miou {r['miou']}",
                             file=sys.stderr, flush=True))
    except ParamError as e:
        print(f'sweep: {e}', file=sys.stderr)
        return 2
    out = dict(summary=summarise(rows), rows=rows, seed=args.seed, poses=args.poses,
               frames=args.frames, strength=args.strength, lens=args.lens, noise=noise,
               params=overrides,
               seconds=round(time.perf_counter() - t0, 1),
               date=time.strftime('%Y-%m-%d'))
    if args.plot:
        plot(rows, args.plot, f'{args.poses} poses, seed {args.seed}')
    ev.write_json(out, args.json, command='sweep ' + ' '.join(
        argv if argv is not None else sys.argv[1:]))
    return 0


if __name__ == '__main__':
    sys.exit(main())
