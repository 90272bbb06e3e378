"""A learned pose prior for the joints a depth image does not see (no ROS).

The fitter holds a joint whose rotation moves no target (a forearm and hand hidden
behind the torso, an arm out of frame): the data says nothing of it. Rest is a poor
guess - people seldom hold a hidden arm straight down. `PoseGaussian` is a Gaussian over
the whole canonical pose (P x 3 axis-angle, body.base axes), in the spirit of SMPLify's
prior learned from motion capture, estimated from poses drawn by the synthetic pose
sampler in its 'broad' mode (synth.poses: the activity templates, postures beyond them -
kneeling, squatting, bending to the floor, reaching overhead - and draws within the
joint limits; on the template-only poses it learned before, it guessed a hidden arm as
the templates hold it). `complete` replaces the hidden joints by their conditional mean
given the fitted visible ones: a raised shoulder implies a bent elbow, one crossed arm
the other.

The anny model's Gaussian ships as `data/pose_prior_anny.npz`, made by

    python -m smpl_depth_ros.fit.pose_prior --backend anny \
        --out smpl_depth_ros/data/pose_prior_anny.npz

so editing a training template does not silently change the live fitter, and start-up
does not draw the poses. Another body model (SMPL) has it estimated once per process.
"""
from __future__ import annotations

import os
from importlib import resources

import numpy as np

SAMPLES = 40000  # poses drawn to estimate the Gaussian (seeded: deterministic)
RIDGE = 1e-4     # rad^2 added to the covariance's diagonal (clipped joints have little)

_CACHE: dict = {}


def shipped_path(backend: str) -> str:
    return str(resources.files('smpl_depth_ros') / 'data' / f'pose_prior_{backend}.npz')


class PoseGaussian:
    """Mean and covariance of canonical poses for one body model.

    Args:
        mean: (P * 3,) canonical axis-angle mean (radians).
        cov: (P * 3, P * 3) covariance.
        limits: (P, 3, 2) canonical joint limits (completions are clipped to them).
    """

    def __init__(self, mean: np.ndarray, cov: np.ndarray, limits: np.ndarray):
        self.mean = np.asarray(mean, np.float64)
        self.cov = np.asarray(cov, np.float64)
        self.limits = np.asarray(limits, np.float64)
        self.P = self.limits.shape[0]
        if self.mean.shape != (self.P * 3,) or self.cov.shape != (self.P * 3,) * 2:
            raise ValueError(f'pose Gaussian of {self.mean.shape} / {self.cov.shape} does '
                             f'not fit {self.P} joints')

    @classmethod
    def estimate(cls, body, samples: int = SAMPLES, seed: int = 0) -> 'PoseGaussian':
        """From `samples` poses of the broad pose sampler (no whole-body tilt)."""
        from smpl_depth_ros.synth.poses import PoseSampler
        sampler = PoseSampler(body, mode='broad', root_tilt=False)
        rng = np.random.default_rng(seed)
        n = len(sampler.names) * 3
        s1, s2 = np.zeros(n), np.zeros((n, n))
        for _ in range(samples):
            x = sampler.sample_canonical(rng).reshape(-1)
            s1 += x
            s2 += np.outer(x, x)
        mean = s1 / samples
        cov = (s2 - samples * np.outer(mean, mean)) / (samples - 1) + RIDGE * np.eye(n)
        return cls(mean, cov, sampler.limits)

    def save(self, path: str, body) -> None:
        np.savez(path, mean=self.mean, cov=self.cov, limits=self.limits,
                 joint_names=np.array(body.joint_names[1:]), body_model=np.array(body.name))

    @classmethod
    def load(cls, path: str, body) -> 'PoseGaussian | None':
        """The Gaussian in `path` if it was made for this body's joints and limits."""
        if not os.path.exists(path):
            return None
        with np.load(path, allow_pickle=False) as f:
            if tuple(f['joint_names'].tolist()) != tuple(body.joint_names[1:]):
                return None
            limits = body.limits_canonical().cpu().numpy().astype(np.float64)
            if f['limits'].shape != limits.shape or not np.allclose(f['limits'], limits):
                return None
            return cls(f['mean'], f['cov'], f['limits'])

    @classmethod
    def for_body(cls, body) -> 'PoseGaussian':
        """One per body model kind and joint set: the shipped one where it fits."""
        key = (body.name, tuple(body.joint_names))
        if key not in _CACHE:
            _CACHE[key] = cls.load(shipped_path(body.name), body) or cls.estimate(body)
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

