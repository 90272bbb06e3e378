"""Frozen configuration dataclasses: every parameter, declared once.

Each field carries its default and, in its metadata, the description users read (ROS
parameter descriptions, the params YAML, `--help`), its range or choices, whether a change
needs a restart, and whether it is an expert knob (`advanced`). `smpl_depth_ros.params`
turns these declarations into the node's ROS parameters, the params YAML, the `-p` of the
command-line tools and the one validation all of them share. No ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace


def param(default, doc: str, *, range: tuple | None = None, choices=None,
          restart: bool = False, advanced: bool = False):
    """A dataclass field declared as a parameter.

    Args:
        default: the default value (its type is the parameter's type).
        doc: one-line description for users.
        range: (lo, hi), inclusive, for numbers.
        choices: a tuple of allowed strings, or a callable returning one.
        restart: a change needs a restart (a read-only ROS parameter).
        advanced: an expert knob: the node declares it under `advanced.`.
    """
    return field(default=default, metadata=dict(doc=doc, range=range, choices=choices,
                                                restart=restart, advanced=advanced))


def _sensor_choices() -> tuple[str, ...]:
    from smpl_depth_ros.sensor_noise import sensor_choices
    return sensor_choices()


_A = dict(advanced=True)
PRECISIONS = ('auto', 'float32', 'bfloat16')  # net_precision (net.infer.resolve_precision)


@dataclass(frozen=True)
class FitConfig:
    """Model fitting (paper Eq. 3-4) and solver settings (all expert knobs: `fit.<name>`)."""

    lambda_data: float = param(1.0, 'fitting: data term weight (lambda_D)', **_A)
    lambda_pose: float = param(1e-3, 'fitting: joint-limit prior weight (lambda_theta, per '
                               'rad^2)', **_A)
    lambda_pose_l2: float = param(1e-6, 'fitting: pull of every joint towards rest (per '
                                  'rad^2)', **_A)
    lambda_pose_weak: float = param(3e-5, 'fitting: pull of the collars and wrists towards '
                                    'rest (per rad^2; joints a depth image hardly observes)',
                                    range=(0.0, 1e6), **_A)
    lambda_shape: float = param(1e-6, 'fitting: shape prior weight (lambda_beta, per squared '
                                'standard deviation)', **_A)
    gm_sigma: float = param(0.03, 'fitting: Geman-McClure scale (m)', range=(1e-6, 10.0),
                            **_A)
    tangent_weight: float = param(0.5, 'fitting: weight of the residual along the model '
                                  'surface (1 = point to point; the depth fixes the normal '
                                  'part better than a correspondence the tangent one)', **_A)
    back_facing_weight: float = param(0.1, 'fitting: weight of targets whose vertex faces '
                                      'away from the camera (with tangent_weight < 1)', **_A)
    gm_sigma_start: float = param(0.1, 'fitting: cold fits start with this wider scale and '
                                  'anneal to gm_sigma (m)', range=(1e-6, 10.0), **_A)
    solver: str = param('fast', "fitting solver: 'fast' (Levenberg-Marquardt) or 'lbfgs' "
                        "(the paper's reference)", choices=('fast', 'lbfgs'), **_A)
    iterations: int = param(10, 'fitting: cold-start iterations', range=(0, 10_000), **_A)
    tracking_iterations: int = param(3, 'fitting: warm-start iterations while tracking',
                                     range=(0, 10_000), **_A)
    lambda_temporal: float = param(3e-5, "fitting: tracking's temporal prior, weight (per "
                                   "rad^2) of a joint's rotation away from the previous "
                                   "frame's (0 = off)", range=(0.0, 1e6), **_A)
    lbfgs_iterations: int = param(20, 'fitting: L-BFGS iterations', range=(0, 10_000), **_A)
    lbfgs_lr: float = param(0.6, 'fitting: L-BFGS learning rate', **_A)
    max_points: int = param(1000, 'fitting: per-vertex targets kept per frame (a random '
                            'subset)', range=(1, 10_000_000), **_A)
    min_cell_points: int = param(2, 'fitting: drop vertex cells with fewer points (isolated '
                                 'wrong correspondences), when typical cells hold twice '
                                 'that', range=(1, 1_000_000), **_A)
    free_space_weight: float = param(1.0, 'fitting: pull of vertices the sensor would have '
                                     'seen (in free space) to where they could hide, per '
                                     'mesh vertex', **_A)
    free_space_margin: float = param(0.1, 'fitting: a measurement must lie this far beyond '
                                     'a vertex for it to be in free space (m)', **_A)
    free_space_iterations: int = param(4, 'fitting: refinement iterations with the '
                                       'free-space term', **_A)
    min_joint_support: float = param(3.0, 'fitting: joints whose rotation moves fewer '
                                     'targets (in skinning weight) are held in place (unseen '
                                     'limbs; 0 = off)', range=(0.0, 1e6), **_A)
    complete_hidden: bool = param(True, 'fitting: cold fits give those joints their most '
                                  'likely pose given the fitted ones (the pose Gaussian of '
                                  'fit.pose_prior), not rest', **_A)
    lost_residual_m: float = param(0.06, 'fitting: median residual above which the track is '
                                   'lost (m)', range=(0.0, 10.0), **_A)
    icp_rounds: int = param(2, 'fitting: part-constrained nearest-vertex refinements after '
                            "the correspondence fit (0 = the paper's single fit)",
                            range=(0, 100), **_A)
    icp_margin_m: float = param(0.03, 'fitting: those refits also take the pixels the '
                                'network left out that lie this close to the fitted mesh '
                                '(m; 0 = off)', range=(0.0, 1.0), **_A)
    icp_front_cos: float = param(0.2, 'fitting: the refinements match each pixel (and each '
                                 'pixel the network left out) to a vertex facing the '
                                 'camera: cosine of its normal and the view ray below this '
                                 '(a pixel sees no back-facing surface; 1 = any)',
                                 range=(-1.0, 1.0), **_A)
    # val_s2: 41.6 mm with 0.5, 38.8 with 0.05 (one round, before icp_margin_m).
    icp_tangent_weight: float = param(0.05, 'fitting: weight of the residual along the '
                                      'surface in the refits to those nearest-vertex '
                                      'correspondences, which say nothing along it (0 = '
                                      'point to plane, 1 = point to point)',
                                      range=(0.0, 1.0), **_A)
    tracking_icp_rounds: int = param(0, "fitting: the same refinements on tracked frames (on "
                                     "this frame's warm fit; 0 = none, faster)",
                                     range=(0, 100), **_A)
    segment_init: bool = param(True, 'fitting: cold fits start from per-segment closed-form '
                               'rotations', **_A)
    limb_init: bool = param(True, 'fitting: cold fits also start with each limb whose upper '
                            'segment is barely seen oriented towards its seen lower '
                            'segments, solved where the first start leaves them '
                            'unexplained, the lower energy kept', **_A)
    flip_restart: bool = param(True, 'fitting: cold fits retry turned 180 degrees when the '
                               'fit is poor', **_A)
    flip_residual_m: float = param(0.06, 'fitting: median residual that triggers that retry '
                                   '(m)', range=(0.0, 10.0), **_A)


@dataclass(frozen=True)
class PipelineConfig:
    """Everything the Reconstructor needs; one frozen value per run."""

    backend: str = param('anny', "body model backend: 'anny' (shipped) or 'smpl' (your own "
                         'model file)', choices=('anny', 'smpl'), restart=True)
    model_path: str = param('', 'SMPL model file or directory (or env SMPL_MODEL_PATH); '
                            'anny: optional', restart=True)
    weights_path: str = param('', "correspondence network weights ('' = the shipped ones: "
                              'the broad network for stereo sensors, the original for the '
                              'others; pipeline.BROAD_NETWORK_FOR)', restart=True)
    device: str = param('auto', "torch device: 'auto' (CUDA when available), 'cpu' or "
                        "'cuda'; a change reloads the model", choices=('auto', 'cpu', 'cuda'))
    depth_min: float = param(0.5, 'person search range: nearest depth (m)',
                             range=(0.0, 100.0))
    depth_max: float = param(6.0, 'person search range: farthest depth (m)',
                             range=(0.0, 100.0))
    net_precision: str = param('auto', "the network's arithmetic: 'auto' (bfloat16 on a CPU "
                               'with bfloat16 units, AMX or AVX-512 BF16: 1.6-2x as fast, '
                               "99.8 % of the labels the same; float32 elsewhere), 'float32' "
                               "or 'bfloat16'", choices=PRECISIONS)
    flip_tta: bool = param(False, 'run the network on each crop and its mirror image and '
                           'average (twice the network time; better segmentation and fits)')
    second_network: bool = param(True, 'when a body was seen but no fit explained it, retry '
                                 "the frame's candidates with the other shipped network (the "
                                 'broad or the original one; not with weights_path)', **_A)
    both_networks: bool = param(True, 'without tracking (single frames), every person is '
                                'fitted with both shipped networks and the fit whose mesh '
                                'lies nearer the depth is kept (twice a cold fit; not with '
                                'weights_path)', **_A)
    max_persons: int = param(3, 'persons reconstructed per frame (most central first)',
                             range=(1, 100))
    min_person_pixels: int = param(400, 'smallest person blob (pixels)',
                                   range=(1, 10_000_000), **_A)
    tracking: bool = param(True, 'warm-start from the previous frame while the track holds')
    max_image_pixels: int = param(4096 * 4096, 'larger depth images are rejected (width x '
                                  'height)', range=(1, 1 << 30), **_A)
    tracking_max_gap_s: float = param(0.5, 'reset tracking after a longer gap between frame '
                                      'stamps (s)', range=(0.0, 3600.0), **_A)
    track_timeout_s: float = param(1.0, 'a person unseen for longer loses its ID (a person '
                                   'seen there later gets a new one; IDs are never reused; s)',
                                   range=(0.0, 3600.0))
    track_gate_m: float = param(0.5, 'a person keeps its ID within this distance of where it '
                                'was predicted, +0.5 m per second unseen (m)',
                                range=(0.0, 100.0), **_A)
    shape_sample_every: int = param(5, 'tracking: every n-th tracked frame also fits the '
                                    'shape; tracked frames fit the pose at the mean of these '
                                    "samples (0: keep the cold fit's shape)",
                                    range=(0, 1_000_000), **_A)
    segmentation: str = param('model', "published labels: 'model' (each person pixel takes "
                              'the part of its nearest fitted vertex: the network\'s body '
                              'pixels and those within model_label_margin_m of the mesh) or '
                              "'network' (the network's labels as they are)",
                              choices=('model', 'network'))
    model_label_margin_m: float = param(0.045, "'model' segmentation: pixels the network "
                                        'called background join the person this close to '
                                        'the fitted mesh, not on a scene plane (m)',
                                        range=(0.0, 1.0), **_A)
    model_label_keep_network_m: float = param(0.01, "'model' segmentation: a body pixel "
                                              "keeps the network's part when a vertex of it "
                                              'is this close to being its nearest (m; 0 = '
                                              'the fit decides everywhere)',
                                              range=(0.0, 1.0), **_A)
    reject_residual_m: float = param(0.09, 'person candidates whose fit leaves a larger '
                                     'median residual are not reported (m)',
                                     range=(0.0, 10.0), **_A)
    undistort: str = param('auto', 'a depth image whose camera_info has a non-zero D: '
                           "'auto' takes it as the lens's own image (resampled to pinhole "
                           'with the distortion_model and D; outputs stay aligned with it) '
                           "unless its topic's name says rect (image_rect, image_rect_raw: "
                           "then it is used with P); 'always' / 'never' decide without the "
                           'name', choices=('auto', 'always', 'never'))
    sensor: str = param('auto', "the depth sensor, whose noise the thresholds scale with: "
                        "'auto' (measured from the frames), a preset (e.g. 'realsense_d435', "
                        "'oak_d', 'azure_kinect_nfov', 'kinect_v1') or 'none' (fixed "
                        'thresholds)', choices=_sensor_choices)
    denoise: bool = param(True, 'average each depth pixel with its neighbours within 2.5 '
                          'sigma of it where the sensor noise exceeds what the thresholds '
                          'were tuned for (a stereo camera far away; the window grows with '
                          'the excess, up to 7x7); a Kinect v1 or time-of-flight camera is '
                          'left as it is beyond about 1.5 m', **_A)
    fit: FitConfig = field(default_factory=FitConfig)

    def with_overrides(self, **kw) -> 'PipelineConfig':
        """Replace fields; keys of FitConfig may be given too (routed to .fit)."""
        fit_names = {f.name for f in fields(FitConfig)}
        fit_kw = {k: kw.pop(k) for k in list(kw) if k in fit_names}
        cfg = replace(self, **kw)
        return replace(cfg, fit=replace(cfg.fit, **fit_kw)) if fit_kw else cfg


@dataclass(frozen=True)
class OutputOptions:
    """Which outputs are built, by the node and by process_bag (ros.outputs)."""

    publish_mesh: bool = param(True, 'publish ~/mesh (a Marker per person) and ~/meshes (the '
                               "frame's persons, DELETE for those gone)")
    publish_segmentation: bool = param(True, 'publish ~/segmentation, ~/segmentation/labels '
                                       'and ~/bodies/index')
    publish_params: bool = param(True, 'publish ~/smpl_params (the most central person), '
                                 '~/bodies/params and ~/bodies/tracked')
    publish_skeleton: bool = param(True, 'publish ~/skeleton')
    publish_tf: bool = param(True, 'broadcast each body as TF frames on /tf (body_<id> at '
                             'the pelvis, <joint>_<id>)')
    mesh_decimation: float = param(1.0, 'fraction of mesh triangles sent in ~/mesh (1 = full '
                                   'mesh)', range=(0.001, 1.0))
    mesh_lifetime_s: float = param(0.5, 'lifetime of the mesh and skeleton markers (0 = '
                                   'forever; s)', range=(0.0, 3600.0))


@dataclass(frozen=True)
class NodeOptions:
    """Settings of the live node only (process_bag ignores them, saying so)."""

    qos_reliability: str = param('best_effort', "input QoS reliability: 'best_effort' "
                                 "(sensor data) or 'reliable' (needed for reliable-only "
                                 'publishers)', choices=('best_effort', 'reliable'),
                                 restart=True)
    qos_depth: int = param(1, 'input QoS history depth', range=(1, 1000), restart=True)
    cpu_threads: int = param(1, 'torch CPU threads (0 = torch default); 1 is fastest beside '
                             'a 30 Hz DDS stream on a 2-core machine', range=(0, 1024),
                             restart=True)
    diagnostics_period_s: float = param(1.0, 'period of the /diagnostics summary (s)',
                                        range=(0.05, 3600.0), **_A)
    warn_throttle_s: float = param(5.0, 'per-problem throttle of warnings (s)',
                                   range=(0.0, 3600.0), **_A)


# -- solver constants (Levenberg-Marquardt) --
LM_DAMPING_START = 1e-3  # initial damping mu of H + mu diag(H)
LM_DAMPING_UP = 10  # mu is multiplied by this when a step raises the energy (rejected)
LM_DAMPING_DOWN = 3  # mu is divided by this when a step is accepted
LM_DAMPING_MIN = 1e-6  # lower bound of mu
LM_RIDGE = 1e-9  # added to the damped system's diagonal (keeps it invertible)
LM_STEP_TOL = 1e-5  # converged when no component of the step exceeds this
LM_SHAPE_MARGIN = 1e-4  # shape steps are clipped this far inside the model's shape bounds
LM_SHAPE_HOLD_DIV = 3  # cold fits to surface points hold the shape for iterations // this
LM_ANNEAL_DIV = 2  # the robust scale reaches gm_sigma after iterations / this
LM_RELIN_TOL = 0.03  # shape change that triggers a re-linearisation of the rest geometry
LM_FREEZE = 1e3  # Hessian diagonal that holds an unsupported joint (data terms are O(1))


# -- person-finding constants --
# Which of the candidates net.preprocess.find_persons returns the pipeline takes as persons.
EXTRA_CANDIDATES = 2  # candidates looked for beyond max_persons (some may be no person)
SECOND_LOOK_CANDIDATES = 6  # ... and when none of those was a person (pipeline.process)
NEAREST_CANDIDATES = 2  # ... and, beyond those (the most central), the nearest of the others
SECOND_LOOK_EVERY = 10  # fewer persons found than wanted and a large blob left whole as
                        # not person-sized: the second look peels it when a person tracked
                        # in the frame before is missing, and on the first frame and every
                        # this-many-th after
MIN_BODY_PIXELS = 60  # network-foreground crop pixels needed to attempt a fit
MIN_BODY_SHARE = 0.4  # a person: the network sees a body in this share of its blob's pixels
MIN_PART_SHARE = 0.02  # body_score: a part counts when it covers this share of the body
RANK_AREA_M2 = 0.15  # ranking candidates: a blob seen over less area than this (m^2; a
                     # whole person 0.18 or more at any distance, a leg cut off by a
                     # depth jump about 0.09) ranks by its share of it
MIN_BEHIND = 0.3  # a blob behind a person is a tracked one with this share of its pixels
MIN_ENCLOSED = 0.1  # ... or not skipped: a found person's pixels enclose less of it
                   # (net.preprocess.enclosed_share)
MAX_SEE_THROUGH = 0.3  # a person's fit: at most this share of its visible side seen through
                       # (fit.freespace.see_through_share; persons <= 0.26, boxes 0.25-0.9)
MIN_COLD_SCORE = 3.4  # a new person (no track yet): at least this body_score (persons
                      # 3.7-13, tracked ones found again half hidden from 1.9; boxes and
                      # scene pieces fitted as a body 0.4-3.2)
NOT_PERSON_IOU = 0.8  # tracking: a candidate whose blob overlaps one the network saw no body
                      # in (MIN_COLD_SCORE) by this intersection over union is that blob ...
NOT_PERSON_FRAMES = 10  # ... and is skipped for this many frames after that verdict
MAX_CLAIMED = 0.5  # a further person: at most this share of its pixels an earlier one's
HELD_BODY_GAIN = 0.5  # a tracked person whose warm fit failed: their last tracked body moved
                     # into place replaces the cold fit when its median residual is at most
                     # this share of the cold fit's (pipeline; validation multi_s31/35)
SEE_THROUGH_GAP_M = 0.05  # both_networks: a fit's score is refine.depth_gap plus this many
                         # metres times its see-through share (validation: the gap alone
                         # kept fits standing in free space, val_s2 30.1 -> 30.8 mm; with
                         # this term 30.2)
GIVE_UP = 1.5  # a new blob beside a person found: its cold fit stops after the first run
               # when that leaves a median target residual above this many times the
               # rejection residual (persons' first runs <= 0.45 times, pieces of the
               # scene from 0.55: validation bags)
