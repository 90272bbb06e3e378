"""Per-frame work, in this process or in worker processes: a `Job` (one depth frame
ready for the pipeline) in, an `Outcome` (processed or skipped, with its serialised output
messages) out. `FrameProcessor` is one Reconstructor plus the node's message builders;
a runner feeds it jobs.

The runner interface, as `run._BagRun` drives it (`_InlineRunner`, `_PoolRunner`,
`ray_runner.RayRunner`; `make_runner` picks one; a new runner implements all of it):

* ``info``: `FrameProcessor.info()` of the loaded model (body, device, joint and shape
  names, sizes), set by the constructor, which loads the model (a Ctrl-C while it does
  propagates as KeyboardInterrupt);
* ``submit(job, ready)``: take one job; its `Outcome` goes into ``ready`` (index ->
  Outcome) now or on a later call of any method below;
* ``poll(ready, block)``: put the outcomes that are done into ``ready``; ``block``: wait
  for the oldest work in flight first;
* ``pending()``: the number of jobs submitted whose outcomes are not in ``ready`` yet;
* ``flush(ready)``: start what is buffered (a partial chunk), at the end of the bag and
  whenever the caller waits for a frame; it may block to bound the work in flight;
* ``close(interrupted=False)``: release the workers; ``interrupted``: without waiting for
  the work in progress;
* ``stats``: a `WorkerStats` (frames, busy time, failures per worker), which the caller
  clears at the start of each bag;
* ``restart()``: before the next bag of a batch (`SharedRunner`): as freshly loaded.

Every submitted job ends as exactly one `Outcome` in ``ready`` (work lost with a worker:
status 'internal' for each of its frames); outcomes may come in any order, the caller
writes them in input order. Tracking lives in the runner: `_InlineRunner` tracks across
the whole bag, the others (`_PoolRunner` here, `ray_runner.RayRunner` on a Ray cluster)
run contiguous chunks through `run_chunk`, which restarts the processor at each chunk, so
that a chunk's result does not depend on which worker runs it or what that worker did
before. Jobs and outcomes are plain picklable data (numpy arrays, strings, bytes), so they
can travel to other processes and machines; mesh files come back as bytes, written by the
caller.
"""
from __future__ import annotations

import io
import os
import resource
import sys
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from smpl_depth_ros.config import PipelineConfig
from smpl_depth_ros.rectify import Lens
from smpl_depth_ros.ros.outputs import TOPICS, FrameOutputs
from smpl_depth_ros.config import OutputOptions as MessageOptions
from smpl_depth_ros.types import InputError

# Output key -> (topic under the namespace, or absolute; message type), as the node
# publishes (ros.outputs).
OUTPUTS = TOPICS


@dataclass
class Job:
    """A depth frame ready for the pipeline."""

    index: int
    stamp_ns: int
    frame_id: str
    depth: np.ndarray
    K: np.ndarray
    reset: bool = False        # reset tracking first (time went backwards)
    mesh_name: str = ''        # file stem for --export-meshes
    lens: Lens | None = None    # the camera's lens, when it distorts (rectify)


@dataclass
class Outcome:
    """What happened to one depth frame (processed or skipped)."""

    index: int
    status: str                       # 'ok' or the skip reason
    message: str = ''
    stamp_ns: int = -1
    frame_id: str = ''
    persons: int = 0
    params: dict | None = None        # first person: pose, shape, global_orient, transl
    residual_m: float = float('nan')
    num_points: int = 0
    tracked: bool = False
    timings_ms: dict = field(default_factory=dict)
    outputs: list = field(default_factory=list)   # (output key, CDR bytes)
    meshes: list = field(default_factory=list)    # (file name, bytes) for --export-meshes
    mesh_files: list = field(default_factory=list)  # the paths written, by the caller


@dataclass(frozen=True)
class OutputOptions(MessageOptions):
    """How outputs are built (the node's publish_* and mesh parameters, ros.outputs) and
    the format of the exported meshes (None: none)."""

    export_meshes: str | None = None


@dataclass
class ChunkResult:
    """The outcomes of a chunk of jobs and who made them."""

    outcomes: list
    pid: int
    busy_s: float
    peak_rss_mb: float


