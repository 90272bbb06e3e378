"""One run of process_bag: `process_bag()` checks the options, prepares the output
directory, loads the model into a runner (`workers`, `ray_runner`; or takes the one a
batch shares) and makes one pass over the bag (`_BagRun`: copies every message, feeds the
depth frames to the runner, writes outputs, mesh files and diagnostics in input order);
then results.npz (`save_results`) and summary.json, with the work of each worker."""
from __future__ import annotations

import json
import os
import resource
import shutil
import sys
import time
from collections import Counter, deque
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable

import numpy as np

from smpl_depth_ros.config import PipelineConfig
from smpl_depth_ros.offline.bagread import BagInput, Topic, _storage_files, select_topics
from smpl_depth_ros.offline.errors import BagReadError, InterruptedBeforeStart, ProcessBagError
from smpl_depth_ros.offline.params import NODE_OPTIONS
from smpl_depth_ros.offline.workers import (OUTPUTS, Job, Outcome, OutputOptions,
                                            SharedRunner, make_runner, peak_rss_mb)
from smpl_depth_ros.stamps import stamp_to_ns
from smpl_depth_ros.types import InputError

PROG = 'process_bag'
MAX_WAITING_FOR_INFO = 30  # depth frames held for a camera_info that has not come yet
DEFAULT_NS = '/reconstructor'
DIAGNOSTICS_TOPIC = '/diagnostics'
DIAG_T = 'diagnostic_msgs/msg/DiagnosticArray'
TIMING_NAMES = ('preprocess', 'network', 'correspondence', 'fit', 'labels', 'total',
                'outputs')
MESH_FORMATS = ('ply', 'obj', 'glb')


class _Progress:
    """tqdm on a terminal, a log line every `period` seconds otherwise."""

    def __init__(self, total: int | None, enabled: bool, log: Callable[[str], None],
                 period: float = 10.0):
        self.total, self.n, self.log, self.period = total, 0, log, period
        self.t0 = self.last = time.monotonic()
        self.bar = None
        self.enabled = enabled
        if enabled and sys.stderr.isatty():
            from tqdm import tqdm
            try:  # some pseudo-terminals report 0 columns: tqdm would draw nothing
                cols = os.get_terminal_size(sys.stderr.fileno()).columns
            except OSError:
                cols = 0
            self.bar = tqdm(total=total, desc=PROG, unit='frame',
                            ncols=None if cols > 0 else 100)

    def update(self, k: int = 1):
        self.n += k
        if self.bar is not None:
            self.bar.update(k)
            return
        now = time.monotonic()
        if self.enabled and now - self.last >= self.period:
            self.last = now
            rate = self.n / max(now - self.t0, 1e-9)
            msg = f'{self.n} frames'
            if self.total:
                left = max(self.total - self.n, 0) / max(rate, 1e-9)
                msg = (f'{self.n}/{self.total} frames ({100 * self.n / self.total:.0f} %), '
                       f'ETA {left:.0f} s')
            self.log(f'{msg}, {rate:.2f} frames/s')

    def close(self):
        if self.bar is not None:
            self.bar.close()


def _prepare_output_dir(out: Path, inputs: Path, overwrite: bool, export_meshes: bool = False,
                        log=None) -> None:
    """Check OUT and, with `overwrite`, remove the products this run writes (a symlink
    among them is unlinked, its target left alone); an earlier run's meshes/ stays when
    this run exports none (and is named in the log)."""
    products = ('bag', 'results.npz', 'summary.json') + (('meshes',) if export_meshes else ())
    out_abs, in_abs = out.resolve(), inputs.resolve()
    if out_abs == in_abs or in_abs.is_relative_to(out_abs) or out_abs.is_relative_to(in_abs):
        raise ProcessBagError(f'output directory {out} overlaps the input bag {inputs}')
    if out.exists() and not out.is_dir():
        raise ProcessBagError(f'output path {out} exists and is not a directory')
    if out.exists():
        present = [p for p in products if (out / p).exists() or (out / p).is_symlink()]
        if present and not overwrite:
            raise ProcessBagError(f'output directory {out} already holds '
                                  f'{", ".join(present)}; pass --overwrite to replace them')
        for p in present:  # only our own products are removed
            q = out / p
            if q.is_symlink() or not q.is_dir():
                q.unlink()
            else:
                shutil.rmtree(q)
        if not export_meshes and (out / 'meshes').exists() and log is not None:
            log(f'{out / "meshes"} is left as it is (from an earlier run: this run exports '
                'no meshes)')
    out.mkdir(parents=True, exist_ok=True)


