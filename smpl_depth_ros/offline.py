"""process_bag: run the reconstructor over a recorded ROS 2 bag, every frame accounted for.

    process_bag BAG --out DIR [--params-file config/reconstructor.yaml] [--device cpu]
                [--depth-topic T] [--info-topic T] [--no-tracking] [-p name=value ...]
                [--storage mcap|sqlite3] [--compress] [--export-meshes ply|obj|glb]
                [--workers N] [--overwrite]

BAG is a rosbag2 directory (metadata.yaml + storage files) or a single .mcap / .db3 file,
read with `rosbags` (no ROS install needed) one message at a time. The depth
(`sensor_msgs/msg/Image`) and camera_info topics are found automatically when there is one
candidate. Frames go through the same `pipeline.Reconstructor` and the same parameters as
the live `reconstructor` node (its `--params-file` YAML, `/**: ros__parameters:`), with
tracking across consecutive frames. DIR receives:

* ``bag/``: the input topics copied unchanged plus the node's outputs (``<ns>/mesh``
  Marker, ``<ns>/segmentation`` rgb8 + ``<ns>/segmentation/labels`` mono8 Image,
  ``<ns>/smpl_params`` JointState, ``<ns>/skeleton`` MarkerArray, ``/diagnostics``), each
  output with its input frame's header and bag timestamp, in input order (MCAP unless
  ``--storage sqlite3``);
* ``results.npz``: one row per depth frame read (stamps, status, parameters, residual,
  timings; see `save_results`);
* ``meshes/<stamp_ns>.<fmt>`` with ``--export-meshes``;
* ``summary.json``: frames_read, processed, skipped by reason, mean timings, fps, peak RSS.
  The same JSON is printed on stdout at the end.

Invariant: ``frames_read == processed + sum(skipped.values())``: a frame is either
processed or skipped with a reason ('no_camera_info', 'no_person', 'encoding',
'size_mismatch', 'deserialize', ... the `types.InputError` reasons).

Real bags: header stamps may go backwards (tracking is reset) or repeat (processed, marked
``duplicate``); depth frames that arrive before the first camera_info of their frame_id
wait for it (up to `MAX_WAITING_FOR_INFO` frames, then the oldest is skipped as
'no_camera_info', as is any still waiting at the end of the bag); unknown topics are
copied through; a truncated or corrupt bag stops the run with an error naming the file
and the position, keeping everything read before it (the readable part of a truncated
MCAP or sqlite3 file is recovered) and closing the output bag properly. Exit codes: 0
done, 1 unusable input or options, 3 the bag is damaged (partial results written), 130
interrupted (partial results written).

`--workers N` runs N processes, each with its own Reconstructor, on contiguous chunks of
frames (tracking restarts at each chunk); the output keeps the input order.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import signal
import sqlite3
import struct
import sys
import tempfile
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field, fields, replace
from io import BytesIO
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from smpl_depth_ros.config import FitConfig, PipelineConfig
from smpl_depth_ros.ros.outputs import OUTPUT_PARAMS, TOPICS, FrameOutputs
from smpl_depth_ros.ros.outputs import OutputOptions as MessageOptions
from smpl_depth_ros.sensor_noise import check_sensor
from smpl_depth_ros.stamps import stamp_to_ns
from smpl_depth_ros.types import InputError

PROG = 'process_bag'
MAX_WAITING_FOR_INFO = 30  # depth frames held for a camera_info that has not come yet
DEFAULT_NS = '/reconstructor'
DIAGNOSTICS_TOPIC = '/diagnostics'
IMAGE_T = 'sensor_msgs/msg/Image'
INFO_T = 'sensor_msgs/msg/CameraInfo'
DIAG_T = 'diagnostic_msgs/msg/DiagnosticArray'
# Output key -> (topic under the namespace, or absolute; message type), as the node
# publishes (ros.outputs).
OUTPUTS = TOPICS
TIMING_NAMES = ('preprocess', 'network', 'correspondence', 'fit', 'labels', 'total',
                'outputs')
MESH_FORMATS = ('ply', 'obj', 'glb')
# Node parameters that matter offline (the rest are about QoS and live diagnostics).
NODE_OPTIONS = {k: v for k, (v, _) in OUTPUT_PARAMS.items()}
NODE_ONLY = {'qos_reliability', 'qos_depth', 'diagnostics_period_s', 'warn_throttle_s',
             'cpu_threads'}  # offline: threads follow --workers
EXIT_OK, EXIT_USAGE, EXIT_DAMAGED, EXIT_INTERRUPTED = 0, 1, 3, 130


class ProcessBagError(RuntimeError):
    """An unusable input or option (exit code 1); the message says what to do."""


class InterruptedBeforeStart(RuntimeError):
    """Ctrl-C / SIGTERM before the first frame: nothing processed, nothing written."""


class BagReadError(RuntimeError):
    """The bag is damaged: `path` is the storage file, `position` where reading stopped."""

    def __init__(self, path, position: str, detail: str):
        super().__init__(f'{path}: unreadable {position}: {detail}')
        self.path = str(path)
        self.position = position
        self.detail = detail


# -- parameters -------------------------------------------------------------------------
def _flatten(d: dict, prefix: str = '') -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        name = f'{prefix}{k}'
        if isinstance(v, dict):
            out.update(_flatten(v, name + '.'))
        else:
            out[name] = v
    return out


def load_params_file(path: str | Path, node_name: str = 'reconstructor') -> dict[str, Any]:
    """The node's parameters from a ROS 2 params YAML, flattened ('fit.iterations').

    Sections keyed ``/**`` (or ``**``) apply, then the ones naming the node (``reconstructor``,
    ``/reconstructor``, ``/<ns>/reconstructor``, ``/**/reconstructor``), later ones winning,
    as in ROS.
    """
    import yaml
    try:
        with open(path) as f:
            data = yaml.safe_load(f) or {}
    except (OSError, yaml.YAMLError) as e:
        raise ProcessBagError(f'cannot read params file {path}: {e}') from None
    if not isinstance(data, dict):
        raise ProcessBagError(f'params file {path}: expected a mapping at the top level')
    generic, specific = {}, {}
    for key, section in data.items():
        if not isinstance(section, dict) or 'ros__parameters' not in section:
            continue
        params = section['ros__parameters'] or {}
        if not isinstance(params, dict):
            raise ProcessBagError(f'params file {path}: {key}: ros__parameters must be a '
                                  f'mapping, got {type(params).__name__}')
        params = _flatten(params)
        k = str(key).strip('/')
        if k in ('**', ''):
            generic.update(params)
        elif k.split('/')[-1] == node_name:
            specific.update(params)
    return {**generic, **specific}


def _coerce(name: str, value, default):
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ProcessBagError(f'parameter {name} must be true/false, got {value!r}')
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ProcessBagError(f'parameter {name} must be an integer, got {value!r}')
        return value
    if isinstance(default, float):
        if isinstance(value, str):  # YAML 1.1 reads 1e-5 (no dot) as a string; ROS doesn't
            try:
                value = float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ProcessBagError(f'parameter {name} must be a number, got {value!r}')
        return float(value)
    if not isinstance(value, str):
        raise ProcessBagError(f'parameter {name} must be a string, got {value!r}')
    return value


def config_from_params(params: dict[str, Any], base: PipelineConfig | None = None
                       ) -> tuple[PipelineConfig, dict[str, Any], list[str]]:
    """Map node parameter names onto (PipelineConfig, node options, ignored names).

    Core names are PipelineConfig fields and 'fit.<FitConfig field>'; node options are
    `NODE_OPTIONS`; QoS/diagnostics parameters of the live node are ignored; anything else
    is an error (a typo would otherwise pass silently).
    """
    cfg = base or PipelineConfig()
    core = {f.name: getattr(cfg, f.name) for f in fields(PipelineConfig) if f.name != 'fit'}
    fit = {f.name: getattr(cfg.fit, f.name) for f in fields(FitConfig)}
    opts = dict(NODE_OPTIONS)
    ignored, unknown = [], []
    for name, value in params.items():
        if name in core:
            core[name] = _coerce(name, value, core[name])
        elif name.startswith('fit.') and name[4:] in fit:
            fit[name[4:]] = _coerce(name, value, fit[name[4:]])
        elif name in opts:
            opts[name] = _coerce(name, value, NODE_OPTIONS[name])
        elif name in NODE_ONLY:
            ignored.append(name)
        else:
            unknown.append(name)
    if unknown:
        raise ProcessBagError(f'unknown parameter(s): {", ".join(sorted(unknown))}')
    out = PipelineConfig(**core, fit=FitConfig(**fit))
    if out.device not in ('auto', 'cpu', 'cuda'):
        raise ProcessBagError(f"device must be 'auto', 'cpu' or 'cuda', got {out.device!r}")
    if out.segmentation not in ('model', 'network'):
        raise ProcessBagError("segmentation must be 'model' or 'network', got "
                              f'{out.segmentation!r}')
    if check_sensor(out.sensor):
        raise ProcessBagError(check_sensor(out.sensor))
    if not out.depth_min < out.depth_max:
        raise ProcessBagError(f'depth_min ({out.depth_min}) must be smaller than depth_max '
                              f'({out.depth_max})')
    if not 0.0 < opts['mesh_decimation'] <= 1.0:
        raise ProcessBagError(f"mesh_decimation must be in (0, 1], got {opts['mesh_decimation']}")
    return out, opts, ignored


def parse_param_overrides(items) -> dict[str, Any]:
    """['name=value', 'name:=value'] -> {name: YAML-typed value}."""
    import yaml
    out = {}
    for item in items or ():
        sep = ':=' if ':=' in item else '='
        name, ok, value = item.partition(sep)
        if not ok or not name:
            raise ProcessBagError(f"-p expects name=value, got {item!r}")
        try:
            out[name.strip()] = yaml.safe_load(value) if value.strip() else ''
        except yaml.YAMLError as e:
            raise ProcessBagError(f'-p {name.strip()}: {value!r} is not a YAML value '
                                  f'({type(e).__name__})') from None
    return out


# -- reading bags -------------------------------------------------------------------------
@dataclass
class Topic:
    """One input connection."""

    id: int
    topic: str
    msgtype: str
    msgdef: str = ''
    msgdef_format: str = 'ros2msg'   # 'ros2msg' | 'ros2idl' | ''
    digest: str = ''
    qos: list = field(default_factory=list)
    count: int | None = None          # messages (None: unknown, a recovered file)


def _storage_files(path: Path) -> list[Path]:
    if path.is_file():
        return [path]
    meta = path / 'metadata.yaml'
    files = []
    if meta.is_file():
        try:
            import yaml
            info = yaml.safe_load(meta.read_text())['rosbag2_bagfile_information']
            files = [path / p for p in info.get('relative_file_paths') or []]
        except Exception:  # noqa: BLE001 - a damaged metadata.yaml: fall back to a listing
            files = []
    if not files or not all(f.exists() for f in files):
        files = sorted(p for p in path.iterdir() if p.suffix in ('.mcap', '.db3'))
    return files


def _typestore_for(topics: list[Topic]):
    """A typestore holding the Jazzy types plus the definitions carried by the bag."""
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    typs = {}
    for t in topics:
        if t.msgtype in store.fielddefs or not t.msgdef:
            continue
        try:
            if t.msgdef_format == 'ros2idl':
                sep = '=' * 80 + '\n'
                parts = t.msgdef.split(sep)[1:] if t.msgdef.startswith(sep + 'IDL: ') else \
                    ['IDL: x\n' + t.msgdef]
                for part in parts:
                    typs.update(get_types_from_idl(part.split('\n', 1)[1]))
            else:
                typs.update(get_types_from_msg(t.msgdef, t.msgtype))
        except Exception:  # noqa: BLE001 - an unparsable definition: copy-through only
            continue
    store.register({k: v for k, v in typs.items() if k not in store.fielddefs})
    return store


def _mcap_records_fit(path: Path) -> bool:
    """Whether every top-level record of an MCAP file lies inside the file (headers only,
    one seek per record: a chunked bag has a few records per megabyte)."""
    size = path.stat().st_size
    with open(path, 'rb') as f:
        if f.read(8) != _McapScan.MAGIC:
            return False
        pos = 8
        while pos + 9 <= size:
            head = f.read(9)
            op, length = head[0], struct.unpack('<Q', head[1:])[0]
            if length > size - pos - 9:
                return False
            if op == 0x02:  # footer
                return True
            pos += 9 + length
            f.seek(pos)
    return False


class _McapScan:
    """Sequential reader of an MCAP file that needs no summary section: it recovers the
    messages of a truncated or damaged file up to the first broken record."""

    MAGIC = b'\x89MCAP0\r\n'

    def __init__(self, path: Path):
        self.path = path
        self.size = path.stat().st_size

    @staticmethod
    def _str(b: BytesIO) -> str:
        (n,) = struct.unpack('<I', b.read(4))
        s = b.read(n)
        if len(s) != n:
            raise ValueError('string runs past its record')
        return s.decode()

    def records(self, with_messages: bool) -> Iterator[tuple]:
        """Yields ('schema', id, name, encoding, data), ('channel', id, schema_id, topic,
        metadata bytes), ('message', channel_id, log_time, data); raises BagReadError at
        the first unreadable record (position in bytes)."""
        with open(self.path, 'rb') as f:
            if f.read(8) != self.MAGIC:
                raise BagReadError(self.path, 'at byte 0', 'not an MCAP file (bad magic)')
            pos = 8
            while True:
                head = f.read(9)
                if not head:
                    raise BagReadError(self.path, f'at byte {pos} of {self.size}',
                                       'the file ends without an MCAP footer (truncated)')
                if len(head) < 9:
                    raise BagReadError(self.path, f'at byte {pos} of {self.size}',
                                       'truncated record header')
                op, length = head[0], struct.unpack('<Q', head[1:])[0]
                if op == 0x02 or op == 0x0F:  # footer / data end: the data section is over
                    return
                truncated = length > self.size - pos - 9
                if truncated and op == 0x06:  # a chunk cut short: recover its first records
                    body = f.read()
                    try:
                        yield from self._chunk(body, with_messages, partial=True)
                    except Exception:  # noqa: BLE001 - whatever was recoverable is yielded
                        pass
                    raise BagReadError(self.path, f'in the chunk at byte {pos} of {self.size}',
                                       f'the chunk needs {length} bytes, the file ends '
                                       f'{self.size - pos - 9} bytes into it (truncated)')
                if truncated:
                    raise BagReadError(self.path, f'at byte {pos} of {self.size}',
                                       f'record 0x{op:02x} of {length} bytes runs past the '
                                       'end of the file (truncated)')
                if op in (0x03, 0x04, 0x06) or (op == 0x05 and with_messages):
                    body = f.read(length)
                    try:
                        yield from self._parse(op, body, with_messages)
                    except Exception as e:  # noqa: BLE001
                        raise BagReadError(self.path, f'at byte {pos} of {self.size}',
                                           f'damaged record 0x{op:02x}: {e}') from None
                else:
                    f.seek(length, 1)
                pos += 9 + length

    def _parse(self, op: int, body: bytes, with_messages: bool) -> Iterator[tuple]:
        b = BytesIO(body)
        if op == 0x03:
            (sid,) = struct.unpack('<H', b.read(2))
            name, enc = self._str(b), self._str(b)
            (n,) = struct.unpack('<I', b.read(4))
            yield ('schema', sid, name, enc, b.read(n).decode())
        elif op == 0x04:
            sid, schema_id = struct.unpack('<HH', b.read(4))
            topic, _enc = self._str(b), self._str(b)
            yield ('channel', sid, schema_id, topic, b.getvalue()[b.tell():])
        elif op == 0x05:
            cid, _seq, log_time, _pub = struct.unpack('<HIQQ', b.read(22))
            yield ('message', cid, log_time, body[22:])
        elif op == 0x06:
            yield from self._chunk(body, with_messages, partial=False)

    def _chunk(self, body: bytes, with_messages: bool, partial: bool) -> Iterator[tuple]:
        """Records of a chunk; `partial`: the chunk is cut short, decode what is there."""
        b = BytesIO(body)
        _t0, _t1, usize, _crc = struct.unpack('<QQQI', b.read(28))
        comp = self._str(b)
        (csize,) = struct.unpack('<Q', b.read(8))
        data = b.read(csize)
        if len(data) != csize and not partial:
            raise ValueError('chunk data runs past its record')
        if comp == 'zstd':
            try:
                from compression import zstd
            except ImportError:
                from backports import zstd
            data = zstd.ZstdDecompressor().decompress(data) if partial else \
                zstd.decompress(data)
        elif comp == 'lz4':
            from lz4.frame import LZ4FrameDecompressor, decompress
            data = LZ4FrameDecompressor().decompress(data) if partial else decompress(data)
        elif comp:
            raise ValueError(f'unsupported chunk compression {comp!r}')
        if len(data) != usize and not partial:
            raise ValueError('chunk size mismatch')
        inner = BytesIO(data)
        msgs = []
        while inner.tell() + 9 <= len(data):
            iop = inner.read(1)[0]
            (ilen,) = struct.unpack('<Q', inner.read(8))
            ibody = inner.read(ilen)
            if len(ibody) != ilen:
                if partial:
                    break
                raise ValueError('record runs past its chunk')
            for rec in self._parse(iop, ibody, with_messages) if iop in (3, 4, 5) else ():
                if rec[0] == 'message':
                    if with_messages:
                        msgs.append(rec)
                else:
                    yield rec
        yield from sorted(msgs, key=lambda r: r[2])  # time order within a chunk

    def topics(self) -> tuple[list[Topic], BagReadError | None]:
        from rosbags.rosbag2.storage_mcap import get_qos
        schemas, topics, err = {}, [], None
        try:
            for rec in self.records(with_messages=False):
                if rec[0] == 'schema':
                    schemas[rec[1]] = rec[2:]
                elif rec[0] == 'channel':
                    name, enc, data = schemas.get(rec[2], ('', '', ''))
                    try:
                        qos = get_qos(rec[4])
                    except Exception:  # noqa: BLE001
                        qos = []
                    topics.append(Topic(rec[1], rec[3], name, data,
                                        'ros2idl' if 'idl' in enc else 'ros2msg', '', qos))
        except BagReadError as e:
            err = e
        return topics, err

    def messages(self) -> Iterator[tuple[int, int, bytes]]:
        for rec in self.records(with_messages=True):
            if rec[0] == 'message':
                yield rec[1], rec[2], rec[3]


class _Sqlite3Scan:
    """Reads what is readable of a damaged rosbag2 sqlite3 file: a copy whose header page
    count matches the file (SQLite refuses a truncated file otherwise), rows in insertion
    order until the first unreadable page."""

    def __init__(self, path: Path, tmpdir: str):
        self.path = path
        self.copy = Path(tmpdir) / 'recovered.db3'
        shutil.copyfile(path, self.copy)
        with open(self.copy, 'r+b') as f:
            head = f.read(100)
            if len(head) < 100 or not head.startswith(b'SQLite format 3\x00'):
                raise BagReadError(path, 'at byte 0', 'not an SQLite database')
            (ps,) = struct.unpack('>H', head[16:18])
            ps = 65536 if ps == 1 else ps
            pages = self.copy.stat().st_size // ps
            f.truncate(pages * ps)
            f.seek(28)
            f.write(struct.pack('>I', pages))
        self.con = sqlite3.connect(f'file:{self.copy}?mode=ro', uri=True)

    def topics(self) -> tuple[list[Topic], BagReadError | None]:
        from rosbags.rosbag2.metadata import parse_qos
        try:
            cols = [r[1] for r in self.con.execute('PRAGMA table_info(topics)')]
            has_hash = 'type_description_hash' in cols
            rows = self.con.execute('SELECT id, name, type, offered_qos_profiles' +
                                    (', type_description_hash' if has_hash else '') +
                                    ' FROM topics ORDER BY id').fetchall()
            defs = {}
            if self.con.execute("SELECT name FROM sqlite_master WHERE "
                                "name='message_definitions'").fetchone():
                for typ, enc, text in self.con.execute(
                        'SELECT topic_type, encoding, encoded_message_definition '
                        'FROM message_definitions'):
                    defs[typ] = (text, 'ros2idl' if 'idl' in (enc or '') else 'ros2msg')
        except sqlite3.DatabaseError as e:
            return [], BagReadError(self.path, 'at open (topics table)', str(e))
        topics = []
        for row in rows:
            try:
                qos = parse_qos(row[3]) if row[3] else []
            except Exception:  # noqa: BLE001
                qos = []
            text, fmt = defs.get(row[2], ('', 'ros2msg'))
            topics.append(Topic(row[0], row[1], row[2], text, fmt,
                                row[4] if has_hash else '', qos))
        return topics, None

    def messages(self) -> Iterator[tuple[int, int, bytes]]:
        last = 0
        try:
            for rid, tid, ts, data in self.con.execute(
                    'SELECT id, topic_id, timestamp, data FROM messages ORDER BY id'):
                last = rid
                yield tid, ts, data
        except sqlite3.DatabaseError as e:
            raise BagReadError(self.path, f'after message row {last}', str(e)) from None

    def close(self):
        self.con.close()


class BagInput:
    """Streams (Topic, bag time ns, raw CDR) from a bag, never holding it in memory.

    Intact bags are read with `rosbags.highlevel.AnyReader` (Jazzy typestore by default,
    definitions embedded in the bag win). When AnyReader cannot open a bag whose storage
    is one MCAP or sqlite3 file, the readable part of that file is recovered (see
    `_McapScan`, `_Sqlite3Scan`) and the damage is raised as `BagReadError` once its
    messages have been yielded: `open_error` holds AnyReader's complaint.

    Attributes:
        topics: the connections; typestore: deserialises their messages;
        recovered: True when reading a damaged file's readable part.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.exists():
            raise ProcessBagError(f'{self.path}: no such bag (a rosbag2 directory, or a .mcap '
                                  'or .db3 file)')
        if self.path.suffix == '.bag':
            raise ProcessBagError(f'{self.path}: a ROS 1 bag; convert it first '
                                  '(`rosbags-convert --src in.bag --dst out_dir`)')
        self.recovered = False
        self.open_error: str | None = None
        self._reader = None
        self._scan = None
        self._scan_error: BagReadError | None = None
        self._tmp = None
        self.files = _storage_files(self.path) if self.path.is_dir() else [self.path]

    def __enter__(self) -> 'BagInput':
        from rosbags.highlevel import AnyReader
        from smpl_depth_ros.bagio import jazzy_typestore
        try:
            for f in self.files:  # a damaged length field would have the reader ask for
                if f.suffix == '.mcap' and not _mcap_records_fit(f):  # that many bytes
                    raise ValueError(f'{f}: an MCAP record runs past the end of the file')
            reader = AnyReader([self.path], default_typestore=jazzy_typestore())
            reader.open()
        except Exception as e:  # noqa: BLE001 - AnyReaderError, ReaderError, OSError ...
            self.open_error = f'{type(e).__name__}: {e}'
            self._open_recovery()
            return self
        self._reader = reader
        self.topics = [Topic(c.id, c.topic, c.msgtype, c.msgdef.data,
                             'ros2idl' if c.msgdef.format.name == 'IDL' else 'ros2msg',
                             c.digest, list(getattr(c.ext, 'offered_qos_profiles', []) or []),
                             int(c.msgcount)) for c in reader.connections]
        self._conns = {c.id: c for c in reader.connections}
        self.typestore = reader.typestore
        return self

    def _open_recovery(self):
        files = [f for f in self.files if f.suffix in ('.mcap', '.db3')]
        if len(files) != 1:
            raise BagReadError(self.path, 'at open', self.open_error or 'no storage file')
        f = files[0]
        if f.suffix == '.mcap':
            self._scan = _McapScan(f)
        else:
            self._tmp = tempfile.mkdtemp(prefix='process_bag_recover_')
            try:
                self._scan = _Sqlite3Scan(f, self._tmp)
            except BagReadError:
                self.close()
                raise
        self.topics, self._scan_error = self._scan.topics()
        if not self.topics:
            err = self._scan_error
            self.close()
            raise BagReadError(f, err.position if err else 'at open',
                               f'{self.open_error}; nothing recoverable'
                               + (f' ({err.detail})' if err else ''))
        self.recovered = True
        self.typestore = _typestore_for(self.topics)

    def messages(self, topics: set[str] | None = None) -> Iterator[tuple[Topic, int, bytes]]:
        """Messages in bag-time order (recovered files: file order, time order in chunks).

        Raises:
            BagReadError when the storage is damaged, after every readable message.
        """
        by_id = {t.id: t for t in self.topics if topics is None or t.topic in topics}
        if self._reader is not None:
            conns = [self._conns[i] for i in by_id]
            if not conns:  # (AnyReader reads every connection when given none)
                return
            n, last_t = 0, None
            try:
                for conn, t, raw in self._reader.messages(connections=conns):
                    n += 1
                    last_t = t
                    yield by_id[conn.id], t, raw
            except GeneratorExit:
                raise
            except Exception as e:  # noqa: BLE001 - any storage-level failure
                where = self._damaged_file(e)
                raise BagReadError(where, f'after message {n}' + (
                    f' (bag time {last_t} ns)' if last_t is not None else ''),
                    f'{type(e).__name__}: {e}') from None
            return
        for tid, t, raw in self._scan.messages():
            if tid in by_id:
                yield by_id[tid], t, raw
        if self._scan_error is not None:  # the metadata pass stopped early: say where
            raise self._scan_error

    def _damaged_file(self, err) -> Path:
        text = str(err)
        for f in self.files:
            if str(f) in text or f.name in text:
                return f
        return self.files[0] if len(self.files) == 1 else self.path

    def close(self):
        if self._reader is not None:
            try:
                self._reader.close()
            except Exception:  # noqa: BLE001
                pass
            self._reader = None
        if isinstance(self._scan, _Sqlite3Scan):
            self._scan.close()
        if self._tmp:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None

    def __exit__(self, *exc):
        self.close()
        return False


