"""Reading rosbag2 bags one message at a time, damaged ones too: `BagInput` (rosbags'
AnyReader, or the readable part of a truncated or corrupt MCAP / sqlite3 file through
`_McapScan` / `_Sqlite3Scan`), the choice of the depth and camera_info topics
(`select_topics`), and which paths are bags (`is_bag`, `bags_in`)."""
from __future__ import annotations

import shutil
import sqlite3
import struct
import tempfile
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Iterator

from smpl_depth_ros.offline.errors import BagReadError, ProcessBagError

IMAGE_T = 'sensor_msgs/msg/Image'
INFO_T = 'sensor_msgs/msg/CameraInfo'


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


def is_bag(path: Path) -> bool:
    """A .mcap / .db3 file, or a rosbag2 directory (metadata.yaml or storage files)."""
    if path.is_file():
        return path.suffix in ('.mcap', '.db3')
    return path.is_dir() and ((path / 'metadata.yaml').is_file() or any(
        p.suffix in ('.mcap', '.db3') and p.is_file() for p in path.iterdir()))


def bags_in(folder: Path) -> list[Path]:
    """The bags directly inside `folder`, by name; [] when it is a bag itself."""
    if not folder.is_dir() or is_bag(folder):
        return []
    return sorted(p for p in folder.iterdir() if is_bag(p))


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
    def choose(topic, cands, narrow, what, flag, short, msgtype):
        if topic is None:
            picked = narrow(cands) if len(cands) > 1 else cands
            if len(picked) != 1:
                raise ProcessBagError(
                    f'cannot choose the {what} topic: {len(cands)} {msgtype} topics '
                    f'({listing(cands)}); pass {flag}')
            return picked[0][0]
        if topic not in types:
            raise ProcessBagError(f'{flag} {topic} is not in the bag; {short} topics: '
                                  f'{listing(cands)}')
        if types[topic][0] != msgtype:
            raise ProcessBagError(f'{flag} {topic} is {types[topic][0]}, not {msgtype}')
        return topic

    depth_topic = choose(depth_topic, images,
                         lambda cs: [c for c in cs if 'depth' in c[0].lower()],
                         'depth', '--depth-topic', 'Image', IMAGE_T)
    ns = depth_topic.rsplit('/', 1)[0]
    info_topic = choose(info_topic, infos,
                        lambda cs: [c for c in cs if c[0].rsplit('/', 1)[0] == ns],
                        'camera_info', '--info-topic', 'CameraInfo', INFO_T)
    return depth_topic, info_topic
