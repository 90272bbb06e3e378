"""process_bag on a Ray cluster (`--ray [ADDRESS]`): `RayRunner`, the runner interface of
`workers` over Ray actors, each holding one `FrameProcessor` loaded once in its
constructor.

Chunks of contiguous frames go to the actors whose model is loaded, at most
`INFLIGHT_PER_ACTOR` per actor, and come back through `ray.wait`; each chunk runs through
`workers.run_chunk`, as on the process pool, so the outputs are the same as with
`--workers N` at the same chunk size. An actor whose process dies (or whose node leaves)
is restarted and its chunks run again (`MAX_RESTARTS`, `MAX_TASK_RETRIES`); a chunk still
failing after that is accounted for as 'internal', frame by frame.

Without an address, a local Ray is started for the run and shut down after it: loopback
only (its node address is 127.0.0.1, so that every Ray server listens on 127.0.0.1), no
dashboard, no usage statistics. With an address the run joins that cluster, whose every
node needs this package installed as on this machine.

Ray is optional (`pip install 'smpl_depth_ros[ray]'`): it is imported only here, and this
module only when a run asks for Ray.
"""
from __future__ import annotations

import importlib.util
import ipaddress
import logging
import os
import signal
import socket
import sys
import threading

from smpl_depth_ros.offline.errors import ProcessBagError
from smpl_depth_ros.offline.workers import FrameProcessor, WorkerStats, lost, run_chunk

MAX_RESTARTS = 3        # an actor's process replaced at most this often
MAX_TASK_RETRIES = 3    # a chunk run again at most this often after its actor died
INFLIGHT_PER_ACTOR = 2  # chunks given to an actor at once (one running, one waiting)
CONNECT_TIMEOUT_S = 10.0  # for a cluster's address to answer
NO_RAY = ("--ray needs Ray, which is not installed: pip install 'smpl_depth_ros[ray]' "
          "(or pip install ray)")
# A local Ray: no usage statistics sent out, the node address kept on loopback (Ray
# otherwise turns 127.0.0.1 into this machine's outward address and listens on all
# interfaces). Read by Ray when it is imported and by the processes it starts.
LOCAL_ENV = {'RAY_USAGE_STATS_ENABLED': '0', 'RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER': '0'}


def check_ray():
    """ProcessBagError (one line: how to install Ray) when there is no Ray to import
    (without importing it)."""
    if importlib.util.find_spec('ray') is None:
        raise ProcessBagError(NO_RAY)


def require_ray():
    """The `ray` module; ProcessBagError (one line: how to install it) without it."""
    try:
        import ray
    except ImportError:
        raise ProcessBagError(NO_RAY) from None
    return ray


def join_cluster(address: str):
    """Connect to the running cluster at `address` ('HOST:PORT'); returns `ray`. Its port
    must answer first: ray.init would otherwise wait for it without end, deaf to Ctrl-C.
    A loopback HOST (a head started on this machine with --node-ip-address 127.0.0.1)
    keeps this process on loopback too."""
    host, sep, port = address.rpartition(':')
    if sep and port.isdigit() and '://' not in address:
        host = host.strip('[]')
        try:
            socket.create_connection((host, int(port)), timeout=CONNECT_TIMEOUT_S).close()
        except OSError as e:
            raise ProcessBagError(f'no Ray cluster answers at {address} ({e}); start one '
                                  'with `ray start --head`') from None
        try:
            loopback = ipaddress.ip_address(host).is_loopback
        except ValueError:
            loopback = host == 'localhost'
        if loopback:
            ray = _loopback_ray()
            _use_token()
            _init(ray, f'cannot join the Ray cluster at {address}', address=address)
            return ray
    os.environ.setdefault('RAY_USAGE_STATS_ENABLED', '0')
    ray = require_ray()
    _use_token()
    _init(ray, f'cannot join the Ray cluster at {address}', address=address)
    return ray


def _use_token():
    """This machine's Ray token (~/.ray/auth_token, RAY_AUTH_TOKEN), when there is one and
    RAY_AUTH_MODE says nothing: what ray.init does for a cluster it finds by itself, not
    for one given by address."""
    try:
        from ray._private.authentication.authentication_token_setup import (
            maybe_enable_token_auth_if_token_available)
    except ImportError:  # a Ray without token authentication
        return
    maybe_enable_token_auth_if_token_available(warn_if_disabled=False)


