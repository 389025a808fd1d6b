"""The one typed configuration of swarmvo, with sane defaults.

Each stage owns one section; ``SwarmvoConfig`` is what the pipeline, the CLI and the service
pass around (the service accepts JSON overrides of it).
"""

from __future__ import annotations

import difflib
import warnings
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    model_validator,
)

from estimator.registration.methods import DEFAULT_ESTIMATOR, Estimator

# Validation context key (``model_validate(data, context=...)``): the rig's frame period in
# seconds, when the caller knows it; old keys counted in frames are converted with it.
FRAME_INTERVAL_CONTEXT = "frame_interval_s"
# The rate the old frame-counted defaults were chosen at (EuRoC's 20 Hz), assumed when the
# frame period is not known at validation time.
ASSUMED_FRAME_INTERVAL_S = 0.05
# The most keyframes a front end keeps for revisits (frontend.revisit_max_keyframes); the back
# end keeps the poses of a few times as many frames that were measured against.
MAX_REVISIT_KEYFRAMES = 64
# The largest disparity offset believed (frontend.disparity_offset_px, pixels): beyond it the
# stereo calibration is wrong, not slightly off (estimator/frontend/disparity_offset.py).
MAX_DISPARITY_OFFSET_PX = 5.0


class _Section(BaseModel):
    # Unknown keys and non-finite numbers are input errors, not settings.
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class RegistrationConfig(_Section):
    """Relative-pose estimator used by the odometry (``estimator.register``)."""

    # The names come from the estimator registry; stored as the plain name (a str).
    model_config = ConfigDict(use_enum_values=True)

    method: Estimator = Field(DEFAULT_ESTIMATOR, validate_default=True)
    # Extra keyword options passed to the estimator (e.g. {"particles": 48}).
    options: dict[str, float | int | str | bool] = Field(default_factory=dict)
    # Hand each stereo point's 3x3 covariance (at the noise level measured on the session's inlier
    # residuals, estimator/frontend/stereo_noise.py) to estimators that weigh it: pso-robust's
    # support is then a Mahalanobis test (noise along the viewing ray, growing with depth).
    use_point_sigmas: bool = True
    # "measured": the pixel / disparity noise is estimated online from the inlier residuals;
    # "fixed": the frontend constants throughout (no state carried from frame to frame).
    noise_model: Literal["measured", "fixed"] = "measured"
    # With "measured": a point's disparity noise grows with its disparity, sigma_d (1 + g d), g
    # measured like the level (a near point's two views differ more: on EuRoC MH_01 the
    # disparity residuals of points at 40-200 px are 2-3x those at 3-20 px); False: one
    # disparity noise at every depth.
    disparity_noise_growth: bool = True
    # Final maximum-likelihood refinement of the pose on the inliers, each point weighed by its full
    # stereo covariance (ray-aligned: depth is far less certain than direction); see
    # estimator/registration/refine.py. The inlier set stays the estimator's; it cuts the front-end
    # error 3-7x for ~0.6 ms per frame, and its 6x6 covariance is what the back end then uses.
    mahalanobis_refine: bool = True
    refine_iterations: int = Field(5, ge=1, le=50)
    # Robust weight on the Mahalanobis distance of each pair (leftover outliers).
    refine_robust: Literal["cauchy", "huber", "none"] = "cauchy"
    # In standard deviations of the measured noise level (estimator/frontend/stereo_noise.py): at 3
    # the kernel, now at the right scale, biased rendered rotations (4 standard errors about the
    # optical axis); 6 removes that and is as accurate on the real clip.
    refine_robust_scale: float = Field(6.0, gt=0)
    # ... times the inliers' own spread at the registration's pose where that is below 1,
    # sqrt(median d^2 / chi-square median) (refine.residual_spread): 1 once the measured level
    # fits, but while a session's first frames still run on the generous noise prior a moving
    # car's pairs look consistent and pull the pose (a rendered drive with traffic: 18 -> 3 mm
    # ATE vision alone; docs/frontend.md, "The kernel in the inliers' own spread").
    refine_scale_from_residuals: bool = True
    # The refinement's 6x6 covariance (estimator/registration/refine.py): "median", the inverse
    # Hessian scaled by the median squared Mahalanobis residual; "sandwich", the robust sandwich
    # from the residuals the inliers actually show (their heavy tails move the pose more than a
    # Gaussian with their median spread: on the rendered drives the median one is 2x too small
    # in variance, translation NEES per DOF 3.8 instead of 1.4); "sandwich-reported": the back
    # end weighs the median one, the frame reports and the odometry messages built from them
    # carry the sandwich (docs/frontend.md, "The covariance the refinement hands on").
    refine_covariance: Literal["median", "sandwich", "sandwich-reported"] = "sandwich-reported"