def select_topics(topics: list[Topic], depth_topic: str | None, info_topic: str | None,
                  exclude_prefix: str | None = None) -> tuple[str, str]:
    """The depth and camera_info topics: given, or the only candidate of each type.

    With several Image topics, those with 'depth' in their name are preferred; with
    several CameraInfo topics, the one in the depth topic's namespace.

    Raises:
        ProcessBagError listing the candidates when the choice is ambiguous or missing.
    """
    def listing(cands):
        return ', '.join(f'{t} ({n} msgs)' if n is not None else t for t, n in cands) or 'none'

    types = {}
    for t in topics:
        types.setdefault(t.topic, (t.msgtype, 0))
        prev = types[t.topic][1]
        types[t.topic] = (t.msgtype, None if t.count is None or prev is None
                          else prev + t.count)
    images = [(k, n) for k, (mt, n) in types.items() if mt == IMAGE_T and
              not (exclude_prefix and k.startswith(exclude_prefix + '/'))]
    infos = [(k, n) for k, (mt, n) in types.items() if mt == INFO_T]
    if depth_topic is None:
        cands = images
        if len(cands) > 1:
            cands = [c for c in images if 'depth' in c[0].lower()]
        if len(cands) != 1:
            raise ProcessBagError(
                f'cannot choose the depth topic: {len(images)} sensor_msgs/msg/Image topics '
                f'({listing(images)}); pass --depth-topic')
        depth_topic = cands[0][0]
    elif depth_topic not in types:
        raise ProcessBagError(f'--depth-topic {depth_topic} is not in the bag; Image topics: '
                              f'{listing(images)}')
    elif types[depth_topic][0] != IMAGE_T:
        raise ProcessBagError(f'--depth-topic {depth_topic} is {types[depth_topic][0]}, '
                              f'not {IMAGE_T}')
    if info_topic is None:
        cands = infos
        if len(cands) > 1:
            ns = depth_topic.rsplit('/', 1)[0]
            cands = [c for c in infos if c[0].rsplit('/', 1)[0] == ns]
        if len(cands) != 1:
            raise ProcessBagError(
                f'cannot choose the camera_info topic: {len(infos)} sensor_msgs/msg/CameraInfo '
                f'topics ({listing(infos)}); pass --info-topic')
        info_topic = cands[0][0]
    elif info_topic not in types:
        raise ProcessBagError(f'--info-topic {info_topic} is not in the bag; CameraInfo '
                              f'topics: {listing(infos)}')
    elif types[info_topic][0] != INFO_T:
        raise ProcessBagError(f'--info-topic {info_topic} is {types[info_topic][0]}, '
                              f'not {INFO_T}')
    return depth_topic, info_topic