class FrameProcessor:
    """One Reconstructor plus the message builders of `ros.adapters` (rosbags flavour)."""

    def __init__(self, config: PipelineConfig, opts: OutputOptions, reconstructor=None):
        from smpl_depth_ros.pipeline import Reconstructor
        from smpl_depth_ros.ros import adapters as A
        self.A = A
        self.opts = opts
        self.rec = reconstructor if reconstructor is not None else Reconstructor(config)
        self.body = self.rec.body
        self.msgs = A.rosbags_factory()
        self.typestore = self.msgs.typestore
        self.faces = self.body.faces_numpy()
        self.outputs = FrameOutputs(self.body, self.rec.fitter.joint_frames,
                                    opts, self.msgs)
        if opts.export_meshes:  # loaded with the model, not in the first frame's time
            import trimesh  # noqa: F401

    def info(self) -> dict:
        return dict(body=self.body.name, device=str(self.rec.device),
                    net_precision=self.rec.net_precision,
                    joint_names=list(self.body.joint_names[1:]),
                    shape_names=list(self.body.shape_names),
                    num_pose=int(self.body.num_pose_joints), num_shape=int(self.body.num_shape))

    def run(self, job: Job) -> Outcome:
        if job.reset:
            self.rec.reset()
            self.outputs.forget()
        out = Outcome(job.index, 'ok', stamp_ns=job.stamp_ns, frame_id=job.frame_id)
        try:
            res = self.rec.process(job.depth, job.K, stamp_ns=job.stamp_ns, lens=job.lens)
        except InputError as e:
            out.status, out.message = e.reason, str(e)
            return out
        except Exception as e:  # noqa: BLE001 - one bad frame must not stop the run
            out.status, out.message = 'internal', f'{type(e).__name__}: {e}'
            return out
        t0 = time.perf_counter()
        persons = list(res.persons)[:max(1, self.rec.config.max_persons)]
        out.persons = len(persons)
        if persons:
            p = persons[0]
            out.params = {k: np.asarray(getattr(p.params, k), np.float32)
                          for k in ('pose', 'shape', 'global_orient', 'transl')}
            out.residual_m = float(p.residual_m)
            out.num_points = int(p.num_points)
            out.tracked = bool(getattr(p, 'tracked', False))
        try:
            out.outputs = self._messages(res, persons, job)
            if self.opts.export_meshes:
                out.meshes = self._export(persons, job)
        except Exception as e:  # noqa: BLE001 - e.g. a full disk: the frame is not written
            out.status, out.message = 'internal', f'writing outputs: {type(e).__name__}: {e}'
            out.outputs, out.params = [], None
        timings = dict(res.timings_ms)
        timings['outputs'] = (time.perf_counter() - t0) * 1e3
        out.timings_ms = timings
        return out

    def _messages(self, res, persons, job: Job) -> list[tuple[str, bytes]]:
        header = self.A.make_header(None, self.msgs, stamp_ns=job.stamp_ns,
                                    frame_id=job.frame_id)
        ts = self.typestore
        return [(k, m if isinstance(m, bytes) else bytes(ts.serialize_cdr(m, OUTPUTS[k][1])))
                for k, m in self.outputs.build(res, persons, header)]

    def _export(self, persons, job: Job) -> list[tuple[str, bytes]]:
        """The frame's mesh files, (name, content): written where the run's output is."""
        import trimesh
        fmt, files = self.opts.export_meshes, []
        for i, person in enumerate(persons):
            name = job.mesh_name + (f'_p{i}' if i else '')
            mesh = trimesh.Trimesh(np.asarray(person.vertices, np.float64), self.faces,
                                   process=False)
            buf = io.BytesIO()
            mesh.export(buf, file_type=fmt)
            files.append((f'{name}.{fmt}', buf.getvalue()))
        return files

    def restart(self):
        """As freshly loaded (`pipeline.Reconstructor.restart`); no DELETE markers for
        earlier IDs."""
        self.rec.restart()
        self.outputs.forget()