class FrontendConfig(_Section):
    """Features, stereo matching, triangulation and temporal matching."""

    # Map every rectified image to this grey-level mean and standard deviation first, so that
    # auto exposure and a left/right gain mismatch do not reach the later stages.
    normalise_contrast: bool = True
    normalised_mean: float = Field(128.0, gt=0, lt=255)
    normalised_std: float = Field(64.0, gt=0)
    # "orb" on one level runs as compiled kernels with array output that give OpenCV's ORB
    # features to the bit (frontend/fast_kernels.py, frontend/steered_brief.py); on several
    # levels OpenCV's ORB runs. "fast-brief": the same kernels with this project's own seeded
    # test pairs instead of ORB's; the same 32-byte descriptors, matched the same way.
    detector: Literal["orb", "sift", "fast-brief"] = "orb"
    max_features: int = Field(1200, gt=0)
    # Detection: over-sample, then keep the best corners cell by cell (docs/frontend.md).
    detection_oversampling: float = Field(2.0, ge=1.0)
    grid_rows: int = Field(6, gt=0)
    grid_cols: int = Field(8, gt=0)
    fast_threshold: int = Field(12, gt=0)  # ORB's FAST threshold (grey levels)
    # Raise FAST's threshold per image while ORB still sees the same corners (one ORB level;
    # estimated from strips of the image, estimator/frontend/fast_threshold.py).
    adaptive_fast_threshold: bool = True
    orb_levels: int = Field(1, gt=0)  # one level: half the cost, same accuracy at 20 Hz
    orb_scale_factor: float = Field(1.2, gt=1.0)
    # Descriptor acceptance: Hamming bits for ORB, L2 for SIFT (unit 512-norm descriptors).
    max_hamming: int = Field(64, ge=0, le=256)
    max_sift_distance: float = Field(250.0, gt=0)
    # Stereo matching on rectified images.
    stereo_row_tolerance_px: float = Field(1.5, ge=0)
    min_disparity_px: float = Field(1.0, gt=0)
    max_disparity_px: float = Field(160.0, gt=0)
    stereo_ratio: float = Field(0.9, gt=0, le=1)
    # Disparity refinement: SAD patch search + equiangular fit, Lucas-Kanade, or none.
    subpixel: Literal["sad", "lk", "none"] = "sad"
    # The right shutter's time minus the left's, in milliseconds (cameras without a shared
    # trigger), undone in every disparity (the image motion over it). None: measured from the
    # stereo matches' rows and reported, not undone; 0: synchronised, not measured
    # (estimator/frontend/shutter_offset.py).
    stereo_time_offset_ms: float | None = Field(None, ge=-100, le=100)
    # A constant offset in every disparity (pixels; a slightly-off calibration of the right
    # camera), taken out of each one. None: measured from the registrations and taken out once
    # measured (detect mode; track mode keeps 0); a number: that offset from the first frame
    # (estimator/frontend/disparity_offset.py).
    disparity_offset_px: float | None = Field(
        None, ge=-MAX_DISPARITY_OFFSET_PX, le=MAX_DISPARITY_OFFSET_PX
    )
    subpixel_window: int = Field(5, ge=1, le=15)  # half size of the patch
    disparity_sigma_px: float = Field(0.5, gt=0)  # disparity noise behind depth_sigma
    # Pixel noise of a stereo point's image position, for its full covariance (disparity noise
    # is disparity_sigma_px). Only the prior of the first frames: the odometry measures the
    # session's own level on its inlier residuals (estimator/frontend/stereo_noise.py).
    pixel_sigma_u_px: float = Field(1.0, gt=0)
    pixel_sigma_v_px: float = Field(1.0, gt=0)
    min_depth_m: float = Field(0.2, gt=0)
    max_depth_m: float = Field(30.0, gt=0)
    # Temporal matching (current frame <-> reference frame).
    temporal_ratio: float = Field(0.85, gt=0, le=1)
    search_radius_px: float = Field(40.0, ge=0)  # around the predicted position; 0 = anywhere
    # Per-point windows (estimator/frontend/temporal.py): each reference point's window is the
    # predicted motion's uncertainty projected at its pixel and depth (3 sigma), within
    # [min_search_radius_px, search_radius_px]; search_radius_px when the prediction is poor
    # (first frames, after a gap or a failed frame). None: search_radius_px for every point
    # (derived, 10 px, from the rig and its frame rate: estimator/rig_settings.py).
    min_search_radius_px: float | None = Field(None, ge=0)
    # What a constant-velocity prediction misses over a span T: angular and linear
    # acceleration times T^2 (one sigma).
    prediction_angular_accel_deg_s2: float = Field(200.0, ge=0)
    prediction_linear_accel_m_s2: float = Field(5.0, ge=0)
    # With IMU samples and per-point windows (min_search_radius_px set) the predicted
    # rotation is the gyro's (estimator/odometry/gyro_prediction.py); its rate error (one
    # sigma) starts here and is then learned against vision.
    gyro_prediction: bool = True
    prediction_gyro_error_deg_s: float = Field(2.0, gt=0)
    # "descriptor": ratio + mutual descriptor matching; "klt": Lucas-Kanade tracking.
    temporal_matcher: Literal["descriptor", "klt"] = "descriptor"
    klt_window: int = Field(10, ge=2, le=30)  # half size of the KLT window
    klt_levels: int = Field(3, ge=0, le=6)  # KLT pyramid levels
    klt_association_px: float = Field(2.0, gt=0)  # track -> nearest stereo point
    # "detect": ORB in both images every frame, stereo and temporal descriptor matching;
    # "track": persistent Lucas-Kanade tracks, new corners only where they thinned out, stereo
    # by LK along the row, pairs by track id (estimator/frontend/tracks.py, docs/frontend.md).
    mode: Literal["detect", "track"] = "detect"
    max_tracks: int = Field(300, gt=0)  # live tracks in track mode
    track_window: int = Field(5, ge=2, le=30)  # half size of the tracks' LK window
    track_levels: int = Field(3, ge=0, le=6)  # LK pyramid levels of the tracks in time
    track_refill_ratio: float = Field(0.8, gt=0, le=1)  # new corners below this share
    track_min_distance_px: float = Field(12.0, gt=0)  # new corners this far from live tracks
    # When fewer than this share of the keyframe's tracks are still live (a black, blurred or
    # dropped frame lost them on the way), the lost ones are searched again from the
    # keyframe's own image, so the frame still shares tracks with its keyframe. 0: never.
    track_recover_ratio: float = Field(0.5, ge=0, le=1)
    # A frame whose tracks' median LK residual in time is above this times the recent frames'
    # (motion blur, a flash) is not followed: no points, and the tracks stay where they were
    # for the next frame. 0: always followed.
    track_blur_ratio: float = Field(4.0, ge=0)
    temporal_refine: bool = True  # sub-pixel current positions by Lucas-Kanade
    temporal_refine_window: int = Field(5, ge=1, le=15)  # half size of the LK window
    # Warp each reference patch by the predicted motion (roll, change of scale) before the
    # LK refinement (estimator/frontend/patch_warp.py).
    temporal_refine_warp: bool = False
    min_matches: int = Field(12, ge=3)  # fewer 3D-3D pairs: the frame is not estimated
    min_inlier_ratio: float = Field(0.25, ge=0, le=1)  # fewer inliers per match: failed
    # Without an estimate the pose coasts at the last velocity (status degraded) for at most
    # this long since the last vision fix (s), then it is held (status lost). 0 = always hold.
    max_coast_s: float = Field(0.25, ge=0)
    # A relative pose whose rotation is further from the constant-velocity prediction than
    # this rate times the predicted time span is rejected: vision alone has no gyro to catch a
    # wrong fit (a 100 deg flip) that a widened support gate let through. None: no check.
    max_rotation_surprise_deg_s: float | None = Field(300.0, gt=0)
    # Tracking against a keyframe (no creeping drift while the view overlaps) or frame-to-frame.
    tracking: Literal["keyframe", "frame"] = "keyframe"
    keyframe_min_inliers: int = Field(80, ge=3)
    keyframe_max_translation_m: float = Field(0.25, gt=0)
    keyframe_max_rotation_deg: float = Field(10.0, gt=0)
    # Translation threshold relative to the scene instead: this times the median depth of the
    # keyframe's points (parallax), so that a street at 40 m and a room at 3 m both keep their
    # keyframes while the view overlaps. None: keyframe_max_translation_m. A configured
    # keyframe_max_translation_m wins.
    keyframe_max_parallax: float | None = Field(None, gt=0)
    # Also measure each frame against the previous one and combine that chain with the
    # keyframe measurement by their covariances and the cross-covariance of the points they
    # share (estimator/odometry/chains.py). None: on when the back end fuses no IMU (vision
    # alone), off with the IMU. Vision alone on MH_01 it gives 0.0173 instead of 0.0211 deg
    # per frame at 4.7 mm (with the link bias below); fused with the IMU it made MH_01 worse
    # (4.4 instead of 3.9 mm). One more registration per frame.
    fuse_previous_frame: bool | None = None
    # Keyframe revisits (estimator/odometry/revisits.py): when a new keyframe is due and a
    # stored keyframe at least ``revisit_min_age_s`` old is within the rotation and
    # translation limits of it, the frame is measured against that one, which becomes the
    # reference again with ``revisit_min_inlier_ratio`` x ``keyframe_min_inliers`` inliers:
    # the frames after a return to a place carry that keyframe's error, not the drift since.
    # None: on when the back end fuses no IMU, in detect mode. Vision alone on MH_01 4.46 ->
    # 3.95 mm ATE, 0.0166 -> 0.0177 deg per frame; the rendered sequences never return to an
    # old keyframe (docs/frontend.md, "Keyframe revisits"). The translation limit, None: 1.2 x
    # the keyframes' own. ``revisit_max_keyframes`` keyframes are kept, each with its image.
    revisit_keyframes: bool | None = None
    revisit_max_keyframes: int = Field(16, ge=1, le=MAX_REVISIT_KEYFRAMES)
    revisit_min_age_s: float = Field(0.5, ge=0)
    revisit_max_rotation_deg: float = Field(15.0, gt=0)
    revisit_max_translation_m: float | None = Field(None, gt=0)
    revisit_min_inlier_ratio: float = Field(0.8, gt=0)
    # Rotation error of the chain's frame-to-frame link that does not average out (motion
    # blur moves consecutive frames' points alike), per unit of the link's image motion
    # (median flow / focal length): sigma = this x flow / f per axis is added to the link's
    # rotation covariance. 0.005: MH_01's links err beyond their covariance by 0.0047 x their
    # motion (keyframe measurements 0.0049); it brings the noisy rendered loop's front end
    # with the chain from +14 % to +8 % of the keyframe-only ATE (docs/frontend.md).
    chain_link_rotation_bias: float = Field(0.005, ge=0)
    # The keyframe measurement's share of that error that the chain cannot average out (the
    # current frame's blur and the calibration err both estimates alike), per unit of its image
    # motion; the combined measurement's covariance counts it once. None: from the rig
    # (estimator/rig_settings.py): 0.005 for a real rig (MH_01's keyframe measurements exceed
    # their covariance by 0.0050 x their motion), 0 for one whose calibration is declared exact
    # (a rendered rig: 0.005 made its rotation covariances some 30x too large).
    chain_common_rotation_bias: float | None = Field(None, ge=0)
    # ... only while the keyframe measurement sees this much image motion (median inlier flow,
    # px): at rest the keyframe measurement alone is as good (V1_01 0.0081 / 0.0080 deg per
    # frame) and the chain would nearly double the frame's matching and estimation.
    chain_min_flow_px: float = Field(1.0, ge=0)
    # ... and against the keyframe before the current one while it is still in view (off: on
    # MH_01 vision alone 4.5 mm instead of 4.6, but the rendered loop's ATE 5 % worse).
    fuse_previous_keyframe: bool = False

    @model_validator(mode="before")
    @classmethod
    def _max_coast_frames_alias(cls, data: Any, info: ValidationInfo) -> Any:
        """Accept the old ``max_coast_frames`` as ``max_coast_s`` (frames x frame period).

        Config files written for earlier releases keep working; one warning line says what
        the key became so that the user can write the new one.
        """
        if not isinstance(data, dict) or "max_coast_frames" not in data:
            return data
        data = dict(data)
        frames = data.pop("max_coast_frames")
        if "max_coast_s" in data:
            raise ValueError("give max_coast_s or the old max_coast_frames, not both")
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 0:
            raise ValueError(f"max_coast_frames must be a whole number >= 0, got {frames!r}")
        interval = (info.context or {}).get(FRAME_INTERVAL_CONTEXT)
        known = interval is not None and interval > 0
        period = interval if known else ASSUMED_FRAME_INTERVAL_S
        data["max_coast_s"] = round(frames * period, 6)  # whole microseconds
        source = "the rig's frame period" if known else "assumed 20 Hz: frame rate not known"
        warnings.warn(
            f"frontend.max_coast_frames is deprecated: read as frontend.max_coast_s = "
            f"{data['max_coast_s']:g} ({frames} frames x {period * 1e3:g} ms, {source})",
            FutureWarning,
            stacklevel=2,
        )
        return data


