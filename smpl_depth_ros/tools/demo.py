"""demo: the shipped sample bag through process_bag, end to end, plus a picture of one frame.

    python -m smpl_depth_ros.tools.demo --out out/demo          # what `make demo` runs

Processes `smpl_depth_ros/data/sample_bag` (a few seconds of a synthetic depth sequence,
320x240 16UC1, made by `synth_bag --sequence`; see `--make-sample`) on the embedded
defaults and leaves in the output folder:

* ``bag/``: the input topics plus the reconstructor's outputs (open it in Foxglove or
  replay it with `play_bag`),
* ``meshes/<stamp_ns>.ply``: the fitted mesh of every frame,
* ``results.npz`` and ``summary.json`` (frames, skips, timings, fps, peak RSS),
* ``frame.png``: one frame as depth | part segmentation | fitted mesh rendered from the
  camera (normal shading) | mesh over depth,

and prints where they are with the headline figures (and, when the bag's ground truth
``sample_bag.gt.npz`` is next to it, the mean per-vertex error). Needs nothing but the
installed Python packages: no ROS install, no network.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

PROG = 'demo'
DATA = Path(__file__).resolve().parents[1] / 'data'
SAMPLE_BAG = DATA / 'sample_bag'
# How the shipped sample was made (`--make-sample` reproduces it).
SAMPLE_RECIPE = dict(frames=40, seed=4, rate=15.0, width=320, height=240,
                     camera='kinect_v1')


def make_sample_bag(dest: Path = SAMPLE_BAG, **recipe) -> dict:
    """Write the sample bag: `synth_bag --sequence` (see SAMPLE_RECIPE), then the same
    messages rewritten into an MCAP file with zstd-compressed chunks (the bag is ~30 %
    smaller; Foxglove, rosbag2 and rosbags all read it). `<dest>.gt.npz` is the ground
    truth."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    from smpl_depth_ros.offline import BagInput
    from smpl_depth_ros.tools import synth_bag
    r = dict(SAMPLE_RECIPE, **recipe)
    dest = Path(dest)
    gt_dest = Path(synth_bag.gt_path(str(dest)))
    if dest.exists() or gt_dest.exists():
        raise FileExistsError(f'{dest} or {gt_dest} exists; remove them first')
    with tempfile.TemporaryDirectory() as tmp:
        raw = Path(tmp) / 'raw'
        assert synth_bag.main([
            '--out', str(raw), '--frames', str(r['frames']), '--seed', str(r['seed']),
            '--sequence', '--rate', str(r['rate']), '--camera', r['camera'],
            '--width', str(r['width']), '--height', str(r['height'])]) == 0
        writer = Writer(dest, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        with BagInput(raw) as src, writer:
            conns = {}
            for topic, t, data in src.messages():
                if topic.id not in conns:
                    conns[topic.id] = writer.add_connection(
                        topic.topic, topic.msgtype, typestore=src.typestore)
                writer.write(conns[topic.id], t, data)
        shutil.copyfile(synth_bag.gt_path(str(raw)), gt_dest)
    size = sum(p.stat().st_size for p in dest.iterdir()) + gt_dest.stat().st_size
    return dict(r, path=str(dest), gt=str(gt_dest), bytes=size)


def _frame_inputs(bag: Path, stamp: int):
    """(depth (H, W) metres, K) of the depth frame with header stamp `stamp`."""
    from smpl_depth_ros.offline import BagInput, select_topics
    from smpl_depth_ros.ros import adapters as A
    from smpl_depth_ros.stamps import stamp_to_ns
    with BagInput(bag) as src:
        depth_topic, info_topic = select_topics(src.topics, None, None)
        K = depth = None
        for topic, _t, raw in src.messages({depth_topic, info_topic}):
            msg = src.typestore.deserialize_cdr(raw, topic.msgtype)
            if topic.topic == info_topic and K is None:
                K = A.camera_info_to_K(msg)[0]
            elif topic.topic == depth_topic and stamp_to_ns(msg.header.stamp) == stamp:
                depth = A.image_to_depth(msg)
            if depth is not None and K is not None:
                return depth, K
    raise ValueError(f'no depth frame with stamp {stamp} (or no camera_info) in {bag}')


def _output_image(out_bag: Path, topic: str, stamp: int) -> np.ndarray | None:
    from smpl_depth_ros.offline import BagInput
    from smpl_depth_ros.ros import adapters as A
    from smpl_depth_ros.stamps import stamp_to_ns
    with BagInput(out_bag) as src:
        for t, _bt, raw in src.messages({topic}):
            msg = src.typestore.deserialize_cdr(raw, t.msgtype)
            if stamp_to_ns(msg.header.stamp) == stamp:
                return A.image_to_array(msg)
    return None


def render_mesh(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, size: tuple[int, int]):
    """(depth (H, W), shading (H, W) in [0, 1]) of a mesh seen from the camera: the
    package's ray caster (`synth.render.render_body`), |cos| of the surface normal."""
    from smpl_depth_ros.synth.camera import Camera
    from smpl_depth_ros.synth.render import render_body
    w, h = size
    cam = Camera(int(w), int(h), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]),
                 float(K[1, 2]), name='bag')
    r = render_body(np.asarray(vertices, np.float64), np.asarray(faces, np.int64),
                    np.zeros(len(vertices), np.int64), cam)
    return r.depth, r.normals_cos


