"""Console-script plumbing shared by the nodes: init, spin, start-up errors, clean exit.

One place for what every entry point must get right: ROS arguments after `--ros-args`
(as `ros2 run` passes them), one line and exit code 1 for a start-up failure (no
traceback), a quiet exit on SIGINT/SIGTERM (also while the models load), workers stopped
before their nodes are destroyed, and an rclpy shutdown that tolerates the race with
rclpy's own signal handler.
"""
from __future__ import annotations

import sys
from typing import Callable, Iterable

import rclpy
import rclpy.logging
import rclpy.utilities
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor


def ros_args(name: str, argv: list[str] | None) -> list[str]:
    """The program name plus the command line (default sys.argv[1:])."""
    return [name] + (sys.argv[1:] if argv is None else list(argv))


def run_nodes(name: str, args: list[str], make_nodes: Callable[[], Iterable],
              executor_factory: Callable = SingleThreadedExecutor,
              describe: Callable[[Exception], str] = lambda e: f'{type(e).__name__}: {e}'
              ) -> int:
    """Init rclpy, build the nodes (each with a `stop() -> bool` for its threads), spin
    until shut down, then stop and destroy them. Returns the process exit code."""
    nodes, executor, code = [], None, 0
    initialised = False
    try:
        # rclpy.init installs the SIGINT/SIGTERM handlers before the nodes load their
        # models, so an early Ctrl-C exits cleanly.
        rclpy.init(args=args)
        initialised = True
        extra = rclpy.utilities.remove_ros_args(args)[1:]
        if extra:
            print(f'{name}: ignoring unknown arguments {extra}', file=sys.stderr)
        executor = executor_factory()
        nodes = list(make_nodes())
        for n in nodes:
            executor.add_node(n)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as e:  # start-up failure: one line, no traceback
        if not initialised or rclpy.ok():
            rclpy.logging.get_logger(name).fatal(describe(e))
            code = 1
        # else: a signal shut the context down while starting (entity creation failed)
    finally:
        for n in reversed(nodes):  # the last built first: it consumes the others' output
            if not n.stop():
                n.get_logger().warning('a worker thread did not stop in time')
        if executor is not None:
            shutdown_executor(executor)
        for n in reversed(nodes):
            n.destroy_node()
        shutdown_rclpy()
    return code


def shutdown_executor(executor, timeout_sec: float = 5.0):
    """Shut down an executor that is no longer spinning.

    A MultiThreadedExecutor's thread pool is drained first: a callback still running there
    triggers the executor's guard condition when it ends, which Jazzy's `shutdown` destroys
    without waiting for it ('cannot use Destroyable' at exit otherwise).
    """
    pool = getattr(executor, '_executor', None)  # MultiThreadedExecutor's ThreadPoolExecutor
    if pool is not None and hasattr(pool, 'shutdown'):
        pool.shutdown(wait=True)
    executor.shutdown(timeout_sec=timeout_sec)


def shutdown_rclpy(context=None) -> None:
    """rclpy.try_shutdown, tolerating the race with rclpy's own SIGINT/SIGTERM handler
    (which may shut the context down between try_shutdown's check and its call)."""
    try:
        rclpy.try_shutdown(context=context)
    except RuntimeError as e:  # rclpy's RCLError: 'rcl_shutdown already called'
        if 'already called' not in str(e):
            raise