class BackendConfig(_Section):
    """GTSAM fusion of relative poses with IMU rotation priors (docs/backend.md)."""

    enabled: bool = True
    use_imu: bool = True
    # Solver: a fixed-lag smoother keeps the per-frame cost flat; "isam2" keeps all history.
    smoother: Literal["fixed-lag", "isam2"] = "fixed-lag"
    # Window of the fixed-lag smoother (s): old frames leave it in blocks of
    # ``marginalize_block_s`` (cheaper than one by one), so each stays between lag and
    # lag + block. Frames up to lag - block old are always in it: that must cover two frame
    # intervals (the inertial factor ties three consecutive frames), 0.2 s by default.
    smoother_lag_s: float = Field(0.4, gt=0)
    marginalize_block_s: float = Field(0.2, ge=0)
    # iSAM2 relinearizes a variable when its update exceeds these (per component). The
    # inertial factor divides positions by the frame interval (1 mm is ~20 mm/s at 20 Hz
    # against a ~3 mm/s sigma), so a position left at a stale linearisation point (a frame
    # across a vision gap, corrected by the next frame's measurement) biases gravity and the
    # accelerometer bias once it is marginalised: positions relinearise at 5 mm (1 mm helps the
    # gaps a little more but costs ~1 mm on the clean real clip without per-point sigmas).
    relinearize_rotation_rad: float = Field(0.02, gt=0)
    relinearize_translation_m: float = Field(0.005, gt=0)
    relinearize_bias: float = Field(0.005, gt=0)  # rad/s
    extra_iterations: int = Field(1, ge=0, le=10)  # extra iSAM2 steps per frame
    # Robust kernel on the front-end relative poses (threshold on the whitened 6-DOF error).
    robust_kernel: Literal["huber", "cauchy", "none"] = "cauchy"
    # The online answer (backend/answer.py): the previous answer moved on by the newest motion,
    # pulled towards the smoother's newest pose with this time constant (s), so the revisions
    # of past frames reach it gradually; 0: the newest pose itself. None: from the rig
    # (estimator/rig_settings.py): the smoother's lag for a rig whose calibration is exact, else 0.
    answer_smoothing_s: float | None = Field(None, ge=0)
    # None: from the rig (estimator/rig_settings.py; backend/noise.py, ``kernel_scale``): 3 for
    # a real rig; for one whose calibration is exact, from the chi-square of 6 DOF so that a
    # consistent measurement keeps nearly full weight (Cauchy 12.3, Huber 4.1).
    robust_parameter: float | None = Field(None, gt=0)
    # Relative poses further than this (squared Mahalanobis distance, 6 DOF) from the
    # prediction (gyro rotation, constant-velocity translation) are not added; None: keep all.
    outlier_gate_chi2: float | None = Field(30.0, gt=0)
    # Relative-pose covariance from the registration inliers (backend/noise.py).
    point_spread_m: float = Field(1.5, gt=0)  # typical RMS distance of inliers from centroid
    translation_sigma_scale: float = Field(1.0, gt=0)
    rotation_sigma_scale: float = Field(1.0, gt=0)
    min_translation_sigma_m: float = Field(0.002, gt=0)
    max_translation_sigma_m: float = Field(0.5, gt=0)
    min_rotation_sigma_rad: float = Field(0.0005, gt=0)
    max_rotation_sigma_rad: float = Field(0.2, gt=0)
    fallback_residual_m: float = Field(0.05, gt=0)  # when no residuals are given
    # Full covariance of the fit when the front end hands over the inlier points: a scale on it
    # and floors added to its diagonal (the max sigmas above act as a weak prior). None: from
    # the rig (estimator/rig_settings.py): 0.1 mrad and 0.5 mm for a real rig, a fifth of that
    # for one whose calibration is exact (backend/systematic_noise.py, ``fit_floor``).
    fit_covariance_scale: float = Field(1.0, gt=0)
    fit_min_rotation_sigma_rad: float | None = Field(None, ge=0)
    fit_min_translation_sigma_m: float | None = Field(None, ge=0)
    # Reported covariances (backend/covariance_scale.py): a per-session factor on them, measured
    # online from the gyro ("gyro"; 1 without an IMU) or none ("off"); within
    # [1 / max, max]; over the last ``window`` measurements; allowing for a gyro bias error
    # of ``gyro_bias_sigma`` rad/s. The back end's factor noise does not change.
    covariance_scale: Literal["gyro", "off"] = "gyro"
    # Correlation of the errors of consecutive measurements against one keyframe (they share
    # its stereo points; half of each fit's error is the keyframe's when both frames' points
    # are equally noisy). The graph counts them as independent, so its pose covariance grows
    # too slowly: the reported growth is multiplied by 1 + 2 x this (the variance of a sum of
    # errors with that lag-1 correlation; backend/systematic_noise.py, ``shared_error_growth``).
    # None: from the rig (estimator/rig_settings.py): 0.5 for a rig whose calibration is exact,
    # 0 for a real one, whose fit floor and placement priors' carried covariance already cover
    # it (real MH_01 fused pose NEES per DOF 0.68 without it, 0.34 with it).
    keyframe_error_correlation: float | None = Field(None, ge=0, lt=1)
    covariance_scale_max: float = Field(16.0, ge=1)
    covariance_scale_window: int = Field(400, ge=5)
    covariance_scale_gyro_bias_sigma: float = Field(2e-4, ge=0)
    # Time-local factor (the larger one is reported): the vision chain against the gyro over
    # stretches of ``local_window_s``, the last ``local_count`` of them (0: off).
    covariance_scale_local_window_s: float = Field(1.0, gt=0)
    covariance_scale_local_count: int = Field(10, ge=0)
    # The session factor, where above 1, also on the graph's relative-pose factors and the gate
    # (the reports are scaled as before). Real MH_01 fused: 0.0097 deg per frame instead of
    # 0.0116, the ATE within the solver's spread, the final drift larger; so not the default
    # (docs/backend.md, "What the fused rotation error on MH_01 is made of").
    covariance_scale_factors: bool = False
    # Reported covariances without the gyro factor (no IMU, or the front end alone;
    # backend/systematic_noise.py): the fit's covariance, this floor instead of ``fit_min_*``,
    # and a calibration error proportional to the measured motion (relative, per axis). None:
    # from the rig (estimator/rig_settings.py): 1 % and 2 %, 0 for a rig whose calibration is
    # exact (a rendered one). The graph's noise does not change.
    report_min_rotation_sigma_rad: float = Field(5e-5, ge=0)
    report_min_translation_sigma_m: float = Field(2.5e-4, ge=0)
    calibration_rotation_gain: float | None = Field(None, ge=0)
    calibration_translation_gain: float | None = Field(None, ge=0)
    # Constant-velocity prior between consecutive frames (per frame interval): on every frame
    # ("always": lets the robust kernel see a wrong relative pose) or only without vision.
    motion_prior: Literal["always", "gaps"] = "gaps"
    # A relative pose whose reference frame has left the smoother's window: "chain" ties it to
    # the previous frame (after a gap: the last one with vision) through their current
    # estimates; "prior" places the frame in the world from the reference's estimate and the
    # measurement; "prior-after-gap" does so only for the first frames with vision after frames
    # without (their recent neighbours are carried by the IMU alone), else "chain". "prior" (the
    # default) places every such frame from its keyframe: on the real MH_01 clip fused 0.0067
    # deg per frame instead of 0.0116, and stable across solver settings where the chain,
    # which feeds the previous frame's estimate back as a measurement, is not; the uncertainty
    # the placement drops is added to the reported covariance (backend/placement_covariance.py,
    # docs/backend.md).
    old_reference: Literal["chain", "prior", "prior-after-gap", "views"] = "prior"
    # "views": a measurement against a keyframe goes through a view variable of that keyframe
    # that stays while measurements refer to it (backend/keyframe_views.py): the fraction
    # ``keyframe_shared_error`` of each measurement's covariance is the error all share (on the
    # view's link to the keyframe), and the n-th measurement against one keyframe has its
    # covariance times n ** ``keyframe_count_inflation`` (they are not independent). MH_01
    # fused: 0.0076 deg per frame, pose NEES 2.07 per DOF, ATE 4.4 mm (docs/backend.md).
    keyframe_shared_error: float = Field(0.01, gt=0, lt=1)
    keyframe_count_inflation: float = Field(1.0, ge=0, le=3)
    # Stereo landmarks (backend/landmarks.py, docs/backend.md): the inliers of each accepted
    # measurement enter the window as 3D points observed in both rectified images
    # (GenericStereoFactor3D), at most ``landmark_max_per_frame`` well-spread ones per frame,
    # with the session's measured pixel noise times ``landmark_noise_scale`` and a Huber kernel
    # at ``landmark_huber`` sigmas. ``landmark_between``: keep the relative-pose factor too
    # (it counts the same pixels twice). Off by default: on the real MH_01 clip it does not
    # beat the relative poses and makes the fused covariance too small (docs/backend.md).
    landmarks: bool = False
    landmark_max_per_frame: int = Field(120, ge=3)
    landmark_noise_scale: float = Field(1.0, gt=0)
    landmark_huber: float = Field(2.0, gt=0)
    landmark_between: bool = True
    landmark_flow_noise: bool = True  # pixel noise grows with the flow (frontend/stereo_noise)
    landmark_across_keyframes: bool = False  # a point matched to a landmark keeps it as keyframe
    landmark_cholesky: bool = True  # Cholesky instead of QR while landmarks are on (~8x faster)
    cv_translation_sigma_m: float = Field(0.05, gt=0)
    cv_rotation_sigma_rad: float = Field(0.05, gt=0)
    # IMU: noise from sensor.yaml times a scale; bias random walk override (rad/s^2/sqrt(Hz)).
    imu_noise_scale: float = Field(1.0, gt=0)
    gyro_random_walk: float | None = Field(None, gt=0)
    gyro_bias_prior_sigma: float = Field(0.05, gt=0)  # rad/s, on the first bias
    imu_time_offset_s: float = 0.0  # t_imu = t_camera + offset (Kalibr's convention)
    imu_max_gap_s: float = Field(0.02, gt=0)  # larger holes in the gyro -> no IMU factor
    gravity_align: bool = True
    # Accelerometer (backend/inertial.py): a factor on every three consecutive frames ties their
    # velocity change to the preintegrated specific force, with world gravity (prior: -z with
    # ``gravity_prior_sigma`` m/s^2 per axis when the world is levelled at start-up) and one
    # accelerometer bias (prior 0 +- ``accel_bias_prior_sigma`` m/s^2) as graph variables. Its
    # sigma is the accelerometer's white noise, at least ``inertial_min_sigma_mps`` (m/s).
    use_accelerometer: bool = True
    gravity_prior_sigma: float = Field(1.0, gt=0)
    accel_bias_prior_sigma: float = Field(0.1, gt=0)
    inertial_min_sigma_mps: float = Field(3e-3, gt=0)
    # Longest frame interval the inertial factor spans (s): the specific force is integrated
    # with the gyro bias of the moment, an error that grows with the square of the interval
    # (10 mrad/s over 1.5 s tilts gravity into 0.2 m of position); longer gaps fall back to
    # the constant-velocity prior.
    inertial_max_interval_s: float = Field(0.25, gt=0)
    # Static initialisation (backend/rest.py): while the IMU (and vision, when it sees) shows
    # the platform at rest at start-up, the gyro bias starts from the mean gyro before the
    # first frame and consecutive frames are tied by a zero-motion factor.
    static_init: bool = True
    rest_z: float = Field(5.0, gt=0)  # standard deviations each standstill test allows
    rest_min_duration_s: float = Field(0.04, gt=0)  # shortest IMU window before frame 0 used
    zero_motion_sigma_rad: float = Field(1e-5, gt=0)
    zero_motion_sigma_m: float = Field(1e-4, gt=0)
    # 16 numbers, row-major T_BS of the left camera; overrides the calibration when given.
    body_from_camera: list[float] | None = Field(None, min_length=16, max_length=16)

    @model_validator(mode="after")
    def _block_inside_lag(self) -> BackendConfig:
        if self.marginalize_block_s >= self.smoother_lag_s:
            raise ValueError(
                f"marginalize_block_s ({self.marginalize_block_s}) must be shorter than "
                f"smoother_lag_s ({self.smoother_lag_s})"
            )
        return self