# -- per-frame work (in this process or in workers) --------------------------------------
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
    mesh_files: list = field(default_factory=list)


@dataclass(frozen=True)
class OutputOptions(MessageOptions):
    """How outputs are built (the node's publish_* and mesh parameters, ros.outputs) and
    where meshes are exported."""

    export_meshes: str | None = None
    mesh_dir: str = ''


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

    def info(self) -> dict:
        return dict(body=self.body.name, device=str(self.rec.device),
                    joint_names=list(self.body.joint_names[1:]),
                    shape_names=list(self.body.shape_names),
                    num_pose=int(self.body.num_pose_joints), num_shape=int(self.body.num_shape))

    def run(self, job: Job) -> Outcome:
        if job.reset:
            self.rec.reset()
            self.outputs.forget()
        out = Outcome(job.index, 'ok', stamp_ns=job.stamp_ns, frame_id=job.frame_id)
        try:
            res = self.rec.process(job.depth, job.K, stamp_ns=job.stamp_ns)
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
                out.mesh_files = self._export(persons, job)
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

    def _export(self, persons, job: Job) -> list[str]:
        import trimesh
        paths = []
        for i, person in enumerate(persons):
            name = job.mesh_name + (f'_p{i}' if i else '')
            path = os.path.join(self.opts.mesh_dir, f'{name}.{self.opts.export_meshes}')
            mesh = trimesh.Trimesh(np.asarray(person.vertices, np.float64), self.faces,
                                   process=False)
            mesh.export(path)
            paths.append(path)
        return paths


