"""ROS time stamps <-> integer nanoseconds, without ROS: the one conversion of header
stamps for the node's adapters (`ros.adapters`), the bag tools (`bagio`) and process_bag
(`offline`).

A stamp is a builtin_interfaces/Time of either message system (an rclpy message or a
rosbags dataclass: only its `sec` and `nanosec` fields are read); nanoseconds are one
Python int (sec x 10^9 + nanosec).
"""
from __future__ import annotations

import struct

NS_PER_S = 1_000_000_000


def stamp_to_ns(stamp) -> int:
    """builtin_interfaces/Time (either system; e.g. header.stamp) -> integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(stamp_ns: int) -> tuple[int, int]:
    """Integer nanoseconds -> the builtin_interfaces/Time fields (sec, nanosec), with
    0 <= nanosec < 10^9."""
    return divmod(int(stamp_ns), NS_PER_S)


def cdr_stamp_ns(data: bytes) -> int:
    """header.stamp (ns) of a serialized message whose first field is a std_msgs/Header
    (Image, Marker, ...), read from its CDR bytes without deserializing the rest: what a
    raw subscription needs to time a 2 MB mesh without building 82k Point objects."""
    if len(data) < 12 or data[1] not in (0, 1):
        raise ValueError('not a CDR-serialized message')
    sec, nsec = struct.unpack_from('<iI' if data[1] == 1 else '>iI', data, 4)
    return sec * NS_PER_S + nsec
