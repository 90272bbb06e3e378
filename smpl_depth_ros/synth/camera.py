"""Pinhole depth-camera models for synthetic data (no ROS).

Intrinsics follow ROS `sensor_msgs/CameraInfo`: pixel (u, v) sees the ray
((u - cx) / fx, (v - cy) / fy, 1) in the camera optical frame (x right, y down,
z forward), with u, v measured from the centre of the top-left pixel. Depth images store
z (not ray length).

Presets (`CAMERAS`) are typical values, not any one unit's calibration: real devices
differ by a few per cent, and a real stream should always use its own CameraInfo.

* kinect_v1: 640x480, fx = fy = 525, c = (319.5, 239.5): the ROS openni_camera default
  and the TUM RGB-D benchmark's "default intrinsics". Range: Microsoft's default mode is
  0.8-4 m; the device returns data from about 0.5 m to 8 m (noisy far away).
* kinect_v2: 512x424, fx = fy ~ 365.5, c ~ (257, 205): typical libfreenect2 factory IR
  parameters (70.6 x 60 degree FOV). Range 0.5-4.5 m nominal, data to about 8 m.
* realsense_d435: 848x480 depth stream (the recommended resolution), fx = fy ~ 424,
  c = (424, 240): the 1280x800 imager (fx ~ 640) scaled by 0.6625 (depth HFOV ~87
  degrees). Its 640x480 mode is a 4:3 crop of the imager scaled by 0.6, fx = fy ~ 384,
  c = (320, 240): preset 'realsense_d435_640x480', which `get_camera('realsense_d435',
  640, 480)` returns (plain `scaled(640, 480)` would stretch the pixels instead).
  Range 0.3-10 m.
* oak_d: 640x400 stereo depth (OV9282 pair at 400P), fx = fy ~ 400, c = (320, 200);
  range ~0.35 m (extended disparity) to ~12 m.
* azure_kinect_nfov: 640x576 NFOV unbinned, fx = fy ~ 504, c ~ (320, 288) (typical
  factory calibration values are within a few pixels). Range 0.5-3.86 m (Microsoft's
  operating range for this mode; the device invalidates pixels beyond it).
* azure_kinect_nfov_binned: 320x288 NFOV 2x2 binned, fx = fy ~ 252, c ~ (160, 144);
  range 0.5-5.46 m.
* astra: Orbbec Astra, 640x480, fx = fy ~ 570, c = (319.5, 239.5) (58.4 x 45.5 degree
  FOV); range 0.6-8 m.
* realsense_d455: 848x480, fx = fy ~ 428 (86 x 57 degree depth FOV), c = (424, 240);
  range 0.4-10 m (95 mm baseline).
* oak_d_pro: 640x400 like oak_d (the same OV9282 pair, an IR dot projector added).
The noise models that go with them are in `synth.sensors`.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class Camera:
    """A pinhole depth camera.

    Attributes:
        width, height: image size in pixels.
        fx, fy: focal lengths in pixels.
        cx, cy: principal point in pixels (centre of the top-left pixel = 0, 0).
        name: preset name (free text).
        min_range, max_range: metres; depth outside is reported as 0 (invalid).
        depth_unit: metres per unit of the integer (16UC1) encoding, 0.001 = mm.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    name: str = 'custom'
    min_range: float = 0.3
    max_range: float = 10.0
    depth_unit: float = 0.001

    def __post_init__(self):
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f'image size must be positive, got {self.width}x{self.height}')
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f'focal lengths must be positive, got {self.fx}, {self.fy}')
        if not 0 <= self.min_range < self.max_range:
            raise ValueError(f'bad range [{self.min_range}, {self.max_range}]')

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx],
                         [0.0, self.fy, self.cy],
                         [0.0, 0.0, 1.0]], dtype=np.float64)

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width), numpy image shape."""
        return (self.height, self.width)

    def scaled(self, width: int, height: int) -> 'Camera':
        """The same camera resampled to width x height (pixel-centre convention).

        A pixel-centre coordinate u maps to (u + 0.5) * s - 0.5, so the image borders
        stay where they are: scaling 640x480 with c = (319.5, 239.5) to 320x240 gives
        c = (159.5, 119.5) and f / 2. A different aspect ratio gives fx != fy (a
        stretched image), which is rarely what a real sensor mode does.
        """
        sx, sy = width / self.width, height / self.height
        return replace(self, width=int(width), height=int(height),
                       fx=self.fx * sx, fy=self.fy * sy,
                       cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5)

    def project(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) optical-frame points -> (N, 2) pixel coordinates (z must be > 0)."""
        p = np.asarray(points, dtype=np.float64)
        return np.stack([self.fx * p[:, 0] / p[:, 2] + self.cx,
                         self.fy * p[:, 1] / p[:, 2] + self.cy], axis=1)

    def backproject(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) depth (z, metres) -> (H, W, 3) optical-frame points (0 where invalid)."""
        if depth.shape != self.shape:
            raise ValueError(f'depth must be {self.shape}, got {depth.shape}')
        v, u = np.mgrid[0:self.height, 0:self.width]
        z = depth.astype(np.float64)
        return np.stack([(u - self.cx) / self.fx * z, (v - self.cy) / self.fy * z, z], -1)


CAMERAS: dict[str, Camera] = {
    'kinect_v1': Camera(640, 480, 525.0, 525.0, 319.5, 239.5, name='kinect_v1',
                        min_range=0.5, max_range=8.0),
    'kinect_v2': Camera(512, 424, 365.5, 365.5, 257.0, 205.0, name='kinect_v2',
                        min_range=0.5, max_range=8.0),
    'realsense_d435': Camera(848, 480, 424.0, 424.0, 424.0, 240.0, name='realsense_d435',
                             min_range=0.3, max_range=10.0),
    'realsense_d435_640x480': Camera(640, 480, 384.0, 384.0, 320.0, 240.0,
                                     name='realsense_d435_640x480', min_range=0.3,
                                     max_range=10.0),
    'oak_d': Camera(640, 400, 400.0, 400.0, 320.0, 200.0, name='oak_d',
                    min_range=0.35, max_range=12.0),
    'azure_kinect_nfov': Camera(640, 576, 504.0, 504.0, 320.0, 288.0,
                                name='azure_kinect_nfov', min_range=0.5, max_range=3.86),
    'azure_kinect_nfov_binned': Camera(320, 288, 252.0, 252.0, 160.0, 144.0,
                                       name='azure_kinect_nfov_binned', min_range=0.5,
                                       max_range=5.46),
    'astra': Camera(640, 480, 570.0, 570.0, 319.5, 239.5, name='astra', min_range=0.6,
                    max_range=8.0),
    'realsense_d455': Camera(848, 480, 428.0, 428.0, 424.0, 240.0, name='realsense_d455',
                             min_range=0.4, max_range=10.0),
    'oak_d_pro': Camera(640, 400, 400.0, 400.0, 320.0, 200.0, name='oak_d_pro',
                        min_range=0.35, max_range=12.0),
}


def get_camera(name: str, width: int | None = None, height: int | None = None) -> Camera:
    """A preset by name, optionally resampled to width x height.

    A size with a preset of its own ('<name>_<W>x<H>', e.g. the D435's 640x480 crop) gives
    that preset; any other size is `Camera.scaled` from the base preset.
    """
    if width is not None and height is not None and f'{name}_{width}x{height}' in CAMERAS:
        return CAMERAS[f'{name}_{width}x{height}']
    try:
        cam = CAMERAS[name]
    except KeyError:
        raise ValueError(f'unknown camera {name!r}; presets: {sorted(CAMERAS)}') from None
    if width is not None or height is not None:
        w = width if width is not None else round(cam.width * height / cam.height)
        h = height if height is not None else round(cam.height * width / cam.width)
        cam = cam.scaled(w, h)
    return cam