# Worker processes (--workers): one FrameProcessor each, chunks of contiguous frames.
_WORKER: FrameProcessor | None = None


def _worker_init(config: PipelineConfig, opts: OutputOptions, threads: int):
    global _WORKER
    import torch
    torch.set_num_threads(max(1, threads))
    _WORKER = FrameProcessor(config, opts)


def _worker_info() -> dict:
    return _WORKER.info()


def _worker_chunk(jobs: list[Job]) -> list[Outcome]:
    _WORKER.rec.reset()  # tracking holds within a chunk only
    _WORKER.outputs.forget()
    if jobs:  # person IDs unique across chunks: a chunk's start at most max_persons a frame
        _WORKER.rec.tracker.start_ids_at(
            1 + jobs[0].index * max(1, _WORKER.rec.config.max_persons))
    return [_WORKER.run(j) for j in jobs]


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

    def submit(self, job: Job, ready: dict):
        ready[job.index] = self.proc.run(job)

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
        self.info = self.pool.submit(_worker_info).result()

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
                for o in fut.result():
                    ready[o.index] = o
            except Exception as e:  # noqa: BLE001 - a worker died: account for its frames
                for j in jobs:
                    ready[j.index] = Outcome(j.index, 'internal', f'worker failed: '
                                             f'{type(e).__name__}: {e}', j.stamp_ns,
                                             j.frame_id)
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


