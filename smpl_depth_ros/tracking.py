"""Person tracks across frames (no ROS): stable IDs and each person's warm-start state.

Every reconstructed person belongs to a `Track`. A frame's person candidates are matched
to the live tracks before they are fitted, so each person is warm-started from its own
previous fit:

1. by overlap: a candidate whose blob and a track's pixels of the previous frame overlap
   (intersection over union >= MIN_OVERLAP; the largest overlaps first) is that track
   (people move a few centimetres between frames at sensor rates; the union, not the
   track's pixels alone, so that a person half hidden behind another does not hand its
   track to the blob in front);
2. the rest by position: the candidate's centre (its crop centre back-projected at its
   median depth) against each remaining track's fitted pelvis predicted with its velocity, an
   optimal assignment (`scipy.optimize.linear_sum_assignment`) within `gate_m` (widened by
   0.5 m per second the track has been unseen, for a person walking behind someone).

A track keeps its ID while it is seen, and for up to `timeout_s` seconds unseen (brief
occlusions, a missed frame); after that it is dropped and a person appearing there gets a
new ID. IDs start at 1 and are never reused by one `Tracker` (one node run, one bag).
Only a track seen in the previous frame within the pipeline's `tracking_max_gap_s` is
warm-started (`Track.warm_start`); older ones give their ID only. A track also keeps the
samples of its mean shape, at which its tracked frames fit the pose (`Track.keep_fit`,
`Track.shape_sample_due`, `Track.add_shape_sample`).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

# A candidate is a track's by overlap when its blob and the track's previous pixels
# overlap by at least this intersection over union.
MIN_OVERLAP = 0.3
# Gate growth while a track is unseen (m/s): a walking person's speed.
GATE_GROWTH_M_S = 0.5
# Time constant of the velocity's smoothing (s).
VELOCITY_TAU_S = 0.2


@dataclass
class Track:
    """One person followed across frames.

    Attributes:
        id: stable ID (>= 1).
        centre: (3,) its fitted pelvis in the last frame it was seen (camera frame, m).
        velocity: (3,) m/s, smoothed over the frames it was seen.
        last_seen: time it was last seen (s; the frame stamps' clock).
        fit: its last fit (fit.fitter.FitResult) while it may be warm-started, else None.
        fit_time: time of that fit (s).
        fit_stamp: stamp of that fit's frame (ns; None: the frame had none).
        mask: (H, W) bool, its pixels in the last frame it was seen.
        shapes: [sum of shape samples, count, tracked frames] (the pipeline's mean shape).
        frames: frames it has been seen in.
        held: (fit, time) of its last tracked fit, the body moved into place in a frame
            whose warm fit fails (`held_body`), or None.
        net: the correspondence network its fits take their correspondences from (set
            by the pipeline; None: the frame's).
    """

    id: int
    centre: np.ndarray
    last_seen: float
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    fit: object = None
    fit_time: float = 0.0
    fit_stamp: int | None = None
    mask: np.ndarray | None = None
    shapes: list | None = None
    frames: int = 0
    held: tuple | None = None
    net: object = None

    def predicted(self, t: float) -> np.ndarray:
        return self.centre + self.velocity * max(0.0, t - self.last_seen)

    def warm_start(self, stamp_ns: int | None, max_gap_s: float):
        """The parameters (types.BodyParams) to warm-start the fit of the frame stamped
        `stamp_ns` from: the last fit's, posed at the mean of the shape samples when there
        are any; None without a fit, or when it is more than `max_gap_s` older (unstamped
        frames: consecutive)."""
        if self.fit is None:
            return None
        prev_stamp = self.fit_stamp
        gap_ok = (stamp_ns is None or prev_stamp is None or
                  0 <= (stamp_ns - prev_stamp) * 1e-9 <= max_gap_s)
        if not gap_ok:
            return None
        return self._at_mean_shape(self.fit.params)

    def _at_mean_shape(self, params):
        """`params` with the mean of the shape samples, when there are any."""
        shapes = self.shapes
        if shapes is not None and shapes[1]:
            mean = shapes[0] / shapes[1]
            params = replace(params, shape=mean.astype(np.asarray(params.shape).dtype))
        return params

    def keep_fit(self, fit, t: float, stamp_ns: int | None, tracked: bool,
                 moved: bool = False) -> None:
        """Keep this frame's fit (time `t`, stamp `stamp_ns`) for the next frame's warm
        start. A cold fit (`tracked` False: a new track, or a lost one) starts the shape
        samples afresh: the track keeps the cold fit's shape until sampled. A tracked fit
        is also the body `held_body` gives, unless it is such a body moved (`moved`)."""
        self.fit, self.fit_time, self.fit_stamp = fit, t, stamp_ns
        if not tracked:
            self.shapes = [np.zeros(len(fit.params.shape)), 0, 0]
            self.held = None
        elif not moved:
            self.held = (fit, t)

    def held_body(self, t: float, max_age_s: float):
        """(params, time) of the track's last tracked fit, posed at the mean of the shape
        samples when there are any, if it is at most `max_age_s` older than `t`; else
        None. A cold fit is no such body: a person found again half hidden is often fitted
        far off, and moving that body would carry the error on."""
        if self.held is None or not 0 <= t - self.held[1] <= max_age_s:
            return None
        return self._at_mean_shape(self.held[0].params), self.held[1]

    def shape_sample_due(self, every: int) -> bool:
        """Count a tracked frame; True when it is the `every`-th since the last shape
        sample (never with `every` <= 0 or no samples kept)."""
        if every <= 0 or self.shapes is None:
            return False
        self.shapes[2] += 1
        return not self.shapes[2] % every

    def add_shape_sample(self, shape) -> None:
        """Add a fitted shape to the samples of the track's mean shape."""
        self.shapes[0] = self.shapes[0] + np.asarray(shape, np.float64)
        self.shapes[1] += 1


class Tracker:
    """The live tracks of one stream and the ID counter.

    Args:
        timeout_s: a track unseen for longer is dropped (its ID is not reused).
        gate_m: the largest distance between a track's predicted centre and a candidate's
            for them to be matched by position.
    """

    def __init__(self, timeout_s: float = 1.0, gate_m: float = 0.5):
        self.timeout_s = float(timeout_s)
        self.gate_m = float(gate_m)
        self.tracks: list[Track] = []
        self._next_id = 1

    def start_ids_at(self, first: int) -> None:
        """Let new IDs start at `first` (at least; IDs already given stay unused)."""
        self._next_id = max(self._next_id, int(first))

    def clear(self) -> None:
        """Drop every track (IDs are still never reused)."""
        self.tracks = []

    def forget_fits(self, keep: set | None = None) -> None:
        """Keep the IDs but warm-start no track on the next frame, except those whose
        `id()` is in `keep` (the tracks seen in this frame)."""
        for t in self.tracks:
            if not keep or id(t) not in keep:
                t.fit = None

    def expire(self, t: float) -> None:
        """Drop the tracks unseen for longer than the timeout at time `t` (and all of
        them when time ran backwards)."""
        self.tracks = [tr for tr in self.tracks
                       if 0.0 <= t - tr.last_seen <= self.timeout_s]

    def warm(self, t: float, max_gap_s: float) -> list[Track]:
        """Tracks with a fit of at most `max_gap_s` before `t`."""
        return [tr for tr in self.tracks
                if tr.fit is not None and 0.0 <= t - tr.fit_time <= max_gap_s]

    def match(self, centres: np.ndarray, masks: list, t: float,
              exclude: set | None = None) -> list[Track | None]:
        """The track of each candidate (None: a new person), each track used once.

        Args:
            centres: (N, 3) candidate centres.
            masks: N (H, W) bool candidate blobs (None where unknown).
            t: the frame's time (s).
            exclude: `id()`s of tracks already taken in this frame.
        """
        n = len(centres)
        out: list[Track | None] = [None] * n
        free = [tr for tr in self.tracks if not exclude or id(tr) not in exclude]
        # 1. overlap with the pixels of the previous frame
        if free and n:
            ov = np.zeros((n, len(free)))
            for j, tr in enumerate(free):
                if tr.mask is None:
                    continue
                for i, m in enumerate(masks):
                    if m is not None and m.shape == tr.mask.shape:
                        ov[i, j] = (m & tr.mask).sum() / max(int((m | tr.mask).sum()), 1)
            while ov.size and ov.max() >= MIN_OVERLAP:
                i, j = np.unravel_index(np.argmax(ov), ov.shape)
                out[i] = free[j]
                ov[i, :] = 0
                ov[:, j] = 0
            used = {id(tr) for tr in out if tr is not None}
            free = [tr for tr in free if id(tr) not in used]
        # 2. the rest by predicted position
        rest = [i for i in range(n) if out[i] is None]
        if free and rest:
            cost = np.array([[np.linalg.norm(centres[i] - tr.predicted(t)) for tr in free]
                             for i in rest])
            gate = np.array([self._gate(tr, t) for tr in free])
            big = 1e6
            rows, cols = linear_sum_assignment(np.where(cost <= gate[None], cost, big))
            for r, c in zip(rows, cols):
                if cost[r, c] <= gate[c]:
                    out[rest[r]] = free[c]
        return out

    def near(self, centre: np.ndarray, t: float) -> bool:
        """Whether a live track's predicted centre lies within its gate (as `match`
        widens it) of `centre` at time `t`."""
        return any(np.linalg.norm(np.asarray(centre) - tr.predicted(t)) <= self._gate(tr, t)
                   for tr in self.tracks)

    def _gate(self, tr: Track, t: float) -> float:
        """`gate_m`, widened by GATE_GROWTH_M_S for each second `tr` has been unseen."""
        return self.gate_m + GATE_GROWTH_M_S * max(0.0, t - tr.last_seen)

    def new(self, centre: np.ndarray, t: float) -> Track:
        """A new track with the next ID (`seen` then records where it is)."""
        tr = Track(id=self._next_id, centre=np.asarray(centre, np.float64), last_seen=t)
        self._next_id += 1
        self.tracks.append(tr)
        return tr

    @staticmethod
    def seen(tr: Track, position: np.ndarray, t: float, mask=None) -> None:
        """Record that `tr` was seen at `position` (its fitted pelvis) at time `t`; the
        velocity follows the positions with a time constant of VELOCITY_TAU_S."""
        position = np.asarray(position, np.float64)
        dt = t - tr.last_seen
        if tr.frames and 0.0 < dt <= 1.0:
            a = dt / (dt + VELOCITY_TAU_S)
            tr.velocity = tr.velocity + a * ((position - tr.centre) / dt - tr.velocity)
        elif dt > 1.0:
            tr.velocity = np.zeros(3)
        tr.centre, tr.last_seen, tr.mask = position, t, mask
        tr.frames += 1


def candidate_centre(crop, K: np.ndarray) -> np.ndarray:
    """(3,) the centre of a person candidate: its crop's centre pixel back-projected at
    its median depth (camera frame, metres)."""
    half = crop.scale * crop.size / 2.0
    u, v, z = crop.u0 + half - 0.5, crop.v0 + half - 0.5, crop.median_depth
    return np.array([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])