def process_bag(bag: str | Path, out_dir: str | Path, *, config: PipelineConfig | None = None,
                options: dict[str, Any] | None = None, depth_topic: str | None = None,
                info_topic: str | None = None, storage: str = 'mcap', compress: bool = False,
                export_meshes: str | None = None, workers: int = 1, chunk_size: int = 32,
                overwrite: bool = False, output_ns: str = DEFAULT_NS, progress: bool = True,
                log: Callable[[str], None] | None = None, reconstructor=None,
                ray: str | None = None, shared: SharedRunner | None = None
                ) -> dict[str, Any]:
    """Process every depth frame of `bag` into `out_dir` (see the module docstring).

    Args:
        bag: rosbag2 directory, or one .mcap / .db3 file.
        out_dir: output directory (created; its previous products need `overwrite`).
        config: PipelineConfig (default: the embedded defaults).
        options: node output options (`NODE_OPTIONS` names: publish_*, mesh_decimation,
            mesh_lifetime_s).
        depth_topic, info_topic: None = auto-detect.
        storage: output bag storage, 'mcap' or 'sqlite3'; compress: zstd chunks (MCAP).
        export_meshes: None or 'ply' | 'obj' | 'glb'.
        workers: processes (1 = this process, tracking over the whole bag), or Ray actors.
        chunk_size: frames per worker task (tracking restarts at each chunk).
        output_ns: namespace of the output topics (the node's '~').
        progress: show progress (tqdm on a TTY, else log lines).
        log: where messages go (default: stderr).
        reconstructor: an already loaded `pipeline.Reconstructor` to use instead of loading
            one (workers=1 only; it gets `config`, except the device it was built for).
        ray: None, or run the workers on Ray: '' a local Ray (started and shut down
            here), else the address of a running cluster ('HOST:6379').
        shared: the runner of a batch of bags (made by the first run, kept open after
            each run; the caller closes it). None: a runner for this run alone.

    Returns:
        The summary dict (also in out_dir/summary.json). A damaged bag sets 'error' (and
        'error_file', 'error_position'); an interruption sets 'interrupted'.

    Raises:
        ProcessBagError: unusable input or options (nothing processed).
    """
    log = log or (lambda m: print(f'{PROG}: {m}', file=sys.stderr, flush=True))
    config = config or PipelineConfig()
    opts_d = dict(NODE_OPTIONS, **(options or {}))
    if storage not in ('mcap', 'sqlite3'):
        raise ProcessBagError(f"storage must be 'mcap' or 'sqlite3', got {storage!r}")
    if export_meshes not in (None, *MESH_FORMATS):
        raise ProcessBagError(f'--export-meshes must be one of {MESH_FORMATS}')
    if workers < 1:
        raise ProcessBagError('--workers must be >= 1')
    if compress and storage != 'mcap':
        raise ProcessBagError('--compress needs --storage mcap')
    if ray is not None:
        from smpl_depth_ros.offline.ray_runner import check_ray
        check_ray()
    output_ns = '/' + output_ns.strip('/')
    bag, out_dir = Path(bag), Path(out_dir)
    t_start = time.perf_counter()

    with BagInput(bag) as src:
        if src.recovered:
            log(f'cannot open {bag} normally ({src.open_error}); reading its readable part')
        depth_topic, info_topic = select_topics(src.topics, depth_topic, info_topic,
                                                exclude_prefix=output_ns)
        out_topics = {k: suffix if suffix.startswith('/') else f'{output_ns}/{suffix}'
                      for k, (suffix, _) in OUTPUTS.items()}
        # /tf is shared: a recording's own transforms and ours go to the same topic.
        clash = sorted({t.topic for t in src.topics} & {
            v for k, v in out_topics.items() if not OUTPUTS[k][0].startswith('/')})
        if clash:
            raise ProcessBagError(f'the bag already has output topic(s) {", ".join(clash)} '
                                  '(an output bag?); pass --output-ns to write elsewhere')
        created = not out_dir.exists()
        _prepare_output_dir(out_dir, bag, overwrite, bool(export_meshes), log)
        mesh_dir = out_dir / 'meshes'
        if export_meshes:
            mesh_dir.mkdir()
        opts = OutputOptions(**opts_d, export_meshes=export_meshes)
        n_depth = sum(t.count for t in src.topics if t.topic == depth_topic) if all(
            t.count is not None for t in src.topics if t.topic == depth_topic) else None
        t_load = time.perf_counter()
        try:
            # The message inside: a Ctrl-C as soon as it is out counts as during loading.
            where = '' if ray is None else f' on Ray at {ray}' if ray else ' on a local Ray'
            log(f"depth '{depth_topic}' ({n_depth if n_depth is not None else '?'} frames), "
                f"camera_info '{info_topic}'; " + (
                    'the model is loaded' if shared is not None and shared.runner else
                    f'loading the model on {config.device}') +
                f' ({workers} worker{"s" if workers > 1 else ""}{where})')

            def make():
                return make_runner(config, opts, workers, chunk_size, ray, reconstructor, log)
            runner = shared.get(make) if shared is not None else make()
            runner.stats.clear()
        except KeyboardInterrupt:
            # Ctrl-C (or SIGTERM) while the model loads: nothing was processed; leave no
            # empty output folder behind.
            for d in ((mesh_dir,) if export_meshes else ()) + ((out_dir,) if created else ()):
                if d.is_dir() and not any(d.iterdir()):
                    d.rmdir()
            raise InterruptedBeforeStart('interrupted while loading the model: no frame '
                                         'was processed and nothing was written') from None
        load_s = time.perf_counter() - t_load
        try:
            run = _BagRun(src, out_dir / 'bag', storage, compress, runner, config,
                          depth_topic, info_topic, out_topics, progress, log, n_depth,
                          mesh_dir if export_meshes else None, keep_runner=shared is not None)
            t_loop, cpu_loop = time.perf_counter(), time.process_time()
            run.run()
        except BaseException:  # a runner in an unknown state is not used again
            if shared is not None:
                shared.discard(interrupted=True)
            else:
                runner.close()
            raise
        if shared is not None and run.interrupted:
            shared.discard(interrupted=True)
        loop_s = time.perf_counter() - t_loop
        # This process's CPU time over the pass (all threads): with workers, the cost of
        # reading, ordering and writing, which bounds the rate any number of workers gets.
        driver_cpu_s = time.process_time() - cpu_loop

    rows = run.rows
    results_path = out_dir / 'results.npz'
    save_results(results_path, rows, run.bag_times, run.duplicate, run.resets, runner.info,
                 config)
    ok = [o for o in rows if o.status == 'ok']
    mean_t = {k: round(float(np.mean([o.timings_ms.get(k, np.nan) for o in ok])), 2)
              for k in TIMING_NAMES} if ok else {}
    error = run.error
    per_worker = runner.stats.summary()
    peaks = [w['peak_rss_mb'] for w in per_worker.values() if 'peak_rss_mb' in w]
    summary = {
        'input': str(bag), 'output_dir': str(out_dir), 'output_bag': str(out_dir / 'bag'),
        'storage': storage, 'depth_topic': depth_topic, 'info_topic': info_topic,
        'frames_read': len(rows), 'processed': len(ok),
        'skipped': dict(sorted(run.skipped.items())),
        'skipped_total': int(sum(run.skipped.values())),
        'duplicates': int(sum(run.duplicate)),
        'tracking_resets_backwards': int(sum(run.resets)),
        'tracked': sum(1 for o in ok if o.tracked),
        'timings_ms_mean': mean_t,
        'fps': round(len(rows) / loop_s, 3) if loop_s > 0 else None,
        'processing_s': round(loop_s, 2), 'load_s': round(load_s, 2),
        'driver_cpu_s': round(driver_cpu_s, 2),
        'wall_s': round(time.perf_counter() - t_start, 2),
        'peak_rss_mb': peak_rss_mb(),
        'peak_rss_workers_mb': (max(peaks, default=None) if ray is not None else
                                peak_rss_mb(resource.RUSAGE_CHILDREN) if workers > 1 else None),
        'workers': workers, 'device': runner.info['device'],
        'net_precision': runner.info['net_precision'], 'body': runner.info['body'],
        'tracking': config.tracking,
        'messages_written': dict(sorted(run.n_written.items())),
        'meshes': str(mesh_dir) if export_meshes else None,
        'meshes_exported': sum(len(o.mesh_files) for o in rows),
        'results': str(results_path),
        'recovered_damaged_input': src.recovered,
        'error': str(error) if error else None,
        'error_file': error.path if error else None,
        'error_position': error.position if error else None,
        'interrupted': run.interrupted,
        'ray': None if ray is None else ray or 'local',
        'per_worker': per_worker,
    }
    assert summary['frames_read'] == summary['processed'] + summary['skipped_total']
    if workers > 1 or ray is not None:
        for line in runner.stats.lines():
            log(line)
    (out_dir / 'summary.json').write_text(json.dumps(summary, indent=2) + '\n')
    return summary