def peak_rss_mb(who=resource.RUSAGE_SELF) -> float:
    """Peak resident memory (MB) of this process (`who`: or of its waited-for children)."""
    kb = resource.getrusage(who).ru_maxrss  # kilobytes on Linux, bytes on macOS
    return round(kb / (1024 * 1024 if sys.platform == 'darwin' else 1024), 1)


def run_chunk(proc: FrameProcessor, jobs: list[Job]) -> ChunkResult:
    """A chunk of contiguous frames on one worker, the same wherever it runs: tracking
    holds within the chunk only (the processor restarts first) and person IDs stay unique
    across chunks (a chunk's IDs start at 1 + its first index times max_persons)."""
    t0 = time.perf_counter()
    proc.restart()
    if jobs:
        proc.rec.tracker.start_ids_at(1 + jobs[0].index * max(1, proc.rec.config.max_persons))
    outcomes = [proc.run(j) for j in jobs]
    return ChunkResult(outcomes, os.getpid(), time.perf_counter() - t0, peak_rss_mb())


class WorkerStats:
    """Per worker (a name: a pid, a Ray actor and its node): frames, chunks, busy seconds,
    failures (chunks lost, worker restarts), peak RSS, and where it ran."""

    def __init__(self):
        self.workers: dict[str, dict] = {}

    def clear(self):
        self.workers = {}

    def _entry(self, name: str) -> dict:
        return self.workers.setdefault(name, dict(frames=0, chunks=0, busy_s=0.0,
                                                  failures=0, frames_lost=0))

    def done(self, name: str, frames: int, busy_s: float, **info):
        """`frames` done in `busy_s`; `info`: pid, node, peak_rss_mb (latest wins)."""
        e = self._entry(name)
        e['frames'] += frames
        e['chunks'] += 1
        e['busy_s'] += busy_s
        e.update(info)

    def failed(self, name: str, frames_lost: int = 0):
        """A failure of the worker: its process died (and the chunk was run again), or a
        chunk was lost with `frames_lost` frames."""
        e = self._entry(name)
        e['failures'] += 1
        e['frames_lost'] += frames_lost

    def summary(self) -> dict[str, dict]:
        out = {}
        for name, e in sorted(self.workers.items()):
            e = dict(e, busy_s=round(e['busy_s'], 2))
            e['fps'] = round(e['frames'] / e['busy_s'], 3) if e['busy_s'] > 0 else None
            out[name] = e
        return out

    def lines(self) -> list[str]:
        """One log line per worker."""
        return [f"worker {name}: {e['frames']} frames, {e['busy_s']:.1f} s busy, "
                f"{e['fps'] if e['fps'] is not None else '-'} frames/s, "
                f"{e['failures']} failure(s)"
                + (f", {e['frames_lost']} frames lost" if e['frames_lost'] else '')
                for name, e in self.summary().items()]


# Worker processes (--workers): one FrameProcessor each, chunks of contiguous frames.
_WORKER: FrameProcessor | None = None


def _worker_init(config: PipelineConfig, opts: OutputOptions, threads: int):
    global _WORKER
    import torch
    torch.set_num_threads(max(1, threads))
    _WORKER = FrameProcessor(config, opts)


def _worker_info() -> dict:
    return _WORKER.info()


def _worker_chunk(jobs: list[Job]) -> ChunkResult:
    return run_chunk(_WORKER, jobs)


def lost(jobs: list[Job], ready: dict, message: str):
    """Account for the frames of a chunk that did not come back: status 'internal'."""
    for j in jobs:
        ready[j.index] = Outcome(j.index, 'internal', message, j.stamp_ns, j.frame_id)


class _InlineRunner:
    """Frames processed here, one by one, tracking across the whole bag."""

    def __init__(self, config, opts, reconstructor=None):
        if reconstructor is not None:  # an already loaded core: give it this run's config
            reconstructor.config = config
            if hasattr(reconstructor, 'set_fit_config'):  # a fresh fitter: same random
                reconstructor.set_fit_config(config.fit)  # subsets as a fresh core
            reconstructor.reset()
        self.proc = FrameProcessor(config, opts, reconstructor)
        self.info = self.proc.info()
        self.stats = WorkerStats()

    def restart(self):
        self.proc.restart()

    def submit(self, job: Job, ready: dict):
        t0 = time.perf_counter()
        ready[job.index] = self.proc.run(job)
        self.stats.done(str(os.getpid()), 1, time.perf_counter() - t0, pid=os.getpid(),
                        peak_rss_mb=peak_rss_mb())

    def poll(self, ready: dict, block: bool):
        pass

    def pending(self) -> int:
        return 0

    def flush(self, ready):
        pass

    def close(self, interrupted: bool = False):
        pass


