"""Depth-camera ROS 2 bags with `rosbags` only (no rclpy): write, and read back.

Messages are rosbags dataclasses of the Jazzy typestore:

* `sensor_msgs/msg/Image`, encoding '16UC1' (uint16 millimetres, 0 = invalid, the
  openni/realsense convention) or '32FC1' (float32 metres, NaN = invalid as REP 118
  asks); little-endian (is_bigendian = 0), rows packed: step = width * bytes per pixel.
* `sensor_msgs/msg/CameraInfo` with the same header: K, P = [K | 0], R = I,
  distortion_model 'plumb_bob' with D = 0 (synthetic images are undistorted).

Image <-> bytes is `depth_codec`'s (`depth_to_bytes` with invalid pixels written as
NaN in 32FC1, `bytes_to_depth`): depth in metres is rounded to millimetres (16UC1) or
cast to float32 (32FC1); decoding honours `step` (row padding) and `is_bigendian`, and
returns float32 metres with 0 for invalid (0, NaN, inf, negative).
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from smpl_depth_ros.depth_codec import bytes_to_depth, check_encoding, depth_to_bytes
from smpl_depth_ros.stamps import ns_to_stamp, stamp_to_ns

DEPTH_TOPIC = '/camera/depth/image_raw'
INFO_TOPIC = '/camera/depth/camera_info'
FRAME_ID = 'camera_depth_optical_frame'
STORAGES = ('mcap', 'sqlite3')


def jazzy_typestore():
    """The rosbags typestore for ROS 2 Jazzy."""
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


def _header(typestore, stamp_ns: int, frame_id: str):
    T = typestore.types
    sec, nsec = ns_to_stamp(stamp_ns)
    return T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](sec=sec, nanosec=nsec),
                                    frame_id=frame_id)


def image_msg(depth: np.ndarray, stamp_ns: int, frame_id: str = FRAME_ID,
              encoding: str = '16UC1', typestore=None):
    """A rosbags sensor_msgs/msg/Image of (H, W) depth in metres."""
    typestore = typestore or jazzy_typestore()
    data, step = depth_to_bytes(depth, encoding, nan_invalid=True)
    return typestore.types['sensor_msgs/msg/Image'](
        header=_header(typestore, stamp_ns, frame_id), height=int(depth.shape[0]),
        width=int(depth.shape[1]), encoding=encoding, is_bigendian=0, step=step, data=data)


def camera_info_msg(K: np.ndarray, width: int, height: int, stamp_ns: int,
                    frame_id: str = FRAME_ID, typestore=None):
    """A rosbags sensor_msgs/msg/CameraInfo: plumb_bob, D = 0, R = I, P = [K | 0]."""
    typestore = typestore or jazzy_typestore()
    T = typestore.types
    K = np.asarray(K, np.float64).reshape(3, 3)
    P = np.zeros((3, 4))
    P[:, :3] = K
    return T['sensor_msgs/msg/CameraInfo'](
        header=_header(typestore, stamp_ns, frame_id), height=int(height), width=int(width),
        distortion_model='plumb_bob', d=np.zeros(5), k=K.reshape(-1).copy(),
        r=np.eye(3).reshape(-1), p=P.reshape(-1),
        binning_x=0, binning_y=0,
        roi=T['sensor_msgs/msg/RegionOfInterest'](x_offset=0, y_offset=0, height=0, width=0,
                                                  do_rectify=False))


def write_depth_bag(path: str | Path, frames_iter: Iterable[tuple[int, np.ndarray]], camera,
                    encoding: str = '16UC1', storage: str = 'mcap', *,
                    frame_id: str = FRAME_ID, depth_topic: str = DEPTH_TOPIC,
                    info_topic: str = INFO_TOPIC, typestore=None) -> int:
    """Write a depth-camera bag: one Image and one CameraInfo per frame, same header.

    Args:
        path: bag directory to create (must not exist).
        frames_iter: (stamp_ns, depth (H, W) metres) pairs; the stamp is both the header
            stamp and the bag's receive time.
        camera: synth.camera.Camera (or anything with K, width, height).
        encoding: '16UC1' or '32FC1'.
        storage: 'mcap' or 'sqlite3'.
        frame_id, depth_topic, info_topic: names.
        typestore: rosbags typestore (default Jazzy).

    Returns:
        Number of frames written.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    if storage not in STORAGES:
        raise ValueError(f'storage must be one of {STORAGES}, got {storage!r}')
    check_encoding(encoding)
    typestore = typestore or jazzy_typestore()
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    img_t, info_t = 'sensor_msgs/msg/Image', 'sensor_msgs/msg/CameraInfo'
    K = np.asarray(camera.K, np.float64)
    n = 0
    with Writer(Path(path), version=9, storage_plugin=plugin) as writer:
        c_img = writer.add_connection(depth_topic, img_t, typestore=typestore)
        c_info = writer.add_connection(info_topic, info_t, typestore=typestore)
        for stamp_ns, depth in frames_iter:
            if depth.shape != (camera.height, camera.width):
                raise ValueError(f'frame {n}: depth {depth.shape} does not match the camera '
                                 f'({camera.height}, {camera.width})')
            stamp_ns = int(stamp_ns)
            img = image_msg(depth, stamp_ns, frame_id, encoding, typestore)
            info = camera_info_msg(K, camera.width, camera.height, stamp_ns, frame_id,
                                   typestore)
            writer.write(c_info, stamp_ns, typestore.serialize_cdr(info, info_t))
            writer.write(c_img, stamp_ns, typestore.serialize_cdr(img, img_t))
            n += 1
    for f in Path(path).glob('*.mcap'):
        mcap_write_chunk_crcs(f)
    return n