class _BagRun:
    """One pass over the bag: copies every message, turns each depth frame into a job or
    a skip record, and writes outputs in input order through a reorder queue (frames done
    by workers come back later than the messages that follow them)."""

    def __init__(self, src: BagInput, bag_out: Path, storage: str, compress: bool, runner,
                 config: PipelineConfig, depth_topic: str, info_topic: str,
                 out_topics: dict[str, str], progress: bool, log, n_depth: int | None,
                 mesh_dir: Path | None = None, keep_runner: bool = False):
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        from smpl_depth_ros.ros import adapters as A
        self.A, self.src, self.runner, self.config, self.log = A, src, runner, config, log
        self.mesh_dir, self.keep_runner = mesh_dir, keep_runner  # keep: a batch's runner
        self.info = runner.info
        self.depth_topic, self.info_topic, self.out_topics = depth_topic, info_topic, out_topics
        self.factory = A.rosbags_factory()
        self.jazzy = self.factory.typestore
        self.node_name = out_topics['mesh'].rsplit('/', 2)[-2] or 'reconstructor'
        self.writer = Writer(bag_out, version=9, storage_plugin=StoragePlugin.MCAP if
                             storage == 'mcap' else StoragePlugin.SQLITE3)
        if compress:
            self.writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self.writer.open()
        try:
            self._connections()
        except BaseException:
            self.writer.close()
            raise
        self.cams: dict[str, Any] = {}           # frame_id -> (CameraIntrinsics, Lens) | InputError
        self.told_lens: set[str] = set()         # frame_ids whose lens notice was logged
        self.waiting: deque = deque()            # depth frames waiting for a camera_info
        self.seen: dict[int, int] = {}           # header stamp -> times seen
        self.last_stamp: int | None = None
        self.rows: list[Outcome] = []
        self.bag_times: list[int] = []
        self.duplicate: list[bool] = []
        self.resets: list[bool] = []
        self.skipped = Counter()
        self.n_written = Counter()
        self.ready: dict[int, Outcome] = {}
        self.queue: deque = deque()              # ('raw', conn, t, data) | ('frame', i, t)
        self.diag_last: int | None = None
        self.diag_problems = Counter()
        self.error: BagReadError | None = None
        self.interrupted = False
        self.progress = _Progress(n_depth, progress, log)

    def _connections(self):
        """Output connections: the inputs (same definitions, QoS), then the node's."""
        w, src = self.writer, self.src
        self.conn_in: dict[int, Any] = {}
        added: dict[tuple, Any] = {}
        for t in src.topics:
            key = (t.topic, t.msgtype)
            if key not in added:
                if t.msgtype in src.typestore.fielddefs:
                    added[key] = w.add_connection(t.topic, t.msgtype, typestore=src.typestore,
                                                  offered_qos_profiles=t.qos)
                else:  # no usable definition: keep what the bag carries
                    added[key] = w.add_connection(
                        t.topic, t.msgtype, msgdef=t.msgdef or '',
                        rihs01=t.digest or 'RIHS01_' + '0' * 64, offered_qos_profiles=t.qos)
            self.conn_in[t.id] = added[key]
        self.conn_out = {k: added.get((self.out_topics[k], OUTPUTS[k][1])) or
                         w.add_connection(self.out_topics[k], OUTPUTS[k][1],
                                          typestore=self.jazzy) for k in OUTPUTS}
        self.conn_diag = added.get((DIAGNOSTICS_TOPIC, DIAG_T)) or w.add_connection(
            DIAGNOSTICS_TOPIC, DIAG_T, typestore=self.jazzy)

    # -- the pass ----------------------------------------------------------------------
    def run(self):
        try:
            try:
                for topic, t_bag, raw in self.src.messages():
                    self.queue.append(('raw', self.conn_in[topic.id], t_bag, raw))
                    if topic.topic == self.info_topic:
                        self._on_info(topic, raw)
                    elif topic.topic == self.depth_topic:
                        self.queue.append(('frame', len(self.bag_times), t_bag))
                        self._on_depth(topic, t_bag, raw)
                    self._drain(block=False)
            except BagReadError as e:
                self.error = e
                self.log(f'error: {e}; keeping the {len(self.bag_times)} depth frame(s) read '
                         'before it')
            while self.waiting:
                self._give_up_waiting('by the end of the bag')
            self.runner.flush(self.ready)
            self._drain(block=True)
        except KeyboardInterrupt:
            self.interrupted = True
            self.log('interrupted: closing the output bag with the frames done so far')
            self._close_runner(interrupted=True)
            self._drain(block=False, abandon=True)
        finally:
            self.progress.close()
            self._close_runner()
            self.writer.close()
            from smpl_depth_ros.bagio import mcap_write_chunk_crcs
            for f in _storage_files(Path(self.writer.path)) if self.writer.path.exists() else ():
                if f.suffix == '.mcap':  # chunk CRCs, so that damage is detectable
                    mcap_write_chunk_crcs(f)

    def _close_runner(self, interrupted: bool = False):
        if self.runner is not None and (interrupted or not self.keep_runner):
            runner, self.runner = self.runner, None
            try:
                runner.close(interrupted)
            except Exception:  # noqa: BLE001 - a dead worker pool at the end
                pass

    def _drain(self, block: bool, abandon: bool = False):
        """Write the queue head up to the first frame whose outcome is not in yet
        (`block`: wait for it; `abandon`: account for it as 'interrupted')."""
        while self.queue:
            item = self.queue[0]
            if item[0] == 'raw':
                self.writer.write(item[1], item[2], item[3])
                self.queue.popleft()
                continue
            idx = item[1]
            if idx not in self.ready and abandon:
                self.ready[idx] = Outcome(idx, 'interrupted', 'the run was interrupted')
            if idx not in self.ready:
                self.runner.poll(self.ready, block)
                if idx not in self.ready:
                    if not block:
                        return
                    if not self.runner.pending():  # cannot happen; never wait forever
                        self.ready[idx] = Outcome(idx, 'internal', 'frame lost by the runner')
                    self.runner.flush(self.ready)
                    continue
            self.queue.popleft()
            self._emit(self.ready.pop(idx), item[2])

    # -- inputs --------------------------------------------------------------------------
    def _on_info(self, topic: Topic, raw):
        try:
            msg = self.src.typestore.deserialize_cdr(raw, topic.msgtype)
        except Exception:  # noqa: BLE001 - an undecodable camera_info is just ignored
            return
        fid = str(msg.header.frame_id)
        try:
            cam = self.A.camera_info_intrinsics(msg)
            lens = cam.lens(self.depth_topic)
            self.cams[fid] = (cam, lens)
            if lens is not None and fid not in self.told_lens:
                self.told_lens.add(fid)
                self.log(lens.notice(fid, self.config.undistort))
        except InputError as e:
            self.cams[fid] = e
        # Frames that came before their camera_info go now, in order.
        ready = [w for w in self.waiting if w[3] == fid]
        if ready:
            self.waiting = deque(w for w in self.waiting if w[3] != fid)
            for w in ready:
                self._submit(*w)

    def _give_up_waiting(self, why: str):
        index, _msg, stamp, frame_id, _name = self.waiting.popleft()
        others = ', '.join(f"'{k}'" for k in self.cams) or 'none'
        self._skip(index, 'no_camera_info', f"no camera_info for frame_id '{frame_id}' on "
                   f"'{self.info_topic}' {why} (camera_info frame_ids seen: {others})",
                   stamp, frame_id)

    def _skip(self, index: int, reason: str, message: str, stamp_ns: int, frame_id: str):
        self.ready[index] = Outcome(index, reason, message, stamp_ns, frame_id)

    def _on_depth(self, topic: Topic, t_bag: int, raw):
        """As the node's depth callback: pair with camera_info, check, convert, submit."""
        index = len(self.bag_times)
        self.bag_times.append(t_bag)
        self.duplicate.append(False)
        self.resets.append(False)
        try:
            msg = self.src.typestore.deserialize_cdr(raw, topic.msgtype)
            stamp, frame_id = stamp_to_ns(msg.header.stamp), str(msg.header.frame_id)
        except Exception as e:  # noqa: BLE001
            self._skip(index, 'deserialize', f'cannot decode the Image message: {e}', -1, '')
            return
        dup = stamp in self.seen
        self.seen[stamp] = self.seen.get(stamp, 0) + 1
        self.duplicate[-1] = dup
        name = str(stamp) + (f'_{self.seen[stamp] - 1}' if dup else '')
        if frame_id not in self.cams:
            # Its camera_info may come next (recorders do not order the two topics).
            self.waiting.append((index, msg, stamp, frame_id, name))
            if len(self.waiting) > MAX_WAITING_FOR_INFO:
                self._give_up_waiting(f'within {MAX_WAITING_FOR_INFO} depth frames')
            return
        self._submit(index, msg, stamp, frame_id, name)

    def _submit(self, index: int, msg, stamp: int, frame_id: str, name: str):
        max_pixels = self.config.max_image_pixels
        try:
            cam = self.cams[frame_id]
            if isinstance(cam, InputError):
                raise cam
            cam, lens = cam
            K, (cw, ch) = cam.K, cam.size
            w, h = int(msg.width), int(msg.height)
            if h * w > max_pixels:
                raise InputError('too_large', f'depth image {w}x{h} has {w * h} pixels, more '
                                 f'than max_image_pixels={max_pixels}')
            if cw and ch and (cw, ch) != (w, h):
                raise InputError('size_mismatch', f'depth image is {w}x{h} but its '
                                 f'camera_info says {cw}x{ch}')
            depth = self.A.image_to_depth(msg, max_pixels=max_pixels)
        except InputError as e:
            self._skip(index, e.reason, str(e), stamp, frame_id)
            return
        reset = self.last_stamp is not None and stamp < self.last_stamp
        self.resets[index] = reset
        self.last_stamp = stamp
        self.runner.submit(Job(index, stamp, frame_id, depth, K, reset, name, lens),
                           self.ready)

    # -- outputs -------------------------------------------------------------------------
    def _diag(self, t_bag: int, stamp_ns: int, frame_id: str, statuses):
        A = self.A
        hdr = A.make_header(None, self.factory, stamp_ns=max(stamp_ns, 0), frame_id=frame_id)
        msg = A.diagnostics(hdr, statuses, msgs=self.factory)
        self.writer.write(self.conn_diag, t_bag, bytes(self.jazzy.serialize_cdr(msg, DIAG_T)))
        self.n_written[DIAGNOSTICS_TOPIC] += 1

    def _write_meshes(self, o: Outcome):
        """The frame's mesh files; a frame whose files cannot be written (e.g. a full
        disk) is not written at all ('internal')."""
        try:
            for name, data in o.meshes:
                path = self.mesh_dir / name
                path.write_bytes(data)
                o.mesh_files.append(str(path))
        except Exception as e:  # noqa: BLE001
            o.status, o.message = 'internal', f'writing outputs: {type(e).__name__}: {e}'
            o.outputs, o.params = [], None
        o.meshes = []

    def _emit(self, o: Outcome, t_bag: int):
        """Write one frame's outputs (its input's bag time) and diagnostics, in order: a
        WARN entry per skipped frame, a processing summary per second of bag time."""
        A = self.A
        if o.meshes:
            self._write_meshes(o)
        for key, data in o.outputs:
            self.writer.write(self.conn_out[key], t_bag, data)
            self.n_written[self.out_topics[key]] += 1
        o.outputs = []
        if o.status != 'ok':
            self.skipped[o.status] += 1
            self.diag_problems[o.status] += 1
            self._diag(t_bag, o.stamp_ns, o.frame_id, [(
                f'{self.node_name}: input', A.WARN, f'[{o.status}] {o.message}',
                {'reason': o.status, 'count': self.skipped[o.status], 'frame_id': o.frame_id})])
        self.rows.append(o)
        if self.diag_last is None or t_bag - self.diag_last >= 1_000_000_000:
            self.diag_last = t_bag
            n, bad = len(self.rows), sum(self.skipped.values())
            values = {'frames_read': n, 'frames_processed': n - bad, 'frames_rejected': bad,
                      'model': self.info['body'], 'device': self.info['device'],
                      'tracking': self.config.tracking, 'source': 'process_bag'}
            values.update({f'errors_{k}': v for k, v in sorted(self.skipped.items())})
            problems = sum(self.diag_problems.values())
            level = A.WARN if problems else A.OK
            self._diag(t_bag, o.stamp_ns, o.frame_id, [(
                f'{self.node_name}: processing', level,
                f'{problems} frame(s) rejected in the last period' if problems else 'ok',
                values)])
            self.diag_problems = Counter()
        self.progress.update()


