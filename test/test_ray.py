"""process_bag on Ray (`--ray`, offline.ray_runner): a local Ray started here (2 CPUs,
loopback only) runs the same chunks as the process pool, with the same outputs; a worker
killed mid-run has its chunk run again; a batch of bags shares one set of actors; without
Ray, `--ray` says in one line how to install it.

The Ray tests are skipped when Ray is not installed (it is optional: `pip install
'smpl_depth_ros[ray]'`); the last test needs no Ray.
"""
from __future__ import annotations

import contextlib
import importlib.util
import io
import ipaddress
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from smpl_depth_ros.config import PipelineConfig
from smpl_depth_ros.offline import main, process_bag

REPO = Path(__file__).resolve().parents[1]
FRAMES, CHUNK = 6, 2
needs_ray = pytest.mark.skipif(importlib.util.find_spec('ray') is None,
                               reason="Ray is not installed (pip install 'smpl_depth_ros[ray]')"
                                      ': the --ray runner is not tested')
RUN = dict(workers=2, chunk_size=CHUNK, export_meshes='ply', config=PipelineConfig(device='cpu'))


# -- helpers --------------------------------------------------------------------------------
def read_messages(path) -> list[tuple[str, int, bytes]]:
    from rosbags.highlevel import AnyReader

    from smpl_depth_ros.bagio import jazzy_typestore
    with AnyReader([Path(path)], default_typestore=jazzy_typestore()) as r:
        return [(c.topic, t, bytes(raw)) for c, t, raw in r.messages()]


def assert_same_outputs(a: Path, b: Path):
    """Two runs' outputs are the same: every message of the output bags (byte for byte),
    results.npz (but the timings), the mesh files, the frame accounting."""
    ra, rb = np.load(a / 'results.npz'), np.load(b / 'results.npz')
    assert sorted(ra.files) == sorted(rb.files)
    for k in ra.files:
        if k != 'timings_ms':
            np.testing.assert_array_equal(ra[k], rb[k], err_msg=k)
    assert read_messages(a / 'bag') == read_messages(b / 'bag')
    names = sorted(os.listdir(a / 'meshes'))
    assert names == sorted(os.listdir(b / 'meshes')) and len(names) == FRAMES
    for n in names:
        assert (a / 'meshes' / n).read_bytes() == (b / 'meshes' / n).read_bytes(), n
    sa, sb = (json.loads((d / 'summary.json').read_text()) for d in (a, b))
    for k in ('frames_read', 'processed', 'skipped', 'skipped_total', 'tracked',
              'messages_written', 'meshes_exported'):
        assert sa[k] == sb[k], k


def _descendants(pid: int) -> set[int]:
    parent = {}
    for d in os.listdir('/proc'):
        if d.isdigit():
            try:
                parent[int(d)] = int(open(f'/proc/{d}/stat').read().rsplit(')', 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                pass
    out, new = {pid}, {pid}
    while new:
        new = {p for p, pp in parent.items() if pp in new} - out
        out |= new
    return out


def _address(text: str):
    host, port = text.split(':')
    raw = bytes.fromhex(host)  # 32-bit words in host (little-endian) order
    raw = b''.join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))
    ip = ipaddress.ip_address(raw)
    return getattr(ip, 'ipv4_mapped', None) or ip, int(port, 16)


def sockets_of(pids: set[int]) -> list[tuple[str, object, object, bool, int]]:
    """(protocol, local (ip, port), remote (ip, port), listening, pid) of every TCP and UDP
    socket of `pids` (from /proc: no psutil in the venv)."""
    inodes = {}
    for pid in pids:
        with contextlib.suppress(OSError):
            for fd in os.listdir(f'/proc/{pid}/fd'):
                with contextlib.suppress(OSError):
                    link = os.readlink(f'/proc/{pid}/fd/{fd}')
                    if link.startswith('socket:['):
                        inodes[link[8:-1]] = pid
    out = []
    for proto in ('tcp', 'tcp6', 'udp', 'udp6'):
        with contextlib.suppress(OSError):
            for line in open(f'/proc/net/{proto}').read().splitlines()[1:]:
                f = line.split()
                if f[9] in inodes:
                    out.append((proto, _address(f[1]), _address(f[2]),
                                proto.startswith('tcp') and f[3] == '0A', inodes[f[9]]))
    return out