def iter_depth_bag(path: str | Path, depth_topic: str = DEPTH_TOPIC,
                   info_topic: str | None = INFO_TOPIC
                   ) -> Iterator[tuple[int, np.ndarray, np.ndarray | None]]:
    """Read a depth bag back in receive-time order.

    Yields:
        (header stamp ns, depth (H, W) float32 metres with 0 invalid, K (3, 3) or None):
        K of the CameraInfo with the same header stamp, else of the latest earlier one.
    """
    from rosbags.highlevel import AnyReader

    with AnyReader([Path(path)], default_typestore=jazzy_typestore()) as reader:
        infos: dict[int, np.ndarray] = {}
        if info_topic:
            conns = [c for c in reader.connections if c.topic == info_topic]
            for conn, _t, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                infos[stamp_to_ns(msg.header.stamp)] = np.asarray(msg.k, np.float64).reshape(3, 3)
        info_stamps = np.array(sorted(infos), np.int64)
        conns = [c for c in reader.connections if c.topic == depth_topic]
        for conn, _t, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = stamp_to_ns(msg.header.stamp)
            i = np.searchsorted(info_stamps, stamp, side='right') - 1
            K = infos[int(info_stamps[i])] if i >= 0 else None
            depth = bytes_to_depth(msg.data, int(msg.width), int(msg.height), msg.encoding,
                                   int(msg.step), bool(msg.is_bigendian))
            yield stamp, depth, K


# -- MCAP chunk CRCs ----------------------------------------------------------------------
# rosbags writes MCAP chunks with uncompressed_crc = 0 ("not computed" in the MCAP spec),
# so a flipped byte in an image payload goes unnoticed. `mcap_write_chunk_crcs` fills
# them in after writing; readers check them (rosbags' reader raises 'Chunk checksum
# mismatch', which process_bag reports as a damaged bag).
MCAP_MAGIC = b'\x89MCAP0\r\n'
_CHUNK = 0x06


def _chunk_records(comp: str, data) -> bytes:
    if comp == '':
        return bytes(data)
    if comp == 'zstd':
        try:
            from compression import zstd
        except ImportError:
            from backports import zstd
        return zstd.decompress(bytes(data))
    if comp == 'lz4':
        from lz4.frame import decompress
        return decompress(bytes(data))
    raise ValueError(f'unsupported chunk compression {comp!r}')


def mcap_chunks(buf) -> Iterator[tuple[int, int, int, int, bytes]]:
    """(offset of the CRC field, stored CRC, first message time, chunk offset, the
    chunk's uncompressed records) of every chunk of an MCAP file's bytes, in file order;
    stops at the first record that runs past the end."""
    import struct
    pos, n = len(MCAP_MAGIC), len(buf)
    if bytes(buf[:pos]) != MCAP_MAGIC:
        return
    while pos + 9 <= n:
        op = buf[pos]
        (length,) = struct.unpack_from('<Q', buf, pos + 1)
        body = pos + 9
        if body + length > n:
            return
        if op == _CHUNK:
            t0, _t1, _usize, crc = struct.unpack_from('<QQQI', buf, body)
            (clen,) = struct.unpack_from('<I', buf, body + 28)
            comp = bytes(buf[body + 32:body + 32 + clen]).decode('utf-8', 'replace')
            at = body + 32 + clen
            (dlen,) = struct.unpack_from('<Q', buf, at)
            data = buf[at + 8:at + 8 + dlen]
            try:
                records = _chunk_records(comp, data)
            except Exception:  # noqa: BLE001 - damaged compressed data: CRC of nothing
                records = b''
            yield body + 24, crc, t0, pos, records
        pos = body + length


def mcap_write_chunk_crcs(path: str | Path) -> int:
    """Fill in the CRC32 of every chunk that has none; returns how many were written."""
    import mmap
    import struct
    import zlib
    done = 0
    with open(path, 'r+b') as f, mmap.mmap(f.fileno(), 0) as buf:
        for at, crc, _t0, _pos, records in list(mcap_chunks(buf)):
            if crc == 0:  # (a true CRC of 0 stays 0: "not computed")
                struct.pack_into('<I', buf, at, zlib.crc32(records))
                done += 1
        buf.flush()
    return done
