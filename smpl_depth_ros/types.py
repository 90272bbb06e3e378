"""Plain result types shared by the core, the node and offline processing (no ROS)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class InputError(ValueError):
    """A frame the pipeline cannot use. `reason` is a short machine-readable code
    (e.g. 'encoding', 'size_mismatch', 'no_valid_depth', 'no_person', 'bad_intrinsics',
    'too_large', 'no_camera_info'); str(err) is the human-readable message."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


@dataclass
class BodyParams:
    """Fitted body-model parameters (numpy, float32), camera frame.

    pose: (P, 3) axis-angle per fitted joint (model frame, see body.base);
    shape: (S,); global_orient: (3,) axis-angle; transl: (3,) metres.
    """

    pose: np.ndarray
    shape: np.ndarray
    global_orient: np.ndarray
    transl: np.ndarray


@dataclass
class PersonResult:
    """One reconstructed person.

    Attributes:
        params: fitted parameters.
        vertices: (V, 3) float32 fitted mesh, camera frame, metres.
        joints: (J, 3) float32, order of the body model's joint_names.
        bbox: (u0, v0, u1, v1) crop in full-image pixels.
        mask: (H, W) bool, this person's pixels in the full image.
        residual_m: median point-to-correspondence distance after fitting (metres).
        num_points: points used for fitting.
        crop: the net.preprocess.Crop the network saw (its mapping to full-image pixels).
        crop_labels: (S, S) uint8, the network's part labels at its own input resolution
            (0 where the input pixel was invalid).
        track_id: the person's stable ID (>= 1; tracking.Tracker), -1 if untracked.
        joint_confidence: (J,) float32 in [0, 1] per joint of `joints`: how well observed
            pixels and the fit support it (pipeline.joint_confidence).
        score: how much of a body the network sees in its blob (pipeline.body_score:
            the share labelled body times the parts covering >= 2 % of it; 0-14).
    """

    params: BodyParams
    vertices: np.ndarray
    joints: np.ndarray
    bbox: tuple[int, int, int, int]
    mask: np.ndarray
    residual_m: float
    num_points: int
    tracked: bool = False
    pixels: np.ndarray | None = None      # (N, 2) full-image (row, col) of fitted points
    vertex_ids: np.ndarray | None = None  # (N,) their Eq. 2 template vertex
    crop: object | None = None
    crop_labels: np.ndarray | None = None
    track_id: int = -1
    joint_confidence: np.ndarray | None = None
    score: float = 0.0


@dataclass
class FrameResult:
    """Everything the pipeline returns for one depth frame.

    Attributes:
        persons: most central person first (may be empty: no person found).
        labels: (H, W) uint8 part class ids at input resolution (0 = background).
        timings_ms: stage -> milliseconds (preprocess, network, correspondence, fit, labels,
            total).
        network_labels: (H, W) uint8, the network's own labels (the same array as
            `labels` with segmentation 'network'; with 'model', `labels` come from the
            fitted mesh).
        unfinished: None, except in the result of `Reconstructor.reconstruct(...,
            finish=False)`: what `Reconstructor.finish` still has to do (until then
            `labels` and the persons' masks are the network's).
    """

    persons: list[PersonResult]
    labels: np.ndarray
    timings_ms: dict[str, float] = field(default_factory=dict)
    network_labels: np.ndarray | None = None
    unfinished: object | None = field(default=None, repr=False)  # see Reconstructor.finish