# -- fixtures -------------------------------------------------------------------------------
@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    """synth_bag --sequence, 320x240, seed 4: a person in every frame."""
    from smpl_depth_ros.tools import synth_bag
    out = tmp_path_factory.mktemp('ray') / 'seq'
    assert synth_bag.main(['--out', str(out), '--frames', str(FRAMES), '--seed', '4',
                           '--sequence', '--width', '320', '--height', '240']) == 0
    return out


@pytest.fixture(scope='module')
def pool_out(bag, tmp_path_factory):
    """--workers 2 (process pool) at the chunk size of the Ray runs."""
    out = tmp_path_factory.mktemp('pool') / 'out'
    process_bag(bag, out, progress=False, log=lambda m: None, **RUN)
    return out


@pytest.fixture(scope='module')
def cluster():
    """A local Ray for this module: 2 CPUs, loopback only, no dashboard (the runs use it
    and leave it running)."""
    from smpl_depth_ros.offline.ray_runner import init_local_ray
    ray = init_local_ray(2)
    yield ray
    ray.shutdown()


@pytest.fixture(scope='module')
def ray_out(cluster, bag, tmp_path_factory):
    out = tmp_path_factory.mktemp('rayrun') / 'out'
    seen = []
    summary = process_bag(bag, out, ray='', progress=False, log=seen.append, **RUN)
    return out, summary, seen


# -- tests ----------------------------------------------------------------------------------
@needs_ray
def test_local_ray_listens_on_loopback_only(cluster, ray_out):
    """Every TCP/UDP socket of the local Ray's processes (this driver, gcs_server, raylet,
    agents, workers: this process and its descendants) is bound to loopback and talks to
    loopback only; usage statistics are off."""
    socks = sockets_of(_descendants(os.getpid()))
    listening = [s for s in socks if s[3]]
    assert len({s[4] for s in listening}) >= 3, socks  # driver, gcs_server, raylet, ...
    outward = [s for s in socks if not s[1][0].is_loopback or not (
        s[2][0].is_loopback or s[2][0].is_unspecified)]
    assert not outward, outward
    assert os.environ['RAY_USAGE_STATS_ENABLED'] == '0'
    assert cluster.util.get_node_ip_address() == '127.0.0.1'


@needs_ray
def test_ray_output_equals_the_process_pool(pool_out, ray_out):
    out, summary, seen = ray_out
    assert_same_outputs(pool_out, out)
    assert summary['frames_read'] == summary['processed'] == FRAMES
    assert summary['ray'] == 'local' and summary['workers'] == 2
    workers = summary['per_worker']
    assert workers and all(k.startswith('actor') and k.endswith('/127.0.0.1') for k in workers)
    assert sum(w['frames'] for w in workers.values()) == FRAMES
    assert all(w['failures'] == 0 and w['busy_s'] > 0 and w['fps'] > 0
               for w in workers.values())
    assert sum(line.startswith('worker actor') for line in seen) == len(workers)
    pool = json.loads((pool_out / 'summary.json').read_text())['per_worker']
    assert sum(w['frames'] for w in pool.values()) == FRAMES
    assert all(k == str(w['pid']) for k, w in pool.items())  # keyed by pid


@needs_ray
def test_a_killed_worker_has_its_chunk_run_again(cluster, bag, ray_out, tmp_path,
                                                 monkeypatch):
    """SIGKILL to an actor's process as soon as it returns a chunk while it holds another:
    Ray restarts it and runs that chunk again; nothing is lost and the outputs are those
    of the undisturbed run."""
    from smpl_depth_ros.offline.ray_runner import RayRunner
    take, killed = RayRunner._take, []

    def take_and_kill(self, ref, i, jobs, ready):
        take(self, ref, i, jobs, ready)
        if not killed and self.busy[i] > 0:  # its next chunk is in flight
            killed.append(self.pids[i])
            os.kill(self.pids[i], signal.SIGKILL)
    monkeypatch.setattr(RayRunner, '_take', take_and_kill)
    seen = []
    summary = process_bag(bag, tmp_path / 'out', ray='', progress=False, log=seen.append,
                          **RUN)
    assert killed
    assert summary['frames_read'] == summary['processed'] == FRAMES
    assert summary['skipped'] == {}
    assert sum(w['failures'] for w in summary['per_worker'].values()) == 1
    assert any('was restarted' in m and str(killed[0]) in m for m in seen), seen
    assert_same_outputs(ray_out[0], tmp_path / 'out')