class SwarmvoConfig(_Section):
    """Everything the odometry needs besides the calibration."""

    seed: int = Field(0, ge=0)  # NumPy seeds are non-negative
    registration: RegistrationConfig = Field(default_factory=RegistrationConfig)
    frontend: FrontendConfig = Field(default_factory=FrontendConfig)
    backend: BackendConfig = Field(default_factory=BackendConfig)


def explain_validation_error(
    error: ValidationError,
    model: type[BaseModel] = SwarmvoConfig,
    hidden: frozenset[str] = frozenset(),
) -> str:
    """One plain line per problem, with a "did you mean" for a mistyped key and the value given
    (never for the fields named in ``hidden``: passwords, keys).

    Pydantic's own message is several lines with a documentation URL for each error: accurate,
    but hard to read in a terminal or an HTTP answer.
    """
    problems = []
    for item in error.errors(include_url=False):
        location = [str(part) for part in item["loc"]]
        where = ".".join(location) or "configuration"
        if item["type"] == "extra_forbidden":
            known = _field_names_at(model, location[:-1])
            close = difflib.get_close_matches(location[-1], known, n=1)
            hint = f" (did you mean {'.'.join([*location[:-1], close[0]])}?)" if close else ""
            problems.append(f"{where}: unknown key{hint}")
        else:
            # A validator's own ValueError reads "Value error, <message>": keep the message.
            message = item["msg"].removeprefix("Value error, ")
            given = item.get("input")
            shown = ""
            if isinstance(given, int | float | str) and not hidden.intersection(location):
                # The value, shortened: never a payload.
                text = repr(given)
                shown = f" (got {text if len(text) <= 40 else text[:37] + '...'})"
            problems.append(f"{where}: {message}{shown}")
    return "; ".join(problems)


def _field_names_at(model: type[BaseModel], path: list[str]) -> list[str]:
    """Field names of the (nested) section at ``path``; empty when the path leaves the models."""
    for name in path:
        field = model.model_fields.get(name)
        annotation = field.annotation if field is not None else None
        if not (isinstance(annotation, type) and issubclass(annotation, BaseModel)):
            return []
        model = annotation
    return list(model.model_fields)