# -- the run --------------------------------------------------------------------------------
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


def _peak_rss_mb(who=resource.RUSAGE_SELF) -> float:
    kb = resource.getrusage(who).ru_maxrss  # kilobytes on Linux, bytes on macOS
    return round(kb / (1024 * 1024 if sys.platform == 'darwin' else 1024), 1)


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
                log: Callable[[str], None] | None = None, reconstructor=None
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
        workers: processes (1 = this process, tracking over the whole bag).
        chunk_size: frames per worker task (tracking restarts at each chunk).
        output_ns: namespace of the output topics (the node's '~').
        progress: show progress (tqdm on a TTY, else log lines).
        log: where messages go (default: stderr).
        reconstructor: an already loaded `pipeline.Reconstructor` to use instead of loading
            one (workers=1 only; it gets `config`, except the device it was built for).

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
        opts = OutputOptions(**opts_d, export_meshes=export_meshes, mesh_dir=str(mesh_dir))
        n_depth = sum(t.count for t in src.topics if t.topic == depth_topic) if all(
            t.count is not None for t in src.topics if t.topic == depth_topic) else None
        t_load = time.perf_counter()
        try:
            # The message inside: a Ctrl-C as soon as it is out counts as during loading.
            log(f"depth '{depth_topic}' ({n_depth if n_depth is not None else '?'} frames), "
                f"camera_info '{info_topic}'; loading the model on {config.device} "
                f'({workers} worker{"s" if workers > 1 else ""})')
            runner = (_InlineRunner(config, opts, reconstructor) if workers == 1 else
                      _PoolRunner(config, opts, workers, chunk_size))
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
                          depth_topic, info_topic, out_topics, progress, log, n_depth)
        except BaseException:
            runner.close()
            raise
        t_loop = time.perf_counter()
        run.run()
        loop_s = time.perf_counter() - t_loop

    rows = run.rows
    results_path = out_dir / 'results.npz'
    save_results(results_path, rows, run.bag_times, run.duplicate, run.resets, runner.info,
                 config)
    ok = [o for o in rows if o.status == 'ok']
    mean_t = {k: round(float(np.mean([o.timings_ms.get(k, np.nan) for o in ok])), 2)
              for k in TIMING_NAMES} if ok else {}
    error = run.error
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
        'wall_s': round(time.perf_counter() - t_start, 2),
        'peak_rss_mb': _peak_rss_mb(),
        'peak_rss_workers_mb': _peak_rss_mb(resource.RUSAGE_CHILDREN) if workers > 1 else None,
        'workers': workers, 'device': runner.info['device'], 'body': runner.info['body'],
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
    }
    assert summary['frames_read'] == summary['processed'] + summary['skipped_total']
    (out_dir / 'summary.json').write_text(json.dumps(summary, indent=2) + '\n')
    return summary