@needs_ray
def test_a_batch_of_bags_shares_the_workers(cluster, bag, ray_out, tmp_path, capsys):
    """Two bags (a rosbag2 folder and a lone .mcap file) and a missing one: one output
    folder per bag under --out, a JSON line each, the actors loaded once, the exit code
    of the worst (1: the missing bag)."""
    single = tmp_path / 'lone.mcap'
    shutil.copy(next(bag.glob('*.mcap')), single)
    out = tmp_path / 'outs'
    code = main([str(bag), str(single), str(tmp_path / 'missing.mcap'), '--out', str(out),
                 '--ray', '--workers', '2', '--chunk-size', str(CHUNK), '--device', 'cpu',
                 '--export-meshes', 'ply'])
    captured = capsys.readouterr()
    lines = [json.loads(line) for line in captured.out.splitlines()]
    assert code == 1
    assert [d.get('exit_code') for d in lines] == [None, None, 1]
    assert sorted(os.listdir(out)) == ['lone', 'seq']
    for d, name in zip(lines, ('seq', 'lone')):
        assert d['output_dir'] == str(out / name) and d['processed'] == FRAMES
        assert_same_outputs(ray_out[0], out / name)
    assert captured.err.count('loading the model') == 1
    assert captured.err.count('the model is loaded') == 1
    assert 'no such bag' in captured.err


@needs_ray
def test_sigterm_mid_run_leaves_a_valid_partial_output(tmp_path):
    """SIGTERM (as Ctrl-C) while the actors work on a local Ray of the run's own: exit
    130 without waiting for the chunks, every frame accounted for, the output bag
    readable (Ray's own signal handler would end the process at once)."""
    import time
    out = tmp_path / 'out'
    p = subprocess.Popen([sys.executable, '-m', 'smpl_depth_ros.offline',
                          str(REPO / 'smpl_depth_ros' / 'data' / 'sample_bag'), '--out',
                          str(out), '--ray', '--workers', '2', '--chunk-size', '4',
                          '--device', 'cpu', '--quiet'], cwd=REPO, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True,
                         env=dict(os.environ, PYTHONPATH=str(REPO)))
    try:
        t0 = time.monotonic()
        while not (out / 'bag').exists() and p.poll() is None and time.monotonic() - t0 < 120:
            time.sleep(0.2)
        time.sleep(0.5)  # the chunks are under way (40 frames take seconds)
        p.send_signal(signal.SIGTERM)
        stdout, stderr = p.communicate(timeout=60)
    finally:
        p.kill()
    assert p.returncode == 130, stderr
    summary = json.loads(stdout.splitlines()[-1])
    assert summary['interrupted'] and summary['skipped'].get('interrupted', 0) > 0
    assert summary['frames_read'] == summary['processed'] + summary['skipped_total']
    assert len(read_messages(out / 'bag')) > 0


@needs_ray
def test_benchmark_compares_the_pool_with_ray(cluster, bag):
    from smpl_depth_ros.tools import benchmark
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert benchmark.main(['ray', str(bag), '--chunk-size', str(CHUNK)]) == 0
    res = json.loads(buf.getvalue().strip().splitlines()[-1])
    for run in ('process_pool', 'ray'):
        assert res[run]['processed'] == FRAMES and res[run]['frames_per_s'] > 0
        assert res[run]['startup_s'] > 0
    assert res['ray_vs_pool_throughput'] > 0 and res['same_results'] is True


def test_ray_option_without_ray_says_how_to_install_it(tmp_path):
    """`--ray` where Ray cannot be imported: one line, exit code 1, nothing written."""
    bag = REPO / 'smpl_depth_ros' / 'data' / 'sample_bag'
    code = ("import sys; sys.modules['ray'] = None; from smpl_depth_ros.offline import main; "
            "sys.exit(main(sys.argv[1:]))")
    out = subprocess.run([sys.executable, '-c', code, str(bag), '--out', str(tmp_path / 'o'),
                          '--ray'], capture_output=True, text=True, cwd=REPO, timeout=120,
                         env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert out.returncode == 1, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert "pip install 'smpl_depth_ros[ray]'" in lines[0] and 'pip install ray' in lines[0]
    assert out.stdout == '' and not (tmp_path / 'o').exists()