def save_results(path: Path, rows: list[Outcome], bag_times, duplicate, resets, info: dict,
                 config: PipelineConfig) -> None:
    """results.npz, one row per depth frame read, in input order:

    stamps (N,) int64 header stamp ns (-1: undecodable); bag_times (N,) int64;
    status (N,) str ('ok' or the skip reason); message (N,) str; frame_id (N,) str;
    duplicate, tracking_reset, tracked (N,) bool; persons (N,) int;
    pose (N, P, 3), shape (N, S), global_orient (N, 3), transl (N, 3) float32 (NaN when
    skipped); residual_m (N,) float32; num_points (N,) int; timings_ms (N, T) float32 with
    timing_names (T,); joint_names (P,), shape_names (S,); body, config (JSON).
    """
    n, P, S = len(rows), info['num_pose'], info['num_shape']
    pose = np.full((n, P, 3), np.nan, np.float32)
    shape = np.full((n, S), np.nan, np.float32)
    go = np.full((n, 3), np.nan, np.float32)
    tr = np.full((n, 3), np.nan, np.float32)
    for i, o in enumerate(rows):
        if o.params is not None:
            pose[i] = o.params['pose'].reshape(P, 3)
            shape[i] = o.params['shape'].reshape(S)
            go[i] = o.params['global_orient'].reshape(3)
            tr[i] = o.params['transl'].reshape(3)
    cfg = asdict(config)
    np.savez_compressed(
        path, stamps=np.array([o.stamp_ns for o in rows], np.int64),
        bag_times=np.array(bag_times, np.int64),
        status=np.array([o.status for o in rows], dtype=str),
        message=np.array([o.message for o in rows], dtype=str),
        frame_id=np.array([o.frame_id for o in rows], dtype=str),
        duplicate=np.array(duplicate, bool), tracking_reset=np.array(resets, bool),
        tracked=np.array([o.tracked for o in rows], bool),
        persons=np.array([o.persons for o in rows], np.int32),
        pose=pose, shape=shape, global_orient=go, transl=tr,
        residual_m=np.array([o.residual_m for o in rows], np.float32),
        num_points=np.array([o.num_points for o in rows], np.int32),
        timings_ms=np.array([[o.timings_ms.get(k, np.nan) for k in TIMING_NAMES]
                             for o in rows], np.float32).reshape(n, len(TIMING_NAMES)),
        timing_names=np.array(TIMING_NAMES), joint_names=np.array(info['joint_names']),
        shape_names=np.array(info['shape_names']), body=np.array(info['body']),
        config=np.array(json.dumps(cfg)))
