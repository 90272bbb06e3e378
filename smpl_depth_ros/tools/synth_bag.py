"""synth_bag: write a synthetic depth-camera ROS 2 bag plus exact ground truth.

    synth_bag --out /tmp/synth --frames 200 --seed 1 [--sequence] [--camera kinect_v1]
    synth_bag --out /tmp/d435 --sensor realsense_d435 --poses broad --depth-range 3 3.5

The bag (rosbags, no ROS install needed) holds /camera/depth/image_raw and
/camera/depth/camera_info (frame camera_depth_optical_frame). Ground truth goes next to
it in `<out>.gt.npz`: stamps (int64 ns, equal to the header stamps), vertices, faces,
joints, joint_names, pose, shape, global_orient, transl, body_model, topology, K, width,
height, labels (N, H, W uint8), vertex_ids (N, H, W int32, -1 empty), seed, camera,
sensor, strength, poses.

`--persons N` (N >= 2) writes several people walking across the view on lanes at their
own depths, crossing in front of each other, entering and leaving
(`synth.dataset.make_multi_sequence`; with `--sequence` one continuous scene, else an
independent scene per frame). Its ground truth adds a person axis: vertices (F, N, V, 3),
joints, pose, shape, global_orient, transl per person, person_ids (N,) (the true IDs),
visible (F, N) pixel counts and person_index (F, H, W int8, -1 none).

`--sensor` takes a depth-sensor preset (synth.sensors: structured light, active stereo,
time of flight): its camera and its noise model. Without it, the Kinect v1 noise model
is applied on `--camera` (the original protocol).
A JSON summary line is printed last.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import numpy as np

EPOCH_NS = 1_700_000_000 * 1_000_000_000  # 2023-11-14T22:13:20Z


def start_stamp_ns(seed: int) -> int:
    """First header stamp: a fixed epoch plus one hour per seed (mod 10,000 seeds)."""
    return EPOCH_NS + (int(seed) % 10_000) * 3600 * 1_000_000_000


def gt_path(bag_path: str) -> str:
    """The ground-truth sidecar of a bag directory: '<bag>.gt.npz'."""
    return os.path.normpath(str(bag_path)) + '.gt.npz'


def topology_name(body) -> str:
    """A short mesh-topology tag (vertex ids are only comparable within one topology)."""
    if body.name == 'anny':
        from smpl_depth_ros.body.anny_model import TOPOLOGY
        return f'anny_{TOPOLOGY}'
    return getattr(body, 'topology', None) or f'{body.name}_{body.num_vertices}v'


def build_parser() -> argparse.ArgumentParser:
    from smpl_depth_ros.synth.camera import CAMERAS
    from smpl_depth_ros.synth.poses import MODES
    ap = argparse.ArgumentParser(prog='synth_bag', description=__doc__.split('\n')[0])
    ap.add_argument('--out', required=True, help='bag directory to create (must not exist)')
    ap.add_argument('--frames', type=int, default=200)
    ap.add_argument('--seed', type=int, default=0)
    from smpl_depth_ros.synth.sensors import SENSORS
    ap.add_argument('--camera', default='kinect_v1', choices=sorted(CAMERAS))
    ap.add_argument('--sensor', default=None, choices=sorted(SENSORS),
                    help='a sensor preset: its camera and noise model (overrides --camera)')
    ap.add_argument('--strength', type=float, default=1.0,
                    help='noise strength of --sensor (1 = nominal)')
    ap.add_argument('--poses', default='templates', choices=MODES,
                    help="'templates': the activity templates; 'broad': postures beyond "
                         "them and uniform draws within the joint limits; 'seated': on a "
                         "chair (rendered under them); 'mocap': real motion capture "
                         'retargeted to anny (synth.poses)')
    ap.add_argument('--depth-range', type=float, nargs=2, default=None, metavar=('MIN', 'MAX'),
                    help='root depth range in metres (default 1 5)')
    ap.add_argument('--width', type=int, default=None, help='resample the camera preset')
    ap.add_argument('--height', type=int, default=None, help='resample the camera preset')
    ap.add_argument('--rate', type=float, default=30.0, help='frame rate for the stamps (Hz)')
    ap.add_argument('--sequence', action='store_true',
                    help='smooth motion of one person instead of independent frames')
    ap.add_argument('--head-turn', type=float, default=0.0, metavar='DEG',
                    help='also turn the heads: yaw up to +-DEG at the neck and again at the '
                         'head, pitch up to +-DEG/2 (default 0: the pose templates only)')
    ap.add_argument('--persons', type=int, default=1,
                    help='people in the scene (>= 2: several people walking across the view)')
    ap.add_argument('--no-noise', action='store_true', help='exact depth (mm-rounded by 16UC1)')
    ap.add_argument('--no-background', action='store_true', help='the person only')
    ap.add_argument('--encoding', default='16UC1', choices=['16UC1', '32FC1'])
    ap.add_argument('--storage', default='mcap', choices=['mcap', 'sqlite3'])
    ap.add_argument('--backend', default='anny', choices=['anny', 'smpl'])
    ap.add_argument('--model-path', default=None,
                    help='body model file (SMPL: or env SMPL_MODEL_PATH)')
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.frames < 1:
        print('synth_bag: --frames must be >= 1', file=sys.stderr)
        return 2
    if args.persons < 1:
        print('synth_bag: --persons must be >= 1', file=sys.stderr)
        return 2
    if args.rate <= 0:
        print('synth_bag: --rate must be > 0', file=sys.stderr)
        return 2
    if not args.strength > 0:
        print('synth_bag: --strength must be > 0', file=sys.stderr)
        return 2
    if args.depth_range is not None and not 0 < args.depth_range[0] <= args.depth_range[1]:
        print('synth_bag: --depth-range needs 0 < MIN <= MAX', file=sys.stderr)
        return 2
    out = os.path.normpath(args.out)
    gt_file = gt_path(out)
    for p in (out, gt_file):
        if os.path.exists(p):
            print(f'synth_bag: {p} exists already, not overwriting', file=sys.stderr)
            return 2

    t0 = time.perf_counter()
    from smpl_depth_ros.bagio import write_depth_bag
    from smpl_depth_ros.body import load_body_model
    from smpl_depth_ros.synth import dataset
    from smpl_depth_ros.synth.camera import get_camera
    from smpl_depth_ros.synth.poses import PoseSampler

    try:
        body = load_body_model(args.backend, args.model_path)
    except (FileNotFoundError, ValueError) as e:
        print(f'synth_bag: {e}', file=sys.stderr)
        return 2
    from smpl_depth_ros.synth.sensors import get_sensor
    sensor = None
    if args.sensor:
        sensor = get_sensor(args.sensor, args.width, args.height)
        camera = sensor.camera
    else:
        camera = get_camera(args.camera, args.width, args.height)
    params = dataset.SynthParams(sensor=sensor, strength=args.strength,
                                 chairs=args.poses == 'seated')
    if args.depth_range is not None:
        params = dataclasses.replace(params, depth_range=tuple(args.depth_range))
    sampler = PoseSampler(body, head_turn_deg=args.head_turn, mode=args.poses)
    rng = np.random.default_rng(args.seed)
    noise, bg = not args.no_noise, not args.no_background
    N, H, W = args.frames, camera.height, camera.width
    try:
        dataset.root_depth_range(camera, params)
    except ValueError as e:
        print(f'synth_bag: {e}', file=sys.stderr)
        return 2
    multi = args.persons > 1
    if multi and args.sequence:
        frames = dataset.make_multi_sequence(body, sampler, rng, camera, N, args.persons,
                                             noise, bg, params, rate=args.rate)
    elif multi:
        frames = (next(dataset.make_multi_sequence(body, sampler, rng, camera, 1,
                                                   args.persons, noise, bg, params))
                  for _ in range(N))
    elif args.sequence:
        frames = dataset.make_sequence(body, sampler, rng, camera, N, noise, bg, params)
    else:
        frames = (dataset.make_frame(body, sampler, rng, camera, noise, bg, params)
                  for _ in range(N))

    start = start_stamp_ns(args.seed)
    stamps = np.array([start + round(i * 1e9 / args.rate) for i in range(N)], np.int64)
    labels = np.zeros((N, H, W), np.uint8)
    vertex_ids = np.full((N, H, W), -1, np.int32)
    per_frame: dict[str, list] = {k: [] for k in
                                  ('vertices', 'joints', 'pose', 'shape', 'global_orient',
                                   'transl')}
    if multi:
        per_frame.update(visible=[], person_index=[])

    def stream():
        it = frames
        if sys.stderr.isatty():
            from tqdm import tqdm
            it = tqdm(it, total=N, desc='synth_bag', unit='frame')
        for i, fr in enumerate(it):
            labels[i] = fr['labels']
            vertex_ids[i] = fr['vertex_ids']
            for k, v in per_frame.items():
                v.append(fr[k])
            yield int(stamps[i]), fr['depth']

    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    n = write_depth_bag(out, stream(), camera, args.encoding, args.storage)
    np.savez_compressed(
        gt_file, stamps=stamps[:n],
        **{k: np.stack(v).astype(np.float32) for k, v in per_frame.items()
           if k not in ('visible', 'person_index')},
        **({'visible': np.stack(per_frame['visible']),
            'person_index': np.stack(per_frame['person_index']),
            'person_ids': np.arange(1, args.persons + 1, dtype=np.int32)} if multi else {}),
        persons=np.int64(args.persons),
        faces=body.faces_numpy(), joint_names=np.array(body.joint_names),
        body_model=np.array(body.name), topology=np.array(topology_name(body)),
        K=camera.K, width=np.int64(W), height=np.int64(H), labels=labels[:n],
        vertex_ids=vertex_ids[:n], seed=np.int64(args.seed), camera=np.array(camera.name),
        part_labels=body.part_labels.cpu().numpy().astype(np.uint8),
        encoding=np.array(args.encoding), sequence=np.bool_(args.sequence),
        noise=np.bool_(noise), background=np.bool_(bg),
        sensor=np.array(args.sensor or ''), strength=np.float64(args.strength),
        poses=np.array(args.poses))
    seconds = time.perf_counter() - t0
    print(json.dumps({'frames': n, 'seconds': round(seconds, 2), 'path': out,
                      'gt': gt_file, 'camera': camera.name, 'size': [W, H],
                      'encoding': args.encoding, 'storage': args.storage,
                      'sequence': bool(args.sequence), 'noise': noise, 'background': bg,
                      'sensor': args.sensor, 'poses': args.poses, 'persons': args.persons,
                      'backend': body.name}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
