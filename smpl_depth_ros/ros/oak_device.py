"""Luxonis OAK devices through depthai 3.x: find, open and run them; the configuration,
pipeline, calibration and frame conversion they use are `ros.oak`'s.

No rclpy here: the `oak_camera` node (`ros.oak_camera_node`) wires this module to topics.

* `find_device`: the first available device matching an MxID / IP / name (or any), or a
  one-line `DeviceNotFoundError` naming what was looked for and what is visible;
* `OakConnection`: an open device running `oak.build_pipeline`; `open_connection` finds
  and opens one; `QueueConnection` is its reading half, and on its own a host-fed
  connection (tests, replay: push `oak.make_host_frame`s into the queue);
* `OakDriver`: reads frames on a thread and keeps the device running across unplugging
  (reconnect with exponential backoff, `backoff_delays`).
"""
from __future__ import annotations

import datetime
import ipaddress
import threading
import time
from typing import Any, Callable

import depthai as dai

from smpl_depth_ros.ros.oak import OakConfig, build_pipeline


class DeviceNotFoundError(RuntimeError):
    """No (matching, free) OAK device."""


class DeviceLostError(RuntimeError):
    """A running device stopped delivering frames."""


def _describe(info: dai.DeviceInfo) -> str:
    state = info.state.name.replace('X_LINK_', '').lower()
    proto = info.protocol.name.replace('X_LINK_', '').lower()
    return f'{info.deviceId or "?"} ({info.name or "?"}, {proto}, {state})'


def _matches(info: dai.DeviceInfo, wanted: str) -> bool:
    return not wanted or wanted in (info.deviceId, info.name)


