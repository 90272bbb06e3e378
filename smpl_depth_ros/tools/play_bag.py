"""play_bag: replay a ROS 2 bag into a live ROS graph with rclpy (no rosbag2 needed).

    play_bag BAG [--rate 1.0] [--loop] [--topics T [T ...]] [--qos reliable|best_effort]
             [--start-delay 1.0] [--wait-for-subscribers 10] [--ros-args ...]
    play_bag BAG --pace /reconstructor/mesh --pace-timeout 30   # one frame at a time
    play_bag BAG --clock        # also publish the bag time on /clock (use_sim_time)

For machines with rclpy from pip but no `ros2 bag` (CI, a laptop without a ROS install):
messages are read one at a time with `rosbags` (a rosbag2 directory, or one .mcap or .db3
file; the readable part of a damaged file too) and published with the recorded timing
(bag timestamps, scaled by --rate). Headers are not rewritten: outputs of a node fed this
way carry the recorded stamps.

Each topic gets a publisher of its rclpy message class (`rosidl_runtime_py`'s get_message
when installed, else `importlib` of '<pkg>.msg'). The recorded CDR is checked once per
topic with `rclpy.serialization.deserialize_message` and then published as is (rclpy
publishes serialized bytes, exactly what rosbag2 does); `--deserialize` converts every
message instead. Topics whose message package is not installed are reported and skipped.

QoS: --qos (default reliable) and --qos-depth apply to every publisher; a topic recorded
with transient_local durability (e.g. /tf_static) keeps it. A reliable publisher reaches
best-effort and reliable subscribers alike.

--pace TOPIC: after each message on --pace-after (default: the bag's only Image topic)
wait until a message arrives on TOPIC (or --pace-timeout passes), then go on with the
recorded timing from there. A node slower than the recording then gets every frame (no
frame replaced in its one-slot queue), which makes a live run comparable frame by frame
with `process_bag`.

--clock [HZ]: publish rosgraph_msgs/Clock on /clock (as `ros2 bag play --clock`): the bag
time at HZ (default 40) and right before every message, scaled by --rate, held while
--pace waits; each --loop starts again at the bag's first time. Nodes run with
`-p use_sim_time:=true` then see the recorded time.

ROS arguments after --ros-args work as for any node: remap a recorded topic with
`--ros-args -r /camera/depth/image_raw:=/depth`. Ctrl-C stops cleanly. A JSON summary
(messages per topic, seconds, loops) is printed on stdout at the end.
"""
from __future__ import annotations

import argparse
import importlib
import json
import signal
import sys
import threading
import time
from collections import Counter

PROG = 'play_bag'


def message_class(msgtype: str):
    """The rclpy message class of 'pkg/msg/Name' (None when its package is missing)."""
    try:
        from rosidl_runtime_py.utilities import get_message
        return get_message(msgtype)
    except ImportError:
        pass
    except (AttributeError, ModuleNotFoundError, ValueError):
        return None
    try:
        pkg, kind, name = msgtype.split('/')
        return getattr(importlib.import_module(f'{pkg}.{kind}'), name)
    except (ValueError, ImportError, AttributeError):
        return None


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n')[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('bag', help='rosbag2 directory, or a .mcap / .db3 file')
    ap.add_argument('--rate', type=float, default=1.0, help='playback speed factor')
    ap.add_argument('--loop', action='store_true', help='start again at the end')
    ap.add_argument('--topics', nargs='+', default=None, help='only these topics')
    ap.add_argument('--qos', default='reliable', choices=['reliable', 'best_effort'],
                    help='publisher reliability (default reliable)')
    ap.add_argument('--qos-depth', type=int, default=10, help='publisher history depth')
    ap.add_argument('--start-delay', type=float, default=0.0,
                    help='seconds to wait after creating the publishers')
    ap.add_argument('--wait-for-subscribers', type=float, default=0.0, metavar='SECONDS',
                    help='before playing, wait up to this long until every publisher has '
                         'a subscriber')
    ap.add_argument('--pace', default=None, metavar='TOPIC',
                    help='after each --pace-after message, wait for a message on TOPIC')
    ap.add_argument('--pace-after', default=None, metavar='TOPIC',
                    help='input topic that --pace waits after (default: the only Image '
                         'topic played)')
    ap.add_argument('--pace-timeout', type=float, default=30.0,
                    help='longest wait for a --pace message (s)')
    ap.add_argument('--clock', type=float, nargs='?', const=40.0, default=0.0, metavar='HZ',
                    help='publish the bag time on /clock at HZ (40 when no value is given)')
    ap.add_argument('--deserialize', action='store_true',
                    help='publish deserialized rclpy messages instead of the recorded CDR')
    ap.add_argument('--quiet', action='store_true', help='no log lines')
    return ap