def _init(ray, failure: str, **kwargs):
    """ray.init, keeping this process's Ctrl-C and SIGTERM handlers (Ray's own would end
    the process at once, with no partial output); ProcessBagError(`failure`: why) when
    it fails."""
    main = threading.current_thread() is threading.main_thread()
    kept = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)} if main else {}
    try:
        ray.init(logging_level=logging.WARNING, log_to_driver=False, **kwargs)
    except Exception as e:  # noqa: BLE001 - Ray's own errors: ConnectionError, RuntimeError, ...
        raise ProcessBagError(f'{failure}: {_short(e)}') from None
    finally:
        for sig, handler in kept.items():
            if handler is not None:
                signal.signal(sig, handler)


def _loopback_ray():
    """`ray`, keeping this process's Ray on loopback (LOCAL_ENV)."""
    os.environ.update(LOCAL_ENV)
    ray = require_ray()
    from ray._private import ray_constants
    ray_constants.ENABLE_RAY_CLUSTER = False  # as LOCAL_ENV, when ray was imported before
    return ray


def init_local_ray(num_cpus: int):
    """Start a Ray on this machine only (see the module docstring); returns `ray`."""
    ray = _loopback_ray()
    _init(ray, 'cannot start a local Ray', address='local', num_cpus=num_cpus,
          include_dashboard=False, _node_ip_address='127.0.0.1')
    node = ray.util.get_node_ip_address()
    if not ipaddress.ip_address(node).is_loopback:
        ray.shutdown()
        raise ProcessBagError(f'the local Ray came up on {node}, not on loopback: not used')
    return ray


class FrameActor:
    """One worker of the cluster: a FrameProcessor loaded once, chunks run through
    `run_chunk` (made a Ray actor class by `RayRunner`)."""

    def __init__(self, config, opts, threads: int):
        import torch
        torch.set_num_threads(max(1, threads))
        self.proc = FrameProcessor(config, opts)

    def ready(self) -> tuple[dict, int, str]:
        """(model info, pid, node address)."""
        import ray
        return self.proc.info(), os.getpid(), ray.util.get_node_ip_address()

    def chunk(self, jobs):
        return run_chunk(self.proc, jobs)


