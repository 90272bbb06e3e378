"""`train_correspondence`: train the (double or single) U-Net on synthetic depth.

    train_correspondence --out smpl_depth_ros/data/corr_anny_double.pt --steps 6000 \\
        --batch 32 --workers 2 --seed 7

Data are rendered on the fly (net.data) in DataLoader workers, each with its own seeded
generator; validation uses a fixed set rendered with another seed. Loss = cross-entropy
(15 classes) + lambda * L2 on the canonical coordinates of body pixels (paper III-B-b);
AdamW with warm-up + cosine decay instead of the paper's RMSprop (faster, stable);
with --max-minutes the schedule runs on wall time, so a time budget always ends annealed.
Checkpoints every --ckpt-every steps (resume with --resume), a progress bar, a
validation-curve PNG and a JSON log next to the weights. Uses CUDA when available;
`--precision bfloat16` runs the forward pass under autocast (the CPU's time halves where
it has bfloat16 matrix units).
The shipped weights are saved in float16 (a few MB).
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import sys
import time
from dataclasses import replace

import numpy as np
import torch
import torch.nn.functional as F

from smpl_depth_ros.body.parts import NUM_CLASSES


def class_weights(labels: torch.Tensor, power: float) -> torch.Tensor | None:
    """Cross-entropy class weights from a label set (the validation set's: fixed and
    seeded): each body part (freq_part / freq_largest_part)^-power, the background 1 (the
    torso's weight); None for power 0. Small parts (hands, forearms) have the lowest IoU
    and a tenth of the torso's pixels; the background keeps a full weight so that boxes
    and walls are not traded for body. (cross_entropy normalises by the weights' sum.)"""
    if not power:
        return None
    freq = torch.bincount(labels.flatten(), minlength=NUM_CLASSES).double().clamp(min=1)
    w = (freq / freq[1:].max()) ** -power
    w[0] = 1.0
    return w.float()


class WeightAverage:
    """Exponential moving average of a network's weights and BatchNorm statistics
    (--ema DECAY): the averaged weights are what is validated and saved. Fine-tuning a
    converged network on a small CPU budget mostly adds step noise; the average keeps
    its gains and smooths the noise away."""

    def __init__(self, net: torch.nn.Module, decay: float):
        self.decay = float(decay)
        self.net = copy.deepcopy(net).eval()
        for p in self.net.parameters():
            p.requires_grad_(False)

    @torch.no_grad()
    def update(self, net: torch.nn.Module) -> None:
        for a, b in zip(self.net.state_dict().values(), net.state_dict().values()):
            if a.is_floating_point():
                a.mul_(self.decay).add_(b.detach(), alpha=1 - self.decay)
            else:
                a.copy_(b)


def losses(logits, coords_pred, labels, coords, cmask, coord_weight: float,
           weight: torch.Tensor | None = None):
    ce = F.cross_entropy(logits, labels, weight=weight)
    m = cmask.unsqueeze(1).float()
    l2 = (((coords_pred - coords) ** 2) * m).sum() / m.sum().clamp(min=1) / 3
    return ce + coord_weight * l2, ce, l2


@torch.no_grad()
def evaluate_batch(net, x, labels, coords, cmask, bs=64):
    """mIoU over the 14 parts and mean coordinate error on the validation set."""
    net.eval()
    inter = torch.zeros(NUM_CLASSES)
    union = torch.zeros(NUM_CLASSES)
    cerr, cnt, ce_sum = 0.0, 0, 0.0
    dev = next(net.parameters()).device
    for i in range(0, len(x), bs):
        xb = x[i:i + bs].to(dev)
        lb, cb, mb = labels[i:i + bs].to(dev), coords[i:i + bs].to(dev), cmask[i:i + bs].to(dev)
        logits, cp = net(xb)
        ce_sum += float(F.cross_entropy(logits, lb, reduction='sum')) / lb[0].numel()
        pred = logits.argmax(1)
        for c in range(NUM_CLASSES):
            p, t = pred == c, lb == c
            inter[c] += float((p & t).sum())
            union[c] += float((p | t).sum())
        d = ((cp - cb) ** 2).sum(1).sqrt()[mb]
        cerr += float(d.sum())
        cnt += int(mb.sum())
    net.train()
    iou = inter[1:] / union[1:].clamp(min=1)
    return dict(miou=float(iou.mean()), coord_err=cerr / max(cnt, 1), ce=ce_sum / len(x))


def plot_curves(log, path):
    """Validation curves as a PNG, drawn with PIL (no matplotlib dependency)."""
    from PIL import Image, ImageDraw
    W, H, pad = 640, 360, 40
    img = Image.new('RGB', (W, H), 'white')
    d = ImageDraw.Draw(img)
    if not log:
        img.save(path)
        return
    steps = [e['step'] for e in log]
    smax = max(steps) or 1
    series = [('miou', (0, 120, 0)), ('coord_err', (200, 0, 0)), ('train_loss', (0, 0, 200))]
    for name, col in series:
        vals = [e.get(name) for e in log if e.get(name) is not None]
        if len(vals) < 1:
            continue
        vmax = max(max(vals), 1e-6)
        pts = [(pad + (W - 2 * pad) * s / smax, H - pad - (H - 2 * pad) * v / vmax)
               for s, v in zip(steps, vals)]
        if len(pts) > 1:
            d.line(pts, fill=col, width=2)
        d.text((pts[-1][0] - 120, pts[-1][1] - 12), f'{name} {vals[-1]:.3f}', fill=col)
    d.rectangle([pad, pad, W - pad, H - pad], outline='black')
    d.text((pad, 10), f'validation (step 0..{smax}); each series scaled to its max', fill='black')
    img.save(path)


def load_checkpoint(path, device='cpu') -> dict:
    """A training checkpoint, loaded without running code from it (weights_only=True;
    numpy float scalars, which earlier checkpoints hold in their optimizer state, are
    the only types allowed beyond torch's own)."""
    safe = [np.dtype, type(np.dtype(np.float64)), np.float64]
    scalar = getattr(getattr(np, '_core', np.core).multiarray, 'scalar', None)
    if scalar is not None:
        safe.append(scalar)
    with torch.serialization.safe_globals(safe):
        return torch.load(path, map_location=device, weights_only=True)


def save_weights(net, path, meta):
    sd = {k: (v.detach().cpu().half() if v.is_floating_point() else v.detach().cpu())
          for k, v in net.state_dict().items()}
    torch.save({'state_dict': sd, 'meta': meta}, path)


def main(argv=None):
    from smpl_depth_ros.synth.poses import MODES
    ap = argparse.ArgumentParser(prog='train_correspondence', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--out', required=True, help='weights file (.pt)')
    ap.add_argument('--kind', default='double', choices=['double', 'single'])
    ap.add_argument('--backend', default='anny', choices=['anny', 'smpl'])
    ap.add_argument('--model-path', default='')
    ap.add_argument('--steps', type=int, default=6000)
    ap.add_argument('--batch', type=int, default=32)
    ap.add_argument('--lr', type=float, default=3e-3, help='peak learning rate')
    ap.add_argument('--also-lr', type=float, nargs='*', default=[], metavar='LR',
                    help='also train one network per LR on the same samples (rendering, not '
                         'the network, bounds a GPU run), each saved as <out stem>.lr<LR>.pt '
                         'with its own log, its checkpoint <ckpt>.lr<LR>')
    ap.add_argument('--coord-weight', type=float, default=20.0)
    ap.add_argument('--class-balance', type=float, default=0.0,
                    help='weight each body part\'s cross-entropy by (its pixel share / the '
                         'largest part\'s)^-POWER, the background as the largest part '
                         '(0: plain cross-entropy; the shipped stage 4 used 0.4)')
    ap.add_argument('--head-turn', type=float, default=0.0, metavar='DEG',
                    help='also turn the heads of the training and validation bodies '
                         '(PoseSampler head_turn_deg; default 0: the pose templates only)')
    ap.add_argument('--truncate', type=float, default=None, metavar='P',
                    help='probability that a training body leaving the sensor image is '
                         'cropped as the sensor sees it (SampleConfig.truncate, default '
                         '0.5; the validation set keeps the default)')
    ap.add_argument('--poses', default='templates', choices=MODES,
                    help='training and validation poses (PoseSampler mode; default the '
                         'activity templates)')
    ap.add_argument('--sensors', default='', metavar='NAMES',
                    help="comma-separated synth.sensors presets drawn per sample, or 'all' "
                         "(default: Kinect v1 noise on every camera preset)")
    ap.add_argument('--rehearse', type=float, default=0.0, metavar='P',
                    help='with --sensors: share of samples drawn from the original protocol '
                         '(template poses, Kinect v1 noise) so a fine-tune keeps what the '
                         'initial weights learned (SampleConfig.rehearse; default 0)')
    ap.add_argument('--chairs', type=float, default=0.0, metavar='P',
                    help='share of samples (training and validation) that are a person '
                         'seated on a chair (SampleConfig.chairs; default 0)')
    ap.add_argument('--workers', type=int, default=max(1, (os.cpu_count() or 2) - 1))
    ap.add_argument('--device', default='auto', choices=['auto', 'cpu', 'cuda'])
    ap.add_argument('--precision', default='float32', choices=['float32', 'bfloat16'],
                    help='bfloat16: the forward pass under autocast (loss, weights, '
                         'optimiser and validation in float32); about twice as fast on a '
                         'CPU with bfloat16 matrix units')
    ap.add_argument('--seed', type=int, default=7)
    ap.add_argument('--val-seed', type=int, default=1000)
    ap.add_argument('--val-size', type=int, default=256)
    ap.add_argument('--val-every', type=int, default=250)
    ap.add_argument('--ckpt-every', type=int, default=500)
    ap.add_argument('--ckpt', default='', help='checkpoint path (default <out>.ckpt)')
    ap.add_argument('--resume', action='store_true', help='continue from the checkpoint')
    ap.add_argument('--init', default='',
                    help='start from these weights (fine-tuning; e.g. the shipped ones)')
    ap.add_argument('--ema', type=float, default=0.0, metavar='DECAY',
                    help='validate and save an exponential moving average of the weights '
                         '(e.g. 0.998; 0: the weights as trained)')
    ap.add_argument('--max-minutes', type=float, default=0.0,
                    help='stop (and save) after this many minutes (0: no limit)')
    args = ap.parse_args(argv)

    from smpl_depth_ros.body import load_body_model
    from smpl_depth_ros.net.data import SampleConfig, SyntheticDataset, make_fixed_set
    from smpl_depth_ros.net.unet import INPUT_SIZE

    device = torch.device('cuda' if args.device == 'auto' and torch.cuda.is_available()
                          else ('cpu' if args.device == 'auto' else args.device))
    if (args.precision == 'bfloat16' and device.type == 'cuda'
            and not torch.cuda.is_bf16_supported()):
        ap.error('--precision bfloat16: this GPU has no bfloat16; use float32')
    torch.manual_seed(args.seed)
    init_sd = None
    if args.init:
        sd = torch.load(args.init, map_location='cpu', weights_only=True)['state_dict']
        init_sd = {k: v.float() if v.is_floating_point() else v for k, v in sd.items()}
    stem, ext = os.path.splitext(args.out)
    ckpt = args.ckpt or args.out + '.ckpt'
    runs = [_Run(args, args.lr, args.out, ckpt, device, init_sd)]
    for lr in args.also_lr:
        runs.append(_Run(args, lr, f'{stem}.lr{lr:g}{ext}', f'{ckpt}.lr{lr:g}', device,
                         init_sd))
    if args.resume:
        for r in runs:
            r.resume(device)

    def body_factory():
        return load_body_model(args.backend, args.model_path or None)

    body = body_factory()
    t_val = time.time()
    from smpl_depth_ros.synth.sensors import SENSORS
    sensors = (tuple(SENSORS) if args.sensors == 'all' else
               tuple(n for n in args.sensors.split(',') if n))
    unknown = [n for n in sensors if n not in SENSORS]
    if unknown:
        ap.error(f'unknown sensors {unknown}; presets: {sorted(SENSORS)}')
    scfg = SampleConfig(head_turn_deg=args.head_turn, poses=args.poses, sensors=sensors,
                        rehearse=args.rehearse, chairs=args.chairs)
    val = make_fixed_set(body, args.val_size, args.val_seed, scfg)
    print(f'validation set: {args.val_size} samples in {time.time() - t_val:.1f} s',
          file=sys.stderr)
    cw = class_weights(val[1], args.class_balance)
    cw = None if cw is None else cw.to(device)
    tcfg = scfg if args.truncate is None else replace(scfg, truncate=args.truncate)
    step = runs[0].step
    ds = SyntheticDataset(body_factory, seed=args.seed * 1000 + step, cfg=tcfg)
    dl = torch.utils.data.DataLoader(ds, batch_size=args.batch, num_workers=args.workers,
                                     pin_memory=device.type == 'cuda',
                                     persistent_workers=args.workers > 0,
                                     prefetch_factor=4 if args.workers > 0 else None)
    meta = dict(kind=args.kind, backend=args.backend, input_size=INPUT_SIZE,
                body_vertices=int(body.num_vertices), seed=args.seed, val_seed=args.val_seed,
                truncate=tcfg.truncate, poses=tcfg.poses, sensors=list(tcfg.sensors),
                rehearse=tcfg.rehearse, head_turn_deg=tcfg.head_turn_deg,
                chairs=tcfg.chairs,
                command='train_correspondence ' + ' '.join(argv if argv is not None
                                                            else sys.argv[1:]))
    try:
        from tqdm import tqdm
        bar = tqdm(total=args.steps, initial=step, disable=not sys.stderr.isatty())
    except ImportError:  # pragma: no cover
        bar = None
    t0 = time.time()

    def progress(s):
        # Fraction of the run done: by steps, or by wall time when --max-minutes is set.
        frac = s / args.steps
        if args.max_minutes:
            frac = max(frac, (time.time() - t0) / (60 * args.max_minutes))
        return min(frac, 1.0)

    it = iter(dl)
    while step < args.steps:
        x, labels, coords, cmask = next(it)
        x, labels = x.to(device, non_blocking=True), labels.to(device, non_blocking=True)
        coords, cmask = coords.to(device, non_blocking=True), cmask.to(device, non_blocking=True)
        frac = progress(step)
        for r in runs:
            r.train_step(x, labels, coords, cmask, cw, frac)
        step += 1
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f'{runs[0].run_loss:.3f}')
        last = progress(step) >= 1.0
        for r in runs:
            r.step = step
            if step % args.val_every == 0 or last:
                ev = r.validate(val, minutes=(time.time() - t0) / 60)
                if bar is None or not sys.stderr.isatty():
                    print(json.dumps(dict(ev, lr=r.lr)), file=sys.stderr, flush=True)
            if step % args.ckpt_every == 0 or last:
                r.save(meta, checkpoint=True)
        if last:
            break
    if bar is not None:
        bar.close()
    for r in runs:
        r.save(meta, checkpoint=False)
        print(json.dumps(dict(out=r.out, lr=r.lr, steps=step, minutes=(time.time() - t0) / 60,
                              val=r.log[-1] if r.log else None)))


class _Run:
    """One network being trained: its optimiser, weight average, log and files. Several
    runs (--also-lr) share one stream of rendered samples."""

    def __init__(self, args, lr, out, ckpt, device, init_sd):
        from smpl_depth_ros.net.unet import build_network
        self.args, self.lr, self.out, self.ckpt = args, lr, out, ckpt
        self.net = build_network(args.kind).to(device).train()  # evaluate_batch restores it
        if init_sd is not None:
            self.net.load_state_dict(init_sd)
        self.opt = torch.optim.AdamW(self.net.parameters(), lr=lr, weight_decay=1e-4)
        self.log_path = os.path.splitext(out)[0] + '.log.json'
        self.step, self.log, self.run_loss = 0, [], None
        self.ema = WeightAverage(self.net, args.ema) if args.ema else None
        self.kept = self.net if self.ema is None else self.ema.net  # validated and saved

    def resume(self, device):
        if not os.path.exists(self.ckpt):
            return
        ck = load_checkpoint(self.ckpt, device)
        self.net.load_state_dict(ck['net'])
        self.opt.load_state_dict(ck['opt'])
        self.step, self.log = ck['step'], ck['log']
        if self.ema is not None and ck.get('ema') is not None:
            self.ema.net.load_state_dict(ck['ema'])
        print(f'resumed from {self.ckpt} at step {self.step}', file=sys.stderr)

    def lr_at(self, frac):
        # 5 % linear warm-up, then cosine decay to 1 % of the peak.
        if frac < 0.05:
            return self.lr * (0.1 + 0.9 * frac / 0.05)
        return self.lr * (0.01 + 0.99 * 0.5 * (1 + np.cos(np.pi * (frac - 0.05) / 0.95)))

    def train_step(self, x, labels, coords, cmask, cw, frac):
        with torch.autocast(x.device.type, torch.bfloat16,
                            enabled=self.args.precision == 'bfloat16'):
            logits, cp = self.net(x)
        loss, _, _ = losses(logits.float(), cp.float(), labels, coords, cmask,
                            self.args.coord_weight, cw)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        for g in self.opt.param_groups:
            g['lr'] = float(self.lr_at(frac))
        self.opt.step()
        if self.ema is not None:
            self.ema.update(self.net)
        lv = loss.item()
        self.run_loss = lv if self.run_loss is None else 0.98 * self.run_loss + 0.02 * lv

    def validate(self, val, minutes):
        ev = evaluate_batch(self.kept, *val)
        if self.ema is not None:
            ev['miou_live'] = evaluate_batch(self.net, *val)['miou']
        ev.update(step=self.step, train_loss=self.run_loss, minutes=minutes)
        self.log.append(ev)
        plot_curves(self.log, os.path.splitext(self.out)[0] + '.val.png')
        with open(self.log_path, 'w') as f:
            json.dump(self.log, f, indent=1)
        return ev

    def save(self, meta, checkpoint):
        if checkpoint:
            torch.save(dict(net=self.net.state_dict(), opt=self.opt.state_dict(),
                            step=self.step, log=self.log, lr=self.lr,
                            ema=None if self.ema is None else self.ema.net.state_dict()),
                       self.ckpt)
        save_weights(self.kept, self.out, dict(meta, lr=self.lr, steps=self.step,
                                               val=self.log[-1] if self.log else None))


if __name__ == '__main__':
    main()