def clock_ns(clock: dict, wall: float, rate: float) -> int | None:
    """The bag time (ns) a /clock timer tick publishes at monotonic time `wall`.

    `clock`: t0 (bag ns of the first message, None before it) played at wall time w0;
    `hold` (ns) while --pace waits; `next`, the bag time of the message about to be
    published, which the tick never passes: a tick that runs late, after that message's
    due time, would otherwise stamp a later time than the message's own /clock and send
    the clock backwards (seen in CI on a loaded machine).
    """
    if clock['t0'] is None:
        return None
    if clock['hold'] is not None:
        return int(clock['hold'])
    ns = clock['t0'] + round((wall - clock['w0']) * rate * 1e9)
    return ns if clock['next'] is None else min(ns, int(clock['next']))


class _Stop(Exception):
    pass


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv=None) -> int:
    import rclpy
    import rclpy.utilities
    from rclpy.context import Context
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)
    from rclpy.serialization import deserialize_message

    from smpl_depth_ros.offline import BagInput, BagReadError, ProcessBagError
    from smpl_depth_ros.ros.runner import shutdown_rclpy

    raw_args = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(rclpy.utilities.remove_ros_args([PROG] + raw_args)[1:])
    log = (lambda m: None) if args.quiet else (
        lambda m: print(f'{PROG}: {m}', file=sys.stderr, flush=True))
    if args.rate <= 0 or args.clock < 0:
        print(f'{PROG}: error: --rate must be > 0 and --clock >= 0', file=sys.stderr)
        return 1

    context = Context()
    rclpy.init(args=[PROG] + raw_args, context=context)
    main_thread = threading.current_thread() is threading.main_thread()
    # SIGTERM like Ctrl-C: stop cleanly and print the summary.
    previous = signal.signal(signal.SIGTERM, _interrupt) if main_thread else None
    node = executor = None
    sent = Counter()
    summary = dict(bag=args.bag, loops=0, interrupted=False, error=None)
    t_begin = time.monotonic()
    code = 0
    try:
        with BagInput(args.bag) as src:
            if src.recovered:
                log(f'{args.bag} is damaged ({src.open_error}); playing its readable part')
            wanted = set(args.topics) if args.topics else None
            names = {t.topic for t in src.topics}
            if wanted and wanted - names:
                raise ProcessBagError(f'topic(s) not in the bag: {sorted(wanted - names)}; '
                                      f'it has {sorted(names)}')
            node = rclpy.create_node(PROG, context=context)
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(node)
            pubs, classes, checked = {}, {}, set()
            for t in src.topics:
                if (wanted and t.topic not in wanted) or t.topic in pubs:
                    continue
                cls = message_class(t.msgtype)
                if cls is None:
                    log(f"skipping '{t.topic}': message type {t.msgtype} is not installed")
                    continue
                transient = any(getattr(q.durability, 'name', '') == 'TRANSIENT_LOCAL'
                                for q in t.qos)
                qos = QoSProfile(
                    history=HistoryPolicy.KEEP_LAST, depth=max(1, args.qos_depth),
                    reliability=ReliabilityPolicy.RELIABLE if args.qos == 'reliable'
                    else ReliabilityPolicy.BEST_EFFORT,
                    durability=DurabilityPolicy.TRANSIENT_LOCAL if transient
                    else DurabilityPolicy.VOLATILE)
                pubs[t.topic] = node.create_publisher(cls, t.topic, qos)
                classes[t.topic] = cls
            if not pubs:
                raise ProcessBagError('nothing to play: no topic with an installed message '
                                      'type was selected')
            # Bag time for /clock: t0 (ns) at wall time w0, or held at `hold` (ns); the
            # timer never runs past `next`, the time of the message about to be published
            # (a late timer tick would otherwise stamp a time that the message's own
            # /clock then sends backwards).
            clock = dict(t0=None, w0=0.0, hold=None, next=None)
            # Reliable publishers whose last messages must reach their subscribers (the
            # slow ones included) before exit.
            acked = list(pubs.values()) if args.qos == 'reliable' else []
            if args.clock > 0:
                from rosgraph_msgs.msg import Clock
                clock_pub = node.create_publisher(Clock, '/clock', QoSProfile(
                    depth=1, reliability=ReliabilityPolicy.RELIABLE))
                acked.append(clock_pub)  # the last message's time must arrive too

                def publish_clock(ns=None):
                    if ns is None:
                        ns = clock_ns(clock, time.monotonic(), args.rate)
                        if ns is None:
                            return
                    msg = Clock()
                    msg.clock.sec, msg.clock.nanosec = divmod(int(ns), 1_000_000_000)
                    clock_pub.publish(msg)
                node.create_timer(1.0 / args.clock, publish_clock)
            else:
                def publish_clock(ns=None):
                    pass
            log('publishing ' + ', '.join(f"'{p.topic_name}'" for p in pubs.values()) +
                f' ({args.qos})')

            pace = None
            if args.pace:
                after = args.pace_after
                if after is None:
                    imgs = [t.topic for t in src.topics
                            if t.topic in pubs and t.msgtype == 'sensor_msgs/msg/Image']
                    if len(set(imgs)) != 1:
                        raise ProcessBagError('--pace needs --pace-after: the played Image '
                                              f'topics are {sorted(set(imgs))}')
                    after = imgs[0]
                elif after not in pubs:
                    raise ProcessBagError(f'--pace-after {after} is not a played topic')
                pace = dict(after=after, count=0)

            def spin_for(seconds: float, until=None):
                end = time.monotonic() + seconds
                while True:
                    if not context.ok():
                        raise _Stop()
                    if until is not None and until():
                        return True
                    left = end - time.monotonic()
                    if left <= 0:
                        return until() if until is not None else True
                    executor.spin_once(timeout_sec=min(left, 0.05))

            if args.wait_for_subscribers > 0:
                ok = spin_for(args.wait_for_subscribers, lambda: all(
                    p.get_subscription_count() > 0 for p in pubs.values()))
                if not ok:
                    lonely = [p.topic_name for p in pubs.values()
                              if p.get_subscription_count() == 0]
                    log(f'no subscriber after {args.wait_for_subscribers:g} s on: '
                        f'{", ".join(lonely)}; playing anyway')
            if pace is not None:
                pace_topic = node.resolve_topic_name(args.pace)

                def pace_type():
                    for name, types in node.get_topic_names_and_types():
                        if name == pace_topic and types:
                            return types[0]
                    return None
                found = [None]

                def look() -> bool:
                    found[0] = pace_type()
                    return found[0] is not None
                typ = found[0] if spin_for(max(args.pace_timeout, 1.0), look) else None
                if typ is None:
                    raise ProcessBagError(f'--pace {pace_topic}: no such topic in the graph '
                                          f'after {args.pace_timeout:g} s')
                pcls = message_class(typ)
                if pcls is None:
                    raise ProcessBagError(f'--pace {pace_topic}: type {typ} is not installed')

                def on_pace(_msg):
                    pace['count'] += 1
                node.create_subscription(pcls, pace_topic, on_pace, QoSProfile(
                    depth=100, reliability=ReliabilityPolicy.RELIABLE), raw=True)
            if args.start_delay > 0:
                spin_for(args.start_delay)

            playing = set(pubs)
            while True:
                t0_bag = None
                w0 = time.monotonic()
                for topic, t_bag, raw in src.messages(playing):
                    if t0_bag is None:
                        t0_bag = t_bag
                        clock.update(t0=t_bag, w0=w0)
                    clock['next'] = t_bag
                    due = w0 + (t_bag - t0_bag) * 1e-9 / args.rate
                    spin_for(max(0.0, due - time.monotonic()))
                    publish_clock(t_bag)
                    name = topic.topic
                    data = bytes(raw)
                    if args.deserialize or name not in checked:
                        try:
                            msg = deserialize_message(data, classes[name])
                        except Exception as e:  # noqa: BLE001
                            raise ProcessBagError(
                                f"'{name}': the recorded {topic.msgtype} does not decode as "
                                f'the installed message ({type(e).__name__}: {e})') from None
                        checked.add(name)
                        pubs[name].publish(msg if args.deserialize else data)
                    else:
                        pubs[name].publish(data)
                    sent[name] += 1
                    if pace is not None and name == pace['after']:
                        before = pace['count']
                        t_wait = time.monotonic()
                        clock['hold'] = t_bag
                        if not spin_for(args.pace_timeout, lambda: pace['count'] > before):
                            log(f'--pace: nothing on {pace_topic} within '
                                f'{args.pace_timeout:g} s; going on')
                        w0 += time.monotonic() - t_wait  # keep the recorded spacing
                        clock.update(w0=clock['w0'] + time.monotonic() - t_wait, hold=None)
                summary['loops'] += 1
                if not args.loop:
                    break
            from rclpy.duration import Duration
            for p in acked:
                p.wait_for_all_acked(Duration(seconds=2.0))
    except BagReadError as e:
        summary['error'] = str(e)
        print(f'{PROG}: error: {e}', file=sys.stderr)
        code = 3
    except ProcessBagError as e:
        summary['error'] = str(e)
        print(f'{PROG}: error: {e}', file=sys.stderr)
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException, _Stop):
        summary['interrupted'] = True
    finally:
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.destroy_node()
        shutdown_rclpy(context=context)
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    summary['seconds'] = round(time.monotonic() - t_begin, 2)
    summary['messages'] = dict(sorted(sent.items()))
    summary['total'] = int(sum(sent.values()))
    print(json.dumps(summary), flush=True)
    return code


if __name__ == '__main__':
    sys.exit(main())