class RayRunner:
    """Frames processed by `workers` Ray actors in contiguous chunks (order kept by the
    caller's reorder queue); see the module docstring."""

    def __init__(self, config, opts, workers: int, chunk: int, address: str | None = None,
                 log=None):
        self.log = log or (lambda m: None)
        self.chunk_size = max(1, chunk)
        self.current: list = []
        self.inflight: dict = {}          # ObjectRef -> (actor index, jobs)
        self.order: list = []             # ObjectRefs in submission order
        self.stats = WorkerStats()
        self.actors: list = []
        self.closed = False
        ray = sys.modules.get('ray')  # imported only once the environment is set
        self.owns_ray = ray is None or not ray.is_initialized()
        try:
            if not self.owns_ray:
                pass  # a Ray this process joined before (a test, a notebook): use it
            elif address:
                ray = join_cluster(address)
            else:
                ray = init_local_ray(workers)
            self.ray = ray
            # Local: the process pool's threads per worker; a cluster: one CPU per actor.
            threads = max(1, (os.cpu_count() or 1) // workers) if not address else 1
            cls = ray.remote(num_cpus=1, max_restarts=MAX_RESTARTS,
                             max_task_retries=MAX_TASK_RETRIES)(FrameActor)
            self.actors = [cls.remote(config, opts, threads) for _ in range(workers)]
            self.names = [f'actor{i}' for i in range(workers)]
            self.pids: list[int | None] = [None] * workers
            self.alive = [True] * workers
            self.loaded = [False] * workers
            self.busy = [0] * workers
            self.loading = {a.ready.remote(): i for i, a in enumerate(self.actors)}
            self.info = None
            while self.info is None:  # the first actor loaded: the run can start
                self._wait_loading(timeout=None)
        except BaseException:
            self.close(interrupted=True)
            raise

    # -- actors --------------------------------------------------------------------------
    def _wait_loading(self, timeout):
        """Take the actors whose model has loaded since (`timeout` None: at least one)."""
        if not self.loading:
            if self.info is None:
                raise ProcessBagError('no Ray worker could load the model')
            return
        done, _ = self.ray.wait(list(self.loading), num_returns=1 if timeout is None else
                                len(self.loading), timeout=timeout)
        for ref in done:
            i = self.loading.pop(ref)
            try:
                info, pid, node = self.ray.get(ref)
            except self.ray.exceptions.RayError as e:
                self.alive[i] = False
                self.log(f'Ray worker {i} could not load the model: {_short(e)}')
                if self.info is None and not self.loading:
                    raise ProcessBagError(f'no Ray worker could load the model: {_short(e)}') \
                        from None
                continue
            self.info = self.info or info
            self.loaded[i], self.pids[i] = True, pid
            self.names[i] = f'actor{i}/{node}'

    def _idle_actor(self) -> int | None:
        free = [i for i in range(len(self.actors)) if self.alive[i] and self.loaded[i]
                and self.busy[i] < INFLIGHT_PER_ACTOR]
        return min(free, key=lambda i: (self.busy[i], i)) if free else None

    # -- the runner interface ------------------------------------------------------------
    def restart(self):
        pass  # every chunk starts afresh

    def submit(self, job, ready: dict):
        self.current.append(job)
        if len(self.current) >= self.chunk_size:
            self.flush(ready)

    def flush(self, ready: dict):
        if not self.current:
            return
        jobs, self.current = self.current, []
        while True:
            if self.loading:
                self._wait_loading(timeout=0)
            i = self._idle_actor()
            if i is not None:
                ref = self.actors[i].chunk.remote(jobs)
                self.inflight[ref] = (i, jobs)
                self.order.append(ref)
                self.busy[i] += 1
                return
            if not any(self.alive):
                lost(jobs, ready, 'no Ray worker left (all failed)')
                return
            # Every loaded actor has its share: wait for a chunk, or for an actor to load.
            refs = list(self.inflight) + list(self.loading)
            self.ray.wait(refs, num_returns=1)
            self._collect(ready, block=False)

    def poll(self, ready: dict, block: bool):
        self._collect(ready, block)

    def pending(self) -> int:
        return len(self.current) + sum(len(j) for _, j in self.inflight.values())

    def _collect(self, ready: dict, block: bool):
        if not self.inflight:
            return
        if block:  # the oldest chunk first: the caller waits for its first frame
            self.ray.wait([self.order[0]], num_returns=1)
        done, _ = self.ray.wait(self.order, num_returns=len(self.order), timeout=0)
        done = set(done)
        for ref in [r for r in self.order if r in done]:
            self.order.remove(ref)
            i, jobs = self.inflight.pop(ref)
            self.busy[i] -= 1
            self._take(ref, i, jobs, ready)

    def _take(self, ref, i: int, jobs: list, ready: dict):
        """One chunk back from actor `i`: its outcomes, or its frames accounted for."""
        ray = self.ray
        try:
            res = ray.get(ref)
        except ray.exceptions.RayError as e:
            if isinstance(e, ray.exceptions.ActorDiedError):
                self.alive[i] = False
                why = f'Ray worker {self.names[i]} died, restarts exhausted'
            else:
                why = f'Ray worker {self.names[i]} failed'
            msg = f'{why}: {_short(e)}'
            lost(jobs, ready, msg)
            self.stats.failed(self.names[i], len(jobs))
            self.log(f'{msg}; frames {jobs[0].index}-{jobs[-1].index} accounted as internal')
            return
        if self.pids[i] is not None and res.pid != self.pids[i]:
            self.stats.failed(self.names[i])  # its process was replaced; chunk run again
            self.log(f'Ray worker {self.names[i]} was restarted (pid {self.pids[i]} -> '
                     f'{res.pid}); its chunks ran again')
        self.pids[i] = res.pid
        for o in res.outcomes:
            ready[o.index] = o
        self.stats.done(self.names[i], len(res.outcomes), res.busy_s, pid=res.pid,
                        node=self.names[i].split('/', 1)[-1], peak_rss_mb=res.peak_rss_mb)

    def close(self, interrupted: bool = False):
        """Release the actors (killed: no waiting for chunks in progress when
        `interrupted`), and shut down a Ray started for this run."""
        if self.closed:
            return
        self.closed = True
        ray = getattr(self, 'ray', None) or require_ray()
        for a in self.actors:
            try:
                ray.kill(a, no_restart=True)
            except Exception:  # noqa: BLE001 - already gone
                pass
        self.actors = []
        if self.owns_ray and ray.is_initialized():
            ray.shutdown()


def _short(e: BaseException) -> str:
    """An exception's first line."""
    text = str(e).strip().splitlines()
    return f'{type(e).__name__}: {text[0] if text else ""}'.rstrip(': ')