class _BagRun:
    """One pass over the bag: copies every message, turns each depth frame into a job or
    a skip record, and writes outputs in input order through a reorder queue (frames done
    by workers come back later than the messages that follow them)."""

    def __init__(self, src: BagInput, bag_out: Path, storage: str, compress: bool, runner,
                 config: PipelineConfig, depth_topic: str, info_topic: str,
                 out_topics: dict[str, str], progress: bool, log, n_depth: int | None):
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        from smpl_depth_ros.ros import adapters as A
        self.A, self.src, self.runner, self.config, self.log = A, src, runner, config, log
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
        self.cams: dict[str, Any] = {}           # frame_id -> (K, (w, h)) | InputError
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
        if self.runner is not None:
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
            K, _D, size = self.A.camera_info_to_K(msg)
            self.cams[fid] = (K, size)
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
            K, (cw, ch) = cam
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
        self.runner.submit(Job(index, stamp, frame_id, depth, K, reset, name), self.ready)

    # -- outputs -------------------------------------------------------------------------
    def _diag(self, t_bag: int, stamp_ns: int, frame_id: str, statuses):
        A = self.A
        hdr = A.make_header(None, self.factory, stamp_ns=max(stamp_ns, 0), frame_id=frame_id)
        msg = A.diagnostics(hdr, statuses, msgs=self.factory)
        self.writer.write(self.conn_diag, t_bag, bytes(self.jazzy.serialize_cdr(msg, DIAG_T)))
        self.n_written[DIAGNOSTICS_TOPIC] += 1

    def _emit(self, o: Outcome, t_bag: int):
        """Write one frame's outputs (its input's bag time) and diagnostics, in order: a
        WARN entry per skipped frame, a processing summary per second of bag time."""
        A = self.A
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
    cfg = {f.name: getattr(config, f.name) for f in fields(PipelineConfig) if f.name != 'fit'}
    cfg['fit'] = {f.name: getattr(config.fit, f.name) for f in fields(FitConfig)}
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


