"""Body-part classes and the 6-D template embedding of paper III-B-a.

15 classes: background plus 14 body parts. Each template vertex gets
E(j) = (normalised canonical T-pose coordinates in [0,1]^3, part colour in [0,1]^3),
and a pixel embedding is matched to its nearest template vertex (paper Eq. 2).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

PART_NAMES = (
    'background', 'head', 'torso',
    'upper_arm_l', 'upper_arm_r', 'lower_arm_l', 'lower_arm_r', 'hand_l', 'hand_r',
    'upper_leg_l', 'upper_leg_r', 'lower_leg_l', 'lower_leg_r', 'foot_l', 'foot_r',
)
NUM_CLASSES = len(PART_NAMES)  # 15, background included
BACKGROUND = 0

# 15 distinct colours (uint8 RGB), left/right parts clearly separated.
PART_COLORS_U8 = np.array([
    [0, 0, 0],        # background
    [255, 224, 64],   # head
    [128, 128, 128],  # torso
    [230, 25, 75],    # upper arm L
    [60, 180, 75],    # upper arm R
    [245, 130, 48],   # lower arm L
    [0, 130, 200],    # lower arm R
    [255, 0, 255],    # hand L
    [0, 255, 255],    # hand R
    [128, 0, 0],      # upper leg L
    [0, 0, 128],      # upper leg R
    [170, 110, 40],   # lower leg L
    [0, 128, 128],    # lower leg R
    [255, 160, 200],  # foot L
    [160, 255, 160],  # foot R
], dtype=np.uint8)
PART_COLORS = PART_COLORS_U8.astype(np.float32) / 255.0

# Mirror map (left <-> right) used by flip augmentation.
MIRROR = np.array([0, 1, 2, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11, 14, 13], dtype=np.int64)


def normalise_canonical(vertices: np.ndarray) -> np.ndarray:
    """Map canonical template vertices (V, 3) into [0, 1]^3 (per-axis min/max)."""
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(0), v.max(0)
    return ((v - lo) / np.maximum(hi - lo, 1e-9)).astype(np.float32)


def template_embedding(canonical_vertices: np.ndarray, part_labels: np.ndarray) -> np.ndarray:
    """E(j) for every template vertex.

    Args:
        canonical_vertices: (V, 3) T-pose template vertices, any units.
        part_labels: (V,) int class ids in 1..14.

    Returns:
        (V, 6) float32: normalised coordinates then part colour.
    """
    if canonical_vertices.ndim != 2 or canonical_vertices.shape[1] != 3:
        raise ValueError(f'canonical_vertices must be (V, 3), got {canonical_vertices.shape}')
    if part_labels.shape != (canonical_vertices.shape[0],):
        raise ValueError('part_labels must be (V,)')
    return np.concatenate([normalise_canonical(canonical_vertices),
                           PART_COLORS[part_labels]], axis=1)


class EmbeddingIndex:
    """Nearest template vertex in the 6-D embedding (paper Eq. 2), for many pixels at once.

    Args:
        embedding: (V, 6) per-vertex embedding E.
        valid: optional (V,) bool; vertices that may be matched (e.g. no mouth cavity).
        color_weight: scale of the colour part; > 1 keeps matches inside the predicted
            part (1.0 is the paper's plain Euclidean metric).
    """

    def __init__(self, embedding: np.ndarray, valid: np.ndarray | None = None,
                 color_weight: float = 1.0):
        self.color_weight = float(color_weight)
        ids = np.arange(embedding.shape[0]) if valid is None else np.flatnonzero(valid)
        self._ids = ids
        self._tree = cKDTree(self._scale(embedding[ids]))

    def _scale(self, e: np.ndarray) -> np.ndarray:
        e = np.asarray(e, dtype=np.float32).copy()
        e[:, 3:] *= self.color_weight
        return e

    def query(self, pixel_embedding: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Match (N, 6) pixel embeddings; returns vertex ids (N,) int64 and distances (N,)."""
        if pixel_embedding.ndim != 2 or pixel_embedding.shape[1] != 6:
            raise ValueError(f'pixel_embedding must be (N, 6), got {pixel_embedding.shape}')
        if len(pixel_embedding) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.float32)
        d, i = self._tree.query(self._scale(pixel_embedding), k=1, workers=-1)
        return self._ids[i].astype(np.int64), d.astype(np.float32)


def labels_to_rgb(labels: np.ndarray) -> np.ndarray:
    """(H, W) class ids -> (H, W, 3) uint8 colours (the colour lookup only runs over the
    bounding box of the body pixels: a person covers a small part of a frame)."""
    labels = np.asarray(labels)
    out = np.empty(labels.shape + (3,), np.uint8)
    out[...] = PART_COLORS_U8[0]
    body = labels != 0
    rows, cols = np.flatnonzero(body.any(1)), np.flatnonzero(body.any(0))
    if len(rows):
        win = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        out[win] = np.take(PART_COLORS_U8, np.clip(labels[win], 0, NUM_CLASSES - 1), axis=0)
    return out