class _PoolRunner:
    """Frames processed by `workers` processes in contiguous chunks (order kept by the
    caller's reorder queue)."""

    def __init__(self, config, opts, workers: int, chunk: int):
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor
        threads = max(1, (os.cpu_count() or 1) // workers)
        self.pool = ProcessPoolExecutor(workers, mp_context=mp.get_context('spawn'),
                                        initializer=_worker_init,
                                        initargs=(config, opts, threads))
        self.chunk_size = max(1, chunk)
        self.max_inflight = workers + 1
        self.current: list[Job] = []
        self.inflight: deque = deque()
        self.stats = WorkerStats()
        self.info = self.pool.submit(_worker_info).result()

    def restart(self):
        pass  # every chunk starts afresh

    def submit(self, job: Job, ready: dict):
        self.current.append(job)
        if len(self.current) >= self.chunk_size:
            self.flush(ready)

    def flush(self, ready: dict):
        if self.current:
            jobs, self.current = self.current, []
            self.inflight.append((self.pool.submit(_worker_chunk, jobs), jobs))
        while len(self.inflight) > self.max_inflight:
            self._collect(ready, block=True)

    def _collect(self, ready, block: bool):
        while self.inflight and (block or self.inflight[0][0].done()):
            fut, jobs = self.inflight.popleft()
            try:
                res = fut.result()
            except Exception as e:  # noqa: BLE001 - a worker died: account for its frames
                lost(jobs, ready, f'worker failed: {type(e).__name__}: {e}')
                self.stats.failed('unknown', len(jobs))  # the pool does not say which
            else:
                for o in res.outcomes:
                    ready[o.index] = o
                self.stats.done(str(res.pid), len(res.outcomes), res.busy_s, pid=res.pid,
                                peak_rss_mb=res.peak_rss_mb)
            block = False

    def poll(self, ready: dict, block: bool):
        self._collect(ready, block)

    def pending(self) -> int:
        return len(self.current) + sum(len(j) for _, j in self.inflight)

    def close(self, interrupted: bool = False):
        if not interrupted:
            self.pool.shutdown(wait=True, cancel_futures=True)
            return
        procs = list((getattr(self.pool, '_processes', None) or {}).values())
        self.pool.shutdown(wait=False, cancel_futures=True)
        for proc in procs:  # do not wait for the chunks in progress
            proc.terminate()
        for proc in procs:
            proc.join(5.0)


def make_runner(config: PipelineConfig, opts: OutputOptions, workers: int, chunk_size: int,
                ray: str | None = None, reconstructor=None, log=None):
    """The runner of a run: `workers` Ray actors (`ray`: '' a local Ray, else the address
    of a running cluster), `workers` processes, or this process (workers 1)."""
    if ray is not None:
        from smpl_depth_ros.offline.ray_runner import RayRunner
        return RayRunner(config, opts, workers, chunk_size, address=ray or None, log=log)
    if workers > 1:
        return _PoolRunner(config, opts, workers, chunk_size)
    return _InlineRunner(config, opts, reconstructor)


class SharedRunner:
    """One runner for several runs (the bags of a batch): made by the first run that needs
    it, restarted for each next run, closed by its owner. A run that fails or is
    interrupted `discard`s it (the next run makes a new one)."""

    def __init__(self):
        self.runner = None

    def get(self, make):
        if self.runner is None:
            self.runner = make()
        else:
            self.runner.restart()
        return self.runner

    def discard(self, interrupted: bool = False):
        runner, self.runner = self.runner, None
        if runner is not None:
            try:
                runner.close(interrupted)
            except Exception:  # noqa: BLE001 - a runner already broken
                pass

    def close(self):
        self.discard()