# -- command line ---------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n')[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog='Exit codes: 0 done, 1 unusable input/options, '
                                        '3 damaged bag (partial results kept), 130 interrupted.')
    ap.add_argument('bag', help='rosbag2 directory, or a .mcap / .db3 file')
    ap.add_argument('--out', required=True, help='output directory')
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
    ap.add_argument('--workers', type=int, default=1, help='processes (default 1)')
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
    args = build_parser().parse_args(argv)
    main_thread = threading.current_thread() is threading.main_thread()
    # SIGTERM as Ctrl-C: the output bag is closed properly and the summary written.
    previous = signal.signal(signal.SIGTERM, _interrupt) if main_thread else None
    try:
        return _run_cli(args)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _run_cli(args) -> int:
    log = (lambda m: None) if args.quiet else (
        lambda m: print(f'{PROG}: {m}', file=sys.stderr, flush=True))
    try:
        params = load_params_file(args.params_file) if args.params_file else {}
        params.update(parse_param_overrides(args.param))
        config, options, ignored = config_from_params(params)
        if args.device:
            config = replace(config, device=args.device)
        if args.no_tracking:
            config = replace(config, tracking=False)
        if ignored:
            log(f'ignoring live-only parameter(s): {", ".join(sorted(ignored))}')
        summary = process_bag(
            args.bag, args.out, config=config, options=options, depth_topic=args.depth_topic,
            info_topic=args.info_topic, storage=args.storage, compress=args.compress,
            export_meshes=args.export_meshes, workers=args.workers,
            chunk_size=args.chunk_size, overwrite=args.overwrite, output_ns=args.output_ns,
            progress=not args.quiet, log=log)
    except (ProcessBagError, BagReadError) as e:
        print(f'{PROG}: error: {e}', file=sys.stderr)
        return EXIT_USAGE
    except InterruptedBeforeStart as e:
        print(f'{PROG}: {e}', file=sys.stderr)
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:  # before the bag was opened
        print(f'{PROG}: interrupted before any frame was processed', file=sys.stderr)
        return EXIT_INTERRUPTED
    except (RuntimeError, ValueError, FileNotFoundError) as e:  # model/device problems
        print(f'{PROG}: error: {type(e).__name__}: {e}', file=sys.stderr)
        return EXIT_USAGE
    print(json.dumps(summary))
    if summary['interrupted']:
        return EXIT_INTERRUPTED
    return EXIT_DAMAGED if summary['error'] else EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
