"""A learned pose prior for the joints a depth image does not see (no ROS).

The fitter holds a joint whose rotation moves no target (a forearm and hand hidden
behind the torso, an arm out of frame): the data says nothing of it. Rest is a poor
guess - people seldom hold a hidden arm straight down. `PoseGaussian` is a Gaussian over
the whole canonical pose (P x 3 axis-angle, body.base axes), estimated once from poses
drawn by the synthetic pose sampler (synth.poses: the activities the network is trained
on, within the joint limits), in the spirit of SMPLify's prior learned from motion
capture. `complete` replaces the hidden joints by their conditional mean given the
fitted visible ones: a raised shoulder implies a bent elbow, one crossed arm the other.
"""
from __future__ import annotations

import numpy as np

SAMPLES = 100000  # poses drawn to estimate the Gaussian (seeded: deterministic)
CHUNK = 10000     # drawn and summed this many at a time (peak memory ~10 MB, not ~100)
RIDGE = 1e-4     # rad^2 added to the covariance's diagonal (clipped joints have little)

_CACHE: dict = {}


class PoseGaussian:
    """Mean and covariance of the sampler's canonical poses for one body model.

    Args:
        body: the body model (generic joint names map the sampler's activities onto it).
        samples: poses drawn; seed: their random stream.
    """

    def __init__(self, body, samples: int = SAMPLES, seed: int = 0):
        from smpl_depth_ros.synth.poses import PoseSampler
        sampler = PoseSampler(body)
        rng = np.random.default_rng(seed)
        # PoseSampler.sample_canonical's distribution, drawn in one go: a template (and
        # its mirror image) scaled by a random amplitude, per-joint noise, the limits.
        T = np.stack([[sampler.template(t, 1.0, mirror=m) for m in (False, True)]
                      for t in sampler.templates])  # (templates, 2, P, 3)
        which = rng.choice(len(T), samples, p=sampler.weights)
        mirror = (rng.random(samples) < 0.5).astype(np.int64)
        amp = rng.uniform(0.3, 1.15, samples)[:, None, None]
        self.limits = sampler.limits
        self.P = T.shape[2]
        n = self.P * 3
        s1, s2 = np.zeros(n), np.zeros((n, n))
        for a in range(0, samples, CHUNK):
            b = min(a + CHUNK, samples)
            X = sampler.clip(T[which[a:b], mirror[a:b]] * amp[a:b] + rng.normal(
                0, sampler.noise, (b - a,) + T.shape[2:])).reshape(b - a, n)
            s1 += X.sum(0)
            s2 += X.T @ X
        self.mean = s1 / samples
        self.cov = ((s2 - samples * np.outer(self.mean, self.mean)) / (samples - 1)
                    + RIDGE * np.eye(n))

    @classmethod
    def for_body(cls, body) -> 'PoseGaussian':
        """One per body model kind and joint set."""
        key = (body.name, tuple(body.joint_names))
        if key not in _CACHE:
            _CACHE[key] = cls(body)
        return _CACHE[key]

    def complete(self, canon: np.ndarray, hidden: np.ndarray) -> np.ndarray:
        """(P, 3) canonical pose with the `hidden` (P,) joints replaced by their
        conditional mean given the others, clipped to the joint limits."""
        canon = np.asarray(canon, np.float64)
        h = np.repeat(np.asarray(hidden, bool), 3)
        if not h.any():
            return canon.copy()
        x = canon.reshape(-1).copy()
        v = ~h
        if v.any():
            S = self.cov
            x[h] = self.mean[h] + S[np.ix_(h, v)] @ np.linalg.solve(
                S[np.ix_(v, v)], x[v] - self.mean[v])
        else:
            x[h] = self.mean[h]
        out = x.reshape(self.P, 3)
        return np.clip(out, self.limits[..., 0], self.limits[..., 1])
