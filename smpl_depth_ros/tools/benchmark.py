"""`benchmark`: speed/accuracy figures as JSON.

    benchmark fit BAG [--frames 200] [--json out.json]
        Fitting alone on a synth_bag bag with ground-truth correspondences (the noisy
        depth pixels and their true template vertex): the fast solver cold and in
        tracking mode, the paper's L-BFGS reference, the 3D-joints baseline (Table II
        row 1), and the fast solver with 30 % of the correspondences replaced by wrong
        vertices. Metrics per row: pve_mm, pa_pve_mm, mpjpe_mm, fit_ms_median,
        fit_ms_p95, iterations_mean, frames.

    benchmark net [--repeats 50] [--json out.json]
        Network (double and single U-Net) and Eq. 2 lookup time per 128x128 crop.

    benchmark node BAG [--frames 2000] [--rate 30] [--json out.json]
        A `reconstructor` subprocess fed at 30 Hz over loopback DDS (localhost discovery,
        private domain): output rate, stamp-to-output latency p50/p95, drops, RSS growth.

    benchmark ray BAG [--workers 2] [--chunk-size 32] [--json out.json]
        process_bag on the same bag with `--workers N` (process pool) and with `--ray`
        (N actors on a local Ray), one after the other: throughput (frames/s), start-up
        (model loading, and Ray's own start), wall time, the ratio, and whether the
        results are the same.

    benchmark empty [--sensors kinect_v1,...] [--bin 3.0 3.5] [--frames 5] [--seed 202]
        Frames with nobody to find: the sensor sweep's subjects (`sweep`'s generator) with
        their pixels blanked, so only the room's blobs are left; the time per frame with
        and without `second_network` (whose last look fits rejected blobs again), single
        frames, one torch thread.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from smpl_depth_ros.evaluation import write_json


def _row(name, results, gts):
    from smpl_depth_ros import evaluation as ev
    V, J = gts
    t = np.array([r.time_ms for r in results])
    return dict(
        method=name, frames=len(results),
        pve_mm=float(np.mean([ev.pve(r.vertices, v) for r, v in zip(results, V)]) * 1000),
        pa_pve_mm=float(np.mean([ev.pa_pve(r.vertices, v) for r, v in zip(results, V)]) * 1000),
        mpjpe_mm=float(np.mean([ev.mpjpe(r.joints, j) for r, j in zip(results, J)]) * 1000),
        fit_ms_median=float(np.median(t)), fit_ms_p95=float(np.percentile(t, 95)),
        iterations_mean=float(np.mean([r.iterations for r in results])))


def bench_fit(args) -> dict:
    import torch
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    from smpl_depth_ros.bagio import iter_depth_bag
    from smpl_depth_ros.body import load_body_model
    from smpl_depth_ros.fit import Fitter
    from smpl_depth_ros.tools.synth_bag import gt_path

    gt = dict(np.load(args.gt or gt_path(args.bag), allow_pickle=False))
    body = load_body_model(str(gt['body_model']), args.model_path or None)
    fitter = Fitter(body)
    rng = np.random.default_rng(0)
    stamps = list(gt['stamps'])
    sequence = bool(gt.get('sequence', False))
    rows = {k: [] for k in ('fast_cold', 'fast_tracking', 'lbfgs_cold', 'init_only_cold',
                            'gt_joints_fast', 'fast_cold_30pct_outliers')}
    Vs, Js = [], []
    prev = None
    fitter.fit(np.zeros((20, 3), np.float32) + 2, np.arange(20))  # warm caches
    for n, (stamp, depth, K) in enumerate(iter_depth_bag(args.bag)):
        if args.frames and n >= args.frames:
            break
        i = stamps.index(stamp)
        gvid = gt['vertex_ids'][i]
        m = (gvid >= 0) & (depth > 0)
        rr, cc = np.nonzero(m)
        z = depth[rr, cc]
        pts = np.stack([(cc - K[0, 2]) * z / K[0, 0], (rr - K[1, 2]) * z / K[1, 1], z],
                       1).astype(np.float32)
        ids = gvid[m]
        Vs.append(gt['vertices'][i])
        Js.append(gt['joints'][i])
        cold = fitter.fit(pts, ids)
        rows['fast_cold'].append(cold)
        if sequence:  # tracking is only meaningful on smooth sequences
            tr = fitter.fit(pts, ids, init=prev) if prev is not None else cold
            rows['fast_tracking'].append(tr)
            prev = tr.params
        if n < args.lbfgs_frames:
            rows['lbfgs_cold'].append(fitter.fit(pts, ids, solver='lbfgs'))
            # Where both solvers start: the data-driven initialisation alone.
            rows['init_only_cold'].append(fitter.fit(pts, ids, solver='none'))
        rows['gt_joints_fast'].append(fitter.fit_joints(gt['joints'][i]))
        bad = rng.random(len(ids)) < 0.3
        ids2 = ids.copy()
        ids2[bad] = rng.integers(0, body.num_vertices, int(bad.sum()))
        rows['fast_cold_30pct_outliers'].append(fitter.fit(pts, ids2))
        if sys.stderr.isatty():
            print(f'\r{n + 1} frames', end='', file=sys.stderr)
    if sys.stderr.isatty():
        print(file=sys.stderr)
    out = {}
    for k, res in rows.items():
        if res:
            out[k] = _row(k, res, (Vs[:len(res)], Js[:len(res)]))
    base, rob = out['fast_cold']['pve_mm'], out['fast_cold_30pct_outliers']['pve_mm']
    out['outlier_error_growth_pct'] = 100.0 * (rob - base) / base
    out['bag'] = args.bag
    out['threads'] = torch.get_num_threads()
    return out


def bench_net(args) -> dict:
    """Network + Eq. 2 lookup time per crop on this machine (batch 1, after warm-up):
    one pass (`net_ms_*`) and with the mirrored pass of flip_tta (`net_tta_ms_*`), in
    float32 and, as rows `<kind>_bfloat16`, in bfloat16 (`net_precision`; the default
    'auto' takes it where `bfloat16_units` says, `bfloat16_units` in the JSON)."""
    import time

    import torch
    torch.set_num_threads(args.threads or max(1, os.cpu_count() or 1))
    from smpl_depth_ros.body import load_body_model
    from smpl_depth_ros.net.data import make_fixed_set
    from smpl_depth_ros.net.infer import CorrespondenceNet, bfloat16_units, default_weights
    body = load_body_model('anny')
    out = {}
    x, _, _, _ = make_fixed_set(body, 8, seed=5)
    x = x.numpy()
    for kind, precision in (('double', 'float32'), ('single', 'float32'),
                            ('double', 'bfloat16'), ('single', 'bfloat16')):
        net = CorrespondenceNet(body, default_weights('anny', kind), precision=precision)
        for i in range(3):
            net.predict(x[i:i + 1])
        tn, tt, tl = [], [], []
        for k in range(args.repeats):
            xi = x[k % len(x):k % len(x) + 1]
            t0 = time.perf_counter()
            net.predict(xi, flip_tta=False)
            t1 = time.perf_counter()
            lab, co = net.predict(xi, flip_tta=True)
            t2 = time.perf_counter()
            fg = (lab[0] > 0) & (xi[0, 1] > 0)
            net.lookup(lab[0], co[0], fg)
            tl.append((time.perf_counter() - t2) * 1e3)
            tn.append((t1 - t0) * 1e3)
            tt.append((t2 - t1) * 1e3)
        row = kind if precision == 'float32' else f'{kind}_{precision}'
        out[row] = dict(net_ms_median=float(np.median(tn)),
                        net_ms_p95=float(np.percentile(tn, 95)),
                        net_tta_ms_median=float(np.median(tt)),
                        net_tta_ms_p95=float(np.percentile(tt, 95)),
                        lookup_ms_median=float(np.median(tl)),
                        params=int(sum(p.numel() for p in net.net.parameters())))
    out['threads'] = torch.get_num_threads()
    out['device'] = 'cpu'
    out['bfloat16_units'] = bfloat16_units()
    return out


def bench_node(args) -> dict:
    """Drive a `reconstructor` subprocess with a 30 Hz depth stream over loopback DDS.

    Measures the node's sustained output rate (frames answered on ~/bodies/tracked, one
    message per frame whatever the number of persons), the stamp-to-receive latency of
    each, the persons per frame, the dropped frames (offered vs answered), the CPU cores
    the node and the driver use (CPU time over the run's wall time) and the node's resident
    memory (VmRSS from /proc) every `--sample-every` frames (default 10 % of the run).
    The soak verdict (`flat`): RSS growth over the last 80 % of the run below 5 MB and the
    p95 latency of the last 1,000 answers within 10 % of the first 1,000's.
    """
    import random
    import subprocess
    import time

    # DDS stays on this machine; a private domain keeps parallel runs apart.
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.randint(30, 99)))
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import CameraInfo, Image, JointState

    from smpl_depth_ros.bagio import iter_depth_bag
    from smpl_depth_ros.ros import adapters
    from smpl_depth_ros.stamps import cdr_stamp_ns

    # Up to 150 frames played forwards then backwards (a sequence bag has no jump
    # where the loop restarts, as a live camera has none).
    frames = [(d, K) for _, (_, d, K) in zip(range(150), iter_depth_bag(args.bag))]
    frames = frames + frames[-2:0:-1]
    H, W = frames[0][0].shape
    exe = [sys.executable, '-m', 'smpl_depth_ros.ros.reconstructor_node', '--ros-args',
           '-r', 'depth:=/bench/depth', '-r', 'camera_info:=/bench/camera_info',
           '-p', 'qos_reliability:=reliable', '-p', 'device:=cpu']
    for p in args.param:
        exe += ['-p', p]
    proc = subprocess.Popen(exe, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)

    def cpu_s():  # the node's user + system CPU time (s), from /proc/PID/stat
        with open(f'/proc/{proc.pid}/stat') as f:
            fields = f.read().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')

    def rss_mb():
        with open(f'/proc/{proc.pid}/status') as f:
            for line in f:
                if line.startswith('VmRSS'):
                    return int(line.split()[1]) / 1024
        return float('nan')

    rclpy.init()
    node = rclpy.create_node('bench_node_driver')
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
    pub_d = node.create_publisher(Image, '/bench/depth', qos)
    pub_i = node.create_publisher(CameraInfo, '/bench/camera_info', qos)
    lat, recv_t, persons = [], [], []

    def on_tracked(data: bytes):
        now = node.get_clock().now().nanoseconds
        lat.append((now - cdr_stamp_ns(data)) * 1e-6)
        recv_t.append(time.monotonic())
        persons.append(len(deserialize_message(data, JointState).name))
    node.create_subscription(JointState, '/reconstructor/bodies/tracked', on_tracked, 10,
                             raw=True)
    msgs = [adapters.depth_to_image_msg(d, encoding='16UC1') for d, _ in frames]
    infos = [adapters.camera_info_msg(K, (W, H)) for _, K in frames]
    # Wait for the node to be up (first output).
    t0 = time.monotonic()
    while not lat and time.monotonic() - t0 < 120:
        hdr = adapters.make_header(stamp_ns=node.get_clock().now().nanoseconds,
                                   frame_id='camera_depth_optical_frame')
        infos[0].header = hdr
        msgs[0].header = hdr
        pub_i.publish(infos[0])
        pub_d.publish(msgs[0])
        rclpy.spin_once(node, timeout_sec=0.2)
    lat.clear()
    recv_t.clear()
    persons.clear()
    rss0 = rss_mb()
    cpu0, driver0, wall0 = cpu_s(), time.process_time(), time.monotonic()
    every = args.sample_every or max(args.frames // 10, 1)
    trace = []  # (frames offered, RSS MB, answers so far)
    period = 1.0 / args.rate
    start = time.monotonic()
    for k in range(args.frames):
        if k % every == 0:
            trace.append((k, rss_mb(), len(lat)))
        target = start + k * period
        while time.monotonic() < target:
            rclpy.spin_once(node, timeout_sec=max(0.0, target - time.monotonic()))
        hdr = adapters.make_header(stamp_ns=node.get_clock().now().nanoseconds,
                                   frame_id='camera_depth_optical_frame')
        i = k % len(msgs)
        infos[i].header = hdr
        msgs[i].header = hdr
        pub_i.publish(infos[i])
        pub_d.publish(msgs[i])
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    rss1 = rss_mb()
    wall = time.monotonic() - wall0
    node_cores, driver_cores = (cpu_s() - cpu0) / wall, (time.process_time() - driver0) / wall
    proc.send_signal(2)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
    node.destroy_node()
    rclpy.try_shutdown()
    dur = (recv_t[-1] - recv_t[0]) if len(recv_t) > 1 else float('nan')
    trace.append((args.frames, rss1, len(lat)))
    pct = lambda a, q: float(np.percentile(a, q)) if len(a) else float('nan')  # noqa: E731
    # After the allocator's warm-up (the first 20 %), the growth that matters:
    late = next(t for t in trace if t[0] >= 0.2 * args.frames)
    n = min(1000, len(lat) // 2)
    p95_first, p95_last = pct(lat[:n], 95), pct(lat[-n:], 95) if n else float('nan')
    growth = rss1 - late[1]
    return dict(input_rate_hz=args.rate, frames_offered=args.frames, image=f'{W}x{H}',
                params=list(args.param),
                outputs=len(lat), output_rate_hz=(len(lat) - 1) / dur if len(lat) > 1 else 0.0,
                latency_ms_p50=pct(lat, 50), latency_ms_p95=pct(lat, 95),
                persons_per_frame_mean=float(np.mean(persons)) if persons else 0.0,
                dropped=args.frames - len(lat), node_cpu_cores=node_cores,
                driver_cpu_cores=driver_cores, rss_mb_start=rss0, rss_mb_end=rss1,
                rss_growth_mb=rss1 - rss0, rss_growth_last_80pct_mb=growth,
                latency_ms_p95_first_1000=p95_first, latency_ms_p95_last_1000=p95_last,
                flat=bool(growth < 5.0 and p95_last <= 1.1 * p95_first),
                trace=[dict(frames=k, rss_mb=round(m, 1), answered=a,
                            dropped=k - a) for k, m, a in trace])


def bench_ray(args) -> dict:
    """process_bag with the process pool, then with Ray, on the same bag and chunks."""
    import tempfile
    from pathlib import Path

    from smpl_depth_ros.config import PipelineConfig
    from smpl_depth_ros.offline import process_bag
    runs = {}
    with tempfile.TemporaryDirectory(prefix='bench_ray_') as tmp:
        for name, ray in (('process_pool', None), ('ray', '')):
            s = process_bag(args.bag, Path(tmp) / name, workers=args.workers,
                            chunk_size=args.chunk_size, ray=ray, progress=False,
                            log=lambda m: None, config=PipelineConfig(device=args.device))
            runs[name] = dict(frames_per_s=s['fps'], startup_s=s['load_s'],
                              processing_s=s['processing_s'], wall_s=s['wall_s'],
                              driver_cpu_s=s['driver_cpu_s'],
                              frames_read=s['frames_read'], processed=s['processed'],
                              per_worker=s['per_worker'])
        a, b = (np.load(Path(tmp) / n / 'results.npz') for n in runs)
        differ = {k: (float(np.nanmax(np.abs(a[k] - b[k]))) if a[k].dtype.kind == 'f'
                      and a[k].shape == b[k].shape and a[k].size else 'differs')
                  for k in a.files if k != 'timings_ms'
                  and not np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == 'f')}
    pool, ray = runs['process_pool'], runs['ray']
    return dict(bag=str(args.bag), workers=args.workers, chunk_size=args.chunk_size,
                device=args.device, cpus=os.cpu_count(), process_pool=pool, ray=ray,
                ray_vs_pool_throughput=(round(ray['frames_per_s'] / pool['frames_per_s'], 3)
                                        if pool['frames_per_s'] else None),
                same_results=not differ, differences=differ)


def bench_empty(args) -> dict:
    import time

    import torch

    from smpl_depth_ros.body import load_body_model
    from smpl_depth_ros.config import PipelineConfig
    from smpl_depth_ros.pipeline import Reconstructor
    from smpl_depth_ros.synth.poses import PoseSampler
    from smpl_depth_ros.synth.sensors import SENSORS
    from smpl_depth_ros.tools.sweep import sweep_frames
    from smpl_depth_ros.types import InputError
    torch.set_num_threads(1)
    body = load_body_model('anny')
    sampler = PoseSampler(body, mode='templates')
    frames = []
    for name in args.sensors.split(','):
        for fr in sweep_frames(body, sampler, SENSORS[name], *args.bin, args.frames, args.seed):
            frames.append((name, np.where(fr['labels'] > 0, 0.0, fr['depth']), fr['K']))
    rows = {}
    for second in (False, True):
        t, found, recs = [], 0, {}
        for name, depth, K in frames:
            if name not in recs:  # one per sensor, as a node on that camera
                recs[name] = Reconstructor(PipelineConfig(
                    tracking=False, device='cpu', max_persons=1, second_network=second),
                    body=body)
            t0 = time.perf_counter()
            try:
                found += bool(recs[name].process(depth, K).persons)
            except InputError:
                pass
            t.append((time.perf_counter() - t0) * 1e3)
        rows['second_network' if second else 'without_second_network'] = dict(
            frame_ms_median=round(float(np.median(t)), 1),
            frame_ms_mean=round(float(np.mean(t)), 1), frames=len(t),
            persons_reported=found)
    return dict(sensors=args.sensors.split(','), bin=list(args.bin), seed=args.seed,
                subjects=args.frames, **rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='benchmark', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest='cmd', required=True)
    f = sub.add_parser('fit', help='fitting with ground-truth correspondences')
    f.add_argument('bag')
    f.add_argument('--gt', default=None)
    f.add_argument('--model-path', default='')
    f.add_argument('--frames', type=int, default=200)
    f.add_argument('--lbfgs-frames', type=int, default=30,
                   help='frames for the (slow) L-BFGS reference')
    f.add_argument('--json', default=None)
    nb = sub.add_parser('net', help='network + correspondence lookup time per crop')
    nb.add_argument('--repeats', type=int, default=50)
    nb.add_argument('--threads', type=int, default=0)
    nb.add_argument('--json', default=None)
    nd = sub.add_parser('node', help='reconstructor node under a 30 Hz depth stream')
    nd.add_argument('bag', help='depth bag (e.g. from synth_bag); up to 150 frames played '
                    'forwards and backwards in a loop')
    nd.add_argument('--frames', type=int, default=2000)
    nd.add_argument('--rate', type=float, default=30.0)
    nd.add_argument('--sample-every', type=int, default=0, metavar='FRAMES',
                    help='RSS / answers sampled every N frames (default 10 %% of the run)')
    nd.add_argument('-p', '--param', action='append', default=[], metavar='NAME:=VALUE',
                    help='extra node parameter (repeatable), e.g. -p flip_tta:=false')
    nd.add_argument('--json', default=None)
    rb = sub.add_parser('ray', help='process_bag: process pool against Ray actors')
    rb.add_argument('bag', help='a bag for process_bag (e.g. smpl_depth_ros/data/sample_bag)')
    rb.add_argument('--workers', type=int, default=2)
    rb.add_argument('--chunk-size', type=int, default=32)
    rb.add_argument('--device', default='cpu', choices=['auto', 'cpu', 'cuda'])
    rb.add_argument('--json', default=None)
    em = sub.add_parser('empty', help='frames with nobody to find, with and without '
                        'second_network')
    em.add_argument('--sensors', default='kinect_v1,realsense_d435,oak_d,'
                    'azure_kinect_nfov_binned')
    em.add_argument('--bin', type=float, nargs=2, default=(3.0, 3.5), metavar=('FROM', 'TO'))
    em.add_argument('--frames', type=int, default=5, help='subjects per sensor')
    em.add_argument('--seed', type=int, default=202)
    em.add_argument('--json', default=None)
    args = ap.parse_args(argv)
    command = ' '.join(['benchmark', *(sys.argv[1:] if argv is None else argv)])
    if args.cmd in ('net', 'node', 'ray', 'empty'):
        out = {'net': bench_net, 'node': bench_node, 'ray': bench_ray,
               'empty': bench_empty}[args.cmd](args)
        write_json(out, args.json, command)
        return 0
    out = bench_fit(args)
    rows = [v for v in out.values() if isinstance(v, dict)]
    print(f'{"method":26s} {"PVE mm":>7s} {"PA-PVE":>7s} {"MPJPE":>7s} {"ms p50":>7s} '
          f'{"ms p95":>7s} {"iters":>6s} {"frames":>6s}')
    for r in rows:
        print(f'{r["method"]:26s} {r["pve_mm"]:7.1f} {r["pa_pve_mm"]:7.1f} {r["mpjpe_mm"]:7.1f} '
              f'{r["fit_ms_median"]:7.1f} {r["fit_ms_p95"]:7.1f} {r["iterations_mean"]:6.1f} '
              f'{r["frames"]:6d}')
    write_json(out, args.json, command)
    return 0


if __name__ == '__main__':
    sys.exit(main())
