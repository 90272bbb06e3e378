"""Frozen configuration dataclasses: the one place that holds defaults (no ROS).

The node declares its ROS parameters from these, `config/reconstructor.yaml` mirrors them,
and the CLI tools map argparse flags onto them.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace


@dataclass(frozen=True)
class FitConfig:
    """Model fitting (paper Eq. 3-4) and solver settings."""

    lambda_data: float = 1.0          # lambda_D
    lambda_pose: float = 1e-3         # lambda_theta: joint-limit prior weight (per rad^2)
    lambda_pose_l2: float = 1e-6      # weak pull of every joint towards rest (per rad^2)
    lambda_pose_weak: float = 3e-5    # pull of the collars and wrists towards rest (per
                                      # rad^2): joints a depth image hardly observes
    lambda_shape: float = 1e-6        # lambda_beta (per squared standard deviation)
    gm_sigma: float = 0.03            # Geman-McClure scale (metres)
    tangent_weight: float = 0.5       # weight of the residual along the model surface
                                      # (1: point to point); the depth fixes the normal
                                      # part better than a correspondence the tangent one
    back_facing_weight: float = 0.1   # IRLS weight of targets whose vertex faces away from
                                      # the camera (with tangent_weight < 1)
    gm_sigma_start: float = 0.1       # cold fits start wider and anneal to gm_sigma
    solver: str = 'fast'              # 'fast' (default) | 'lbfgs' (the paper's reference)
    iterations: int = 10              # cold-start iterations of the fast solver
    tracking_iterations: int = 3      # warm-start iterations
    lambda_temporal: float = 3e-5     # tracking: weight (per rad^2) of a joint's rotation
                                      # away from the previous frame's
    lbfgs_iterations: int = 20        # the paper's reference solver
    lbfgs_lr: float = 0.6
    max_points: int = 1000            # per-vertex targets kept per frame (random subset)
    min_cell_points: int = 2          # vertex cells with fewer points are dropped (when
                                      # typical cells hold twice that): isolated outliers
    free_space_weight: float = 1.0    # pull of vertices the sensor would have seen (in free
                                      # space) to where they could hide, per mesh vertex
    free_space_margin: float = 0.1    # metres a measurement must lie beyond a vertex
    free_space_iterations: int = 4    # refinement iterations with the free-space term
    min_joint_support: float = 3.0    # joints moving fewer targets (skinning weight) are
                                      # held in place: an unseen limb keeps its pose
    complete_hidden: bool = True      # cold fits: those joints take their conditional
                                      # mean given the fitted ones under the pose Gaussian
                                      # learned from the synthetic poses (fit.pose_prior)
    lost_residual_m: float = 0.06     # median residual above which the track is lost
    icp_rounds: int = 2               # part-constrained nearest-vertex refinements after
                                      # the Eq. 2 fit (0 = the paper's single fit)
    icp_margin_m: float = 0.03        # their refits also take the pixels the network left
                                      # out that lie this close to the fitted mesh (0 = off)
    icp_front_cos: float = 0.2        # their nearest vertex (and that of the pixels the
                                      # network left out) is one facing the camera: the
                                      # cosine of its normal and the view ray below this
                                      # (a pixel sees no back-facing surface; 1 = any)
    icp_tangent_weight: float = 0.05  # tangent_weight of the refits to those nearest-vertex
                                      # correspondences, which say nothing along the surface
                                      # (near point to plane; val_s2 41.6 mm with 0.5,
                                      # 38.8 with 0.05, one round, before icp_margin_m)
    tracking_icp_rounds: int = 0      # the same refinement on tracked frames (after their
                                      # warm fit, on this frame's mesh)
    segment_init: bool = True         # cold fits: per-segment closed-form rotations
    flip_restart: bool = True         # cold fits: retry turned 180 deg when the fit is poor
    flip_residual_m: float = 0.06     # median residual that triggers that retry


@dataclass(frozen=True)
class PipelineConfig:
    """Everything the Reconstructor needs; one frozen value per run."""

    backend: str = 'anny'             # 'anny' | 'smpl'
    model_path: str = ''              # SMPL file (or env SMPL_MODEL_PATH); anny: optional
    weights_path: str = ''            # '' = the weights shipped for the backend (for anny:
                                      # per sensor class, pipeline.BROAD_NETWORK_FOR)
    device: str = 'auto'              # 'auto' | 'cpu' | 'cuda'
    depth_min: float = 0.5            # metres; person search range
    depth_max: float = 6.0
    flip_tta: bool = False            # network on the crop and its mirror image, averaged
                                      # (more accurate; twice the network time)
    max_persons: int = 1              # persons reconstructed per frame (most central first)
    min_person_pixels: int = 400
    tracking: bool = True
    max_image_pixels: int = 4096 * 4096
    tracking_max_gap_s: float = 0.5   # reset tracking after a longer gap between frames
    track_timeout_s: float = 1.0      # a person unseen for longer loses its ID (a person
                                      # seen there later gets a new one; IDs never reused)
    track_gate_m: float = 0.5         # a person matches an earlier one within this distance
                                      # of where it was predicted (+0.5 m per second unseen)
    shape_sample_every: int = 5       # tracking: every n-th tracked frame also fits the
                                      # shape; tracked frames fit the pose at the mean of
                                      # these samples (0: keep the cold fit's shape)
    segmentation: str = 'model'       # published labels: 'model' (each of the person's
                                      # pixels takes the part of its nearest fitted vertex:
                                      # the network's body pixels, and those within
                                      # model_label_margin_m of the fitted mesh) or
                                      # 'network' (the network's labels as they are)
    model_label_margin_m: float = 0.045  # 'model': pixels the network called background
                                      # join the person this close to the fitted mesh
                                      # (not on a scene plane: pipeline.PLANE_M)
    model_label_keep_network_m: float = 0.01  # 'model': a body pixel keeps the network's
                                      # part when a vertex of it is this close to being its
                                      # nearest (0: the fit's part everywhere)
    reject_residual_m: float = 0.09   # candidates whose fit leaves a larger median residual
                                      # are not reported as persons
    sensor: str = 'auto'              # the depth sensor's noise, which the noise-dependent
                                      # thresholds scale with: 'auto' (measured from the
                                      # frames), a synth.sensors preset name (e.g.
                                      # 'realsense_d435'), or 'none' (fixed defaults)
    fit: FitConfig = field(default_factory=FitConfig)

    def with_overrides(self, **kw) -> 'PipelineConfig':
        """Replace fields; keys of FitConfig may be given too (routed to .fit)."""
        fit_names = {f.name for f in fields(FitConfig)}
        fit_kw = {k: kw.pop(k) for k in list(kw) if k in fit_names}
        cfg = replace(self, **kw)
        return replace(cfg, fit=replace(cfg.fit, **fit_kw)) if fit_kw else cfg


# -- person-finding constants --
# Which of the candidates net.preprocess.find_persons returns the pipeline takes as persons.
EXTRA_CANDIDATES = 2  # candidates looked for beyond max_persons (some may be no person)
MIN_BODY_PIXELS = 60  # network-foreground crop pixels needed to attempt a fit
MIN_BODY_SHARE = 0.4  # a person: the network sees a body in this share of its blob's pixels
MIN_PART_SHARE = 0.02  # body_score: a part counts when it covers this share of the body
MIN_BEHIND = 0.3  # a blob behind a person is a tracked one with this share of its pixels
MAX_CLAIMED = 0.5  # a further person: at most this share of its pixels an earlier one's
