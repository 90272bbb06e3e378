"""process_bag: run the reconstructor over a recorded ROS 2 bag, every frame accounted for.

The command line (`main`, console script `process_bag`): options and the node's parameters
(``--params-file``, ``-p``) into `process_bag()`, SIGTERM taken as Ctrl-C, the summary
JSON on stdout, and the exit code. Several bags (or a folder of bags): one output folder
per bag under ``--out``, one runner (processes, Ray actors) for them all, a JSON line per
bag, the worst exit code. What a run reads and writes: the package docstring.
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from dataclasses import replace
from pathlib import Path

from smpl_depth_ros import params as P
from smpl_depth_ros.offline.bagread import bags_in
from smpl_depth_ros.offline.errors import BagReadError, InterruptedBeforeStart, ProcessBagError
from smpl_depth_ros.offline.params import config_from_params
from smpl_depth_ros.offline.run import DEFAULT_NS, MESH_FORMATS, PROG, process_bag
from smpl_depth_ros.offline.workers import SharedRunner

EXIT_OK, EXIT_USAGE, EXIT_DAMAGED, EXIT_INTERRUPTED = 0, 1, 3, 130
# The exit code of a batch: its worst bag's, from best to worst.
SEVERITY = (EXIT_OK, EXIT_DAMAGED, EXIT_USAGE, EXIT_INTERRUPTED)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n')[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog='Exit codes: 0 done, 1 unusable input/options, '
                                        '3 damaged bag (partial results kept), 130 interrupted; '
                                        'several bags: the worst of theirs (130, 1, 3, 0).')
    ap.add_argument('bag', nargs='*', help='rosbag2 directory, or a .mcap / .db3 file; '
                    'several, or a folder of bags: one output folder per bag under --out')
    ap.add_argument('--out', required=True, help='output directory (several bags: the '
                    'folder of their output folders, named after the bags)')
    ap.add_argument('--depth-topic', default=None, help='sensor_msgs/Image depth topic '
                    '(default: the only candidate)')
    ap.add_argument('--info-topic', default=None, help='sensor_msgs/CameraInfo topic '
                    '(default: the only candidate)')
    ap.add_argument('--params-file', default=None,
                    help="the node's parameter YAML (e.g. config/reconstructor.yaml)")
    ap.add_argument('-p', '--param', action='append', default=[], metavar='NAME=VALUE',
                    help="override one node parameter, e.g. -p fit.iterations=10")
    ap.add_argument('--device', default=None, choices=['auto', 'cpu', 'cuda'])
    ap.add_argument('--no-tracking', action='store_true',
                    help='fit every frame cold (no warm start from the previous one)')
    ap.add_argument('--storage', default='mcap', choices=['mcap', 'sqlite3'],
                    help='output bag storage')
    ap.add_argument('--compress', action='store_true', help='zstd-compressed MCAP chunks')
    ap.add_argument('--export-meshes', default=None, choices=MESH_FORMATS,
                    help='also write one mesh file per frame (named by stamp)')
    ap.add_argument('--workers', type=int, default=1, help='processes, or Ray actors '
                    'with --ray (default 1)')
    ap.add_argument('--ray', nargs='?', const='', default=None, metavar='ADDRESS',
                    help='run the workers on Ray: a local Ray (loopback only), or the '
                    'running cluster at ADDRESS (HOST:6379); write --ray=ADDRESS, or '
                    'put --ray after the bags')
    ap.add_argument('--chunk-size', type=int, default=32,
                    help='frames per worker task; tracking restarts at each (default 32)')
    ap.add_argument('--output-ns', default=DEFAULT_NS,
                    help=f'namespace of the output topics (default {DEFAULT_NS})')
    ap.add_argument('--overwrite', action='store_true',
                    help='replace the outputs of a previous run in --out')
    ap.add_argument('--quiet', action='store_true', help='no progress, no log lines')
    return ap


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv=None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    if args.ray and Path(args.ray).exists():  # `--ray BAG ...`: BAG is no address
        args.bag.insert(0, args.ray)
        args.ray = ''
    if not args.bag:
        ap.error('the following arguments are required: bag')
    main_thread = threading.current_thread() is threading.main_thread()
    # SIGTERM as Ctrl-C: the output bag is closed properly and the summary written.
    previous = signal.signal(signal.SIGTERM, _interrupt) if main_thread else None
    try:
        return _run_cli(args)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def batch_outputs(paths: list[str], out: str) -> list[tuple[Path, Path]] | None:
    """(bag, its output folder) for a batch: each path a bag or a folder of bags, each
    bag's output folder under `out`, named after it. None for one path that is not a
    folder of bags: one run, `out` its output folder."""
    if len(paths) == 1 and not bags_in(Path(paths[0])):
        return None
    bags = [b for p in map(Path, paths) for b in (bags_in(p) or [p])]
    names: dict[str, list[Path]] = {}
    for b in bags:
        names.setdefault(b.stem if b.is_file() else b.name, []).append(b)
    same = [f'{", ".join(map(str, bs))} -> {n}' for n, bs in names.items() if len(bs) > 1]
    if same:
        raise ProcessBagError(f'bags with the same name would share an output folder: '
                              f'{"; ".join(same)}')
    return [(b, Path(out) / (b.stem if b.is_file() else b.name)) for b in bags]


def _run_cli(args) -> int:
    log = (lambda m: None) if args.quiet else (
        lambda m: print(f'{PROG}: {m}', file=sys.stderr, flush=True))
    try:
        params = P.load_params_file(args.params_file) if args.params_file else {}
        params.update(P.parse_overrides(args.param))
        config, options, ignored = config_from_params(params)
        if args.device:
            config = replace(config, device=args.device)
        if args.no_tracking:
            config = replace(config, tracking=False)
        if args.ray is not None:
            from smpl_depth_ros.offline.ray_runner import check_ray
            check_ray()
        batch = batch_outputs(args.bag, args.out)
    except (ProcessBagError, P.ParamError) as e:
        print(f'{PROG}: error: {e}', file=sys.stderr)
        return EXIT_USAGE
    if ignored:
        log(f'ignoring live-only parameter(s): {", ".join(sorted(ignored))}')
    if batch is None:
        code, summary = _run_one(args, args.bag[0], args.out, config, options, log, None)
        if summary is not None:
            print(json.dumps(summary))
        return code
    shared, worst = SharedRunner(), EXIT_OK
    try:
        for bag, out in batch:
            log(f'{bag} -> {out}')
            code, summary = _run_one(args, bag, out, config, options, log, shared)
            print(json.dumps(summary if summary is not None else {
                'input': str(bag), 'output_dir': str(out), 'exit_code': code}), flush=True)
            worst = max(worst, code, key=SEVERITY.index)
            if code == EXIT_INTERRUPTED:
                break
    finally:
        shared.close()
    return worst


def _run_one(args, bag, out, config, options, log, shared) -> tuple[int, dict | None]:
    """One bag: (exit code, its summary; None when nothing was processed)."""
    try:
        summary = process_bag(
            bag, out, config=config, options=options, depth_topic=args.depth_topic,
            info_topic=args.info_topic, storage=args.storage, compress=args.compress,
            export_meshes=args.export_meshes, workers=args.workers,
            chunk_size=args.chunk_size, overwrite=args.overwrite, output_ns=args.output_ns,
            progress=not args.quiet, log=log, ray=args.ray, shared=shared)
    except (ProcessBagError, P.ParamError, BagReadError) as e:
        print(f'{PROG}: error: {e}', file=sys.stderr)
        return EXIT_USAGE, None
    except InterruptedBeforeStart as e:
        print(f'{PROG}: {e}', file=sys.stderr)
        return EXIT_INTERRUPTED, None
    except KeyboardInterrupt:  # before the bag was opened
        print(f'{PROG}: interrupted before any frame was processed', file=sys.stderr)
        return EXIT_INTERRUPTED, None
    except (RuntimeError, ValueError, FileNotFoundError) as e:  # model/device problems
        print(f'{PROG}: error: {type(e).__name__}: {e}', file=sys.stderr)
        return EXIT_USAGE, None
    if summary['interrupted']:
        return EXIT_INTERRUPTED, summary
    return (EXIT_DAMAGED if summary['error'] else EXIT_OK), summary