def _is_ip(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
        return True
    except ValueError:
        return False


def find_device(device_id: str = '', timeout_s: float = 5.0,
                sleep: Callable[[float], Any] = time.sleep) -> dai.DeviceInfo:
    """The first available device matching `device_id` (MxID / device ID, IP, or USB name;
    '' = any), looked for during `timeout_s`.

    Raises:
        DeviceNotFoundError: with one line naming what was looked for and what is visible.
    """
    wanted = device_id.strip()
    deadline = time.monotonic() + max(0.0, timeout_s)
    while True:
        for info in dai.Device.getAllAvailableDevices():
            if _matches(info, wanted):
                return info
        if wanted and _is_ip(wanted):  # PoE outside the broadcast domain: ask directly
            found, info = dai.Device.getDeviceByIdOrName(wanted)
            if found:
                return info
        if time.monotonic() >= deadline:
            break
        sleep(0.2)
    visible = dai.Device.getAllConnectedDevices()
    busy = [i for i in visible if _matches(i, wanted)]
    what = f"OAK device '{wanted}' (MxID, IP or USB name)" if wanted else \
        'any OAK device (USB or PoE)'
    if busy:
        what = f"OAK device '{wanted}'" if wanted else 'every OAK device connected'
        raise DeviceNotFoundError(
            f'{what} is in use (by another process?): '
            f'{", ".join(_describe(i) for i in busy)}')
    seen = ', '.join(_describe(i) for i in visible) or 'none'
    usb = 'check the cable and udev rules (in a container pass /dev/bus/usb)'
    if not wanted:
        hint = f"{usb}, or set device_id to a PoE camera's IP"
    elif _is_ip(wanted):
        hint = "check the camera's power and network (can you ping it?)"
    else:
        hint = f'{usb} and the ID'
    during = f' for {timeout_s:g} s' if timeout_s > 0 else ''
    raise DeviceNotFoundError(f'no OAK device found: looked for {what}{during}; '
                              f'devices visible: {seen}; {hint}')


class QueueConnection:
    """Depth frames from a depthai MessageQueue: the reading half of `OakConnection`, and on
    its own a host-fed connection (tests, replay: push `oak.make_host_frame`s into the
    queue).

    Attributes:
        device_id: the device's MxID / device ID.
        description: product name and id for logs.
        calibration: the device's CalibrationHandler.
    """

    def __init__(self, queue: dai.MessageQueue, calibration: dai.CalibrationHandler,
                 device_id: str = 'host', description: str | None = None):
        self._queue = queue
        self.calibration = calibration
        self.device_id = device_id
        self.description = description or f'host queue {device_id}'

    def _running(self) -> bool:
        return not self._queue.isClosed()

    def get(self, timeout_s: float) -> dai.ImgFrame | None:
        """The next depth frame, or None after `timeout_s`.

        Raises:
            DeviceLostError: the pipeline stopped or the queue closed (device gone).
        """
        if not self._running():
            raise DeviceLostError('the pipeline stopped running')
        try:
            return self._queue.get(datetime.timedelta(seconds=timeout_s))
        except (RuntimeError, dai.MessageQueue.QueueException) as e:  # closed, XLink error
            raise DeviceLostError(str(e) or type(e).__name__) from None

    def close(self):
        try:
            self._queue.close()
        except Exception:  # noqa: BLE001 - closing twice, or a lost device
            pass


class OakConnection(QueueConnection):
    """An open device running the stereo pipeline (`build_pipeline`)."""

    def __init__(self, cfg: OakConfig, info: dai.DeviceInfo):
        self.device = dai.Device(info)
        self.pipeline = None
        try:
            if hasattr(self.device, 'setMaxReconnectionAttempts'):
                self.device.setMaxReconnectionAttempts(0)  # OakDriver reconnects itself
            device_id = str(self.device.getDeviceId())
            try:
                product = str(self.device.getProductName())
            except RuntimeError:
                product = ''
            calibration = self.device.readCalibration()
            self.pipeline = dai.Pipeline(self.device)
            queue = build_pipeline(self.pipeline, cfg)
            super().__init__(queue, calibration, device_id, f'{product or "OAK"} {device_id}')
            self.pipeline.start()
        except Exception:
            self.close()
            raise

    def _running(self) -> bool:
        return self.pipeline.isRunning() and super()._running()

    def close(self):
        if hasattr(self, '_queue'):
            super().close()
        try:
            if self.pipeline is not None and self.pipeline.isRunning():
                self.pipeline.stop()
        except Exception:  # noqa: BLE001 - a lost device may fail to stop cleanly
            pass
        try:
            self.device.close()
        except Exception:  # noqa: BLE001
            pass


def open_connection(cfg: OakConfig, device_id: str | None = None,
                 timeout_s: float | None = None) -> OakConnection:
    """Find (`find_device`) and open a device, start the pipeline.

    Args:
        device_id: overrides cfg.device_id (reconnecting to the same unit).
        timeout_s: overrides cfg.connect_timeout_s.
    """
    wanted = cfg.device_id if device_id is None else device_id
    info = find_device(wanted, cfg.connect_timeout_s if timeout_s is None else timeout_s)
    return OakConnection(cfg, info)


def backoff_delays(initial: float, maximum: float):
    """initial, 2 x initial, 4 x ... capped at maximum (an endless generator)."""
    d = float(initial)
    while True:
        yield min(d, maximum)
        d = min(d * 2.0, maximum)


class OakDriver:
    """Reads frames from a connection on a thread; reconnects with backoff when it fails.

    Callbacks run on the driver thread:
        on_frame(frame: dai.ImgFrame, connection) for every frame;
        on_event(kind, message, info) with kind 'lost' (the connection failed: message says
        why), 'retry' (an attempt to open failed; info has attempt and delay_s, the wait
        before the next one), 'reconnected' (after a loss; info has outage_s and attempts)
        or 'connected' (the first connection when started without one); a raising on_frame is
        reported as 'frame_error' and the loop goes on.

    Args:
        connection: the open first connection (the node opens it before starting, so that a
            missing device fails start-up), or None to look for the device on the thread
            (retrying with backoff: `wait_for_device`).
        reopen: opens a new connection for a device id (default: `open_connection` without
            waiting): cfg.device_id when set, else the MxID of the unit first opened, so
            a re-plugged camera comes back and another one does not take its place.
    """

    def __init__(self, cfg: OakConfig, connection, on_frame: Callable, on_event: Callable,
                 reopen: Callable[[str], Any] | None = None):
        self.cfg = cfg
        self.connection = connection
        self._on_frame = on_frame
        self._on_event = on_event
        self._open = reopen or (lambda dev: open_connection(cfg, device_id=dev, timeout_s=0.0))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='oak-driver', daemon=True)
        self.frames = 0
        self.reconnects = 0

    def start(self):
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> bool:
        """Stop the thread and close the connection; True when the thread ended."""
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout)
        return not self._thread.is_alive()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def _read(self, connection):
        """Frames until the connection fails (raises) or stop is requested."""
        # The first frame after (re)starting a pipeline can take a few seconds.
        timeout = max(self.cfg.frame_timeout_s, 10.0)
        last = time.monotonic()
        while not self._stop.is_set():
            frame = connection.get(min(0.2, self.cfg.frame_timeout_s))
            now = time.monotonic()
            if frame is None:
                if now - last > timeout:
                    raise DeviceLostError(f'no frame for {now - last:.1f} s')
                continue
            last = now
            timeout = self.cfg.frame_timeout_s
            self.frames += 1
            try:
                self._on_frame(frame, connection)
            except Exception as e:  # noqa: BLE001 - one bad frame must not stop the camera
                self._on_event('frame_error', f'{type(e).__name__}: {e}', {})

    def _run(self):
        connection = self.connection
        first = connection is None  # wait_for_device: nothing opened yet
        # Reopen what was asked for (an IP reaches a PoE camera outside the broadcast
        # domain); when that was 'any', the unit found first, by its MxID.
        device_id = self.cfg.device_id or (getattr(connection, 'device_id', '') if connection
                                           is not None else '')
        lost_at = time.monotonic()
        while not self._stop.is_set():
            if connection is None:
                connection = self._reconnect(device_id, lost_at, first)
                if connection is None:
                    return
                first = False
                device_id = self.cfg.device_id or getattr(connection, 'device_id', '')
            try:
                self._read(connection)
            except Exception as e:  # noqa: BLE001 - any failure: report and reconnect
                lost_at = time.monotonic()
                self._on_event('lost', f'{type(e).__name__}: {e}', {'device_id': device_id})
            finally:
                connection.close()
                self.connection = connection = None

    def _reconnect(self, device_id: str, lost_at: float, first: bool):
        """A new connection, retried with backoff; None when stopped first."""
        delays = backoff_delays(self.cfg.reconnect_backoff_s, self.cfg.reconnect_backoff_max_s)
        wait = 0.0 if first else next(delays)
        attempt = 0
        while not self._stop.wait(wait):
            attempt += 1
            try:
                connection = self._open(device_id)
            except Exception as e:  # noqa: BLE001
                wait = next(delays)
                self._on_event('retry', f'{type(e).__name__}: {e}',
                               {'attempt': attempt, 'delay_s': wait, 'device_id': device_id})
                continue
            if self._stop.is_set():
                connection.close()
                return None
            self.connection = connection
            if not first:
                self.reconnects += 1
            self._on_event('connected' if first else 'reconnected',
                           getattr(connection, 'description', device_id),
                           {'outage_s': time.monotonic() - lost_at, 'attempts': attempt,
                            'device_id': getattr(connection, 'device_id', device_id)})
            return connection
        return None