def frame_picture(depth: np.ndarray, seg_rgb: np.ndarray | None, vertices, faces, K,
                  title: str = ''):
    """PIL image: depth | segmentation | fitted mesh (shaded) | mesh over depth."""
    from PIL import Image, ImageDraw

    from smpl_depth_ros.tools.render_panel import colorize_depth
    H, W = depth.shape
    dcol = colorize_depth(depth)
    rdepth, shade = render_mesh(vertices, faces, K, (W, H))
    hit = rdepth > 0
    skin = np.array([235, 190, 150], np.float64)
    mesh = np.full((H, W, 3), 255, np.uint8)
    mesh[hit] = (skin * (0.25 + 0.75 * shade[hit, None])).astype(np.uint8)
    over = dcol.astype(np.float64) * 0.45
    over[hit] = 0.3 * dcol[hit] + 0.7 * mesh[hit]
    seg = seg_rgb if seg_rgb is not None else np.zeros((H, W, 3), np.uint8)
    tiles = [(dcol, 'depth'), (seg, 'segmentation'), (mesh, 'fitted mesh'),
             (over.astype(np.uint8), 'mesh over depth')]
    pad, top = 4, 30
    img = Image.new('RGB', (4 * W + 5 * pad, H + top + pad), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    draw.text((pad, 2), title, fill=(0, 0, 0))
    for k, (tile, name) in enumerate(tiles):
        x = pad + k * (W + pad)
        img.paste(Image.fromarray(np.ascontiguousarray(tile)), (x, top))
        draw.text((x + 2, top - 13), name, fill=(0, 0, 0))
    return img


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n')[0])
    ap.add_argument('--out', default='out/demo', help='output folder (default out/demo)')
    ap.add_argument('--bag', default=str(SAMPLE_BAG), help='bag to process (default: the '
                    'shipped sample)')
    ap.add_argument('--frame', type=int, default=None,
                    help='frame index for frame.png (default: the middle processed frame)')
    ap.add_argument('--device', default='auto', choices=['auto', 'cpu', 'cuda'])
    ap.add_argument('--workers', type=int, default=1)
    ap.add_argument('--make-sample', action='store_true',
                    help='(maintainers) regenerate the shipped sample bag and exit')
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.make_sample:
        print(json.dumps(make_sample_bag()))
        return 0
    from smpl_depth_ros.config import PipelineConfig
    from smpl_depth_ros.offline import BagReadError, ProcessBagError, process_bag
    from smpl_depth_ros.tools.synth_bag import gt_path

    bag, out = Path(args.bag), Path(args.out)
    try:
        summary = process_bag(bag, out, config=PipelineConfig(device=args.device),
                              export_meshes='ply', overwrite=True, workers=args.workers)
    except (ProcessBagError, BagReadError) as e:
        print(f'{PROG}: error: {e}', file=sys.stderr)
        return 1
    res = np.load(out / 'results.npz')
    ok = np.flatnonzero(res['status'] == 'ok')
    figures = dict(frames=summary['frames_read'], processed=summary['processed'],
                   skipped=summary['skipped'], fps=summary['fps'],
                   peak_rss_mb=summary['peak_rss_mb'], device=summary['device'],
                   timings_ms_mean=summary['timings_ms_mean'])
    gt_file = Path(gt_path(str(bag)))
    errors = {}
    if gt_file.exists() and len(ok):
        import trimesh
        gt = np.load(gt_file)
        index = {int(s): i for i, s in enumerate(gt['stamps'])}
        for i in ok:
            s = int(res['stamps'][i])
            if s in index and s not in errors:
                v = trimesh.load(out / 'meshes' / f'{s}.ply', process=False).vertices
                if len(v) == gt['vertices'].shape[1]:
                    errors[s] = float(np.linalg.norm(v - gt['vertices'][index[s]],
                                                     axis=1).mean()) * 1e3
        if errors:
            figures['mean_vertex_error_mm'] = round(float(np.mean(list(errors.values()))), 1)
    picture = None
    if len(ok):
        i = int(ok[len(ok) // 2]) if args.frame is None else int(args.frame)
        if res['status'][i] != 'ok':
            print(f'{PROG}: frame {i} was skipped ({res["status"][i]}); no picture',
                  file=sys.stderr)
        else:
            import trimesh
            stamp = int(res['stamps'][i])
            depth, K = _frame_inputs(bag, stamp)
            seg = _output_image(out / 'bag', '/reconstructor/segmentation', stamp)
            mesh = trimesh.load(out / 'meshes' / f'{stamp}.ply', process=False)
            title = (f'frame {i} (stamp {stamp}): residual {res["residual_m"][i] * 1e3:.0f} mm'
                     + (f', error vs ground truth {errors[stamp]:.0f} mm' if stamp in errors
                        else '') + f'; {summary["fps"]} frames/s on {summary["device"]}')
            picture = out / 'frame.png'
            frame_picture(depth, seg, mesh.vertices, mesh.faces, K, title).save(picture)
    figures['picture'] = str(picture) if picture else None
    (out / 'demo.json').write_text(json.dumps(figures, indent=2) + '\n')
    print(f'\n{PROG}: processed {summary["processed"]}/{summary["frames_read"]} frames of '
          f'{bag} at {summary["fps"]} frames/s (peak RSS {summary["peak_rss_mb"]} MB)')
    if 'mean_vertex_error_mm' in figures:
        print(f'{PROG}: mean per-vertex error against the ground truth: '
              f'{figures["mean_vertex_error_mm"]} mm')
    print(f'{PROG}: output bag   {summary["output_bag"]}')
    print(f'{PROG}: meshes       {summary["meshes"]} ({summary["meshes_exported"]} ply)')
    print(f'{PROG}: results      {summary["results"]}')
    print(f'{PROG}: summary      {os.path.join(out, "summary.json")}')
    if picture:
        print(f'{PROG}: picture      {picture}')
    print(json.dumps(figures))
    return 0 if summary['processed'] else 1


if __name__ == '__main__':
    sys.exit(main())
