"""Write the stored test frames of test/data (a stereo person far away, a crouch, a
stereo person seen through noisier disparity than the preset's, a time-of-flight person
beside a piece of the scene the network sees a few body parts in).

    python -m smpl_depth_ros.tools.make_test_frames --out test/data [--only NAME]

Each is one synthetic frame (anny body, random room, the sensor's noise model) saved as
`depth_mm` (uint16, the 16UC1 image), `K`, `vertices` (the true mesh, camera frame,
metres) and `sensor`: the first frame of its seed sequence that meets its condition, so
the choice is the seed's, not a pick of easy frames (or, given `sweep`, that frame of
the sensor sweep).
"""
from __future__ import annotations

import argparse
import os
from dataclasses import replace

import numpy as np

FRAMES = {
    # a RealSense D435 (848x480) person at 3.5-4.0 m, template poses
    'stereo_d435_far': dict(sensor='realsense_d435', depth=(3.6, 4.0), poses='templates',
                            seed=31, posture=None),
    # a deep squat / crouch seen by a Kinect v1 at 2-3 m
    'crouch_kinect_v1': dict(sensor='kinect_v1', depth=(2.0, 3.0), poses='broad', seed=32,
                             posture='squat_deep'),
    # a D435 (848x480) person at 3.0-3.5 m through a noisier unit than the preset: the
    # disparity error per pixel (no block-matching correlation) at 0.15 px RMS
    'stereo_d435_noisy': dict(sensor='realsense_d435', depth=(3.0, 3.5), poses='templates',
                              seed=33, posture=None,
                              noise=dict(white_share=1.0, subpixel_sigma_px=0.15)),
    # the broad-pose validation sweep's Azure Kinect NFOV frame 4 at 3.5 m (`sweep --seed
    # 202 --poses broad`): a person reaching, and a piece of the scene the network labels
    # as a few body parts (body score 2.6)
    'scene_piece_azure': dict(sensor='azure_kinect_nfov', depth=(3.5, 3.56), poses='broad',
                              sweep=(202, 4)),
}


class _Posture:
    """A PoseSampler stand-in that draws one posture (with the broad noise)."""

    def __init__(self, sampler, name):
        self.s, self.name = sampler, name

    def sample_posed(self, rng):
        pose = self.s._from_templates(rng, [self.name], np.ones(1), 10.0, amp=(0.9, 1.05))
        return self.s.to_model(pose[None])[0], np.zeros(2)


def make(name: str, body) -> dict:
    from smpl_depth_ros.synth import dataset
    from smpl_depth_ros.synth.poses import PoseSampler
    from smpl_depth_ros.synth.sensors import SENSORS
    spec = FRAMES[name]
    sensor = SENSORS[spec['sensor']].with_noise(**spec.get('noise', {}))
    sampler = PoseSampler(body, mode=spec['poses'])
    if 'sweep' in spec:  # that frame of the sensor sweep (tools.sweep.sweep_frames)
        from smpl_depth_ros.tools.sweep import sweep_frames
        seed, i = spec['sweep']
        fr = list(sweep_frames(body, sampler, sensor, *spec['depth'], i + 1, seed))[i]
        return _saved(fr, spec)
    if spec['posture']:
        sampler = _Posture(sampler, spec['posture'])
    p = replace(dataset.SynthParams(sensor=sensor), depth_range=spec['depth'])
    rng = np.random.default_rng(spec['seed'])
    cam = sensor.camera
    for _ in range(50):  # the first frame whose whole body is in the image
        fr = dataset.make_frame(body, sampler, rng, cam, params=p)
        uv = cam.project(fr['vertices'].astype(np.float64))
        inside = ((uv >= 0) & (uv < [cam.width, cam.height])).all(1).mean()
        if inside > 0.99 and (fr['labels'] > 0).sum() > 1500:
            return _saved(fr, spec)
    raise RuntimeError(f'no frame for {name}')


def _saved(fr: dict, spec: dict) -> dict:
    return dict(depth_mm=np.rint(fr['depth'] * 1000).astype(np.uint16), K=fr['K'],
                vertices=fr['vertices'], sensor=np.array(spec['sensor']))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='make_test_frames', description=__doc__.split('\n')[0])
    ap.add_argument('--out', default='test/data')
    ap.add_argument('--only', choices=sorted(FRAMES), help='write this frame only')
    args = ap.parse_args(argv)
    from smpl_depth_ros.body import load_body_model
    body = load_body_model('anny')
    for name in [args.only] if args.only else FRAMES:
        path = os.path.join(args.out, f'{name}.npz')
        np.savez_compressed(path, **make(name, body))
        print(path)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
