"""Settings that follow from the stereo rig and the frame rate.

A depth limit in metres or a search window in pixels means something different on every rig:
30 m is the edge of what a 11 cm EuRoC pair can triangulate, but a 54 cm KITTI pair still
measures depth at 200 m. So these settings are derived from the calibration and the frame
interval, with constants chosen so that the real EuRoC rig (436 px after rectification,
0.11 m, 20 Hz), for which the defaults were tuned, keeps them (30 m, 40 px):

- ``max_depth_m`` = f b / d_min: the depth whose disparity is the smallest one worth using,
  d_min = disparity_sigma_px / MAX_RELATIVE_DEPTH_ERROR (depth error / depth = sigma_d / d).
  Farther points are then noisier in depth than that, but they still pin the rotation.
- ``max_features``: the feature budget keeps EuRoC's density (1200 corners on 752 x 480
  pixels), so a larger image is not covered more sparsely: the grid cells keep their corners
  and a wide KITTI frame (1241 x 376) gets the budget of its area (1551), up to
  ``MAX_DERIVED_FEATURES``: the frame's cost grows with its corners, and a 1280 x 720 image
  covered at EuRoC's density (3064) would cost twice a EuRoC frame (and exceed what a shared
  service worker accepts per session, 1600).
- ``search_radius_px``: the image motion a constant-velocity prediction misses grows with the
  focal length (pixels per radian) and the frame interval (the motion changes more between
  frames), so the window scales with f * dt: 40 px at 436 px and 50 ms.
- ``min_search_radius_px``: one wide window for every point hands each point the candidates
  of a motion it did not make (dozens in KITTI's 132 px window; on EuRoC's still V1_01 clip
  21 000 candidate pairs per frame in 40 px windows for a motion of a pixel or two); each
  point gets its own window from the prediction's uncertainty and its depth, within the wide
  one and no narrower than ``NARROW_SEARCH_RADIUS_PX`` (estimator/frontend/temporal.py).
- ``frontend.chain_common_rotation_bias``: the error a combined measurement cannot average out
  (estimator/odometry/combination.py, ``ChainCombination``), per unit of image motion: 0.005
  for a real rig (MH_01's keyframe measurements), 0 for an exact one.
- ``backend.calibration_rotation_gain`` / ``calibration_translation_gain``: the calibration
  error in the covariances reported without a gyro (``estimator.backend.systematic_noise``):
  1 % and 2 % of the motion for a real rig, 0 for one whose calibration declares itself exact
  (``StereoRig.calibration_exact``: a rendered rig), whose covariances they made ~100x too
  large.
- ``backend.fit_min_rotation_sigma_rad`` / ``fit_min_translation_sigma_m``: the floor of the
  graph's relative-pose covariance (``estimator.backend.systematic_noise.fit_floor``): 0.1 mrad
  and 0.5 mm for a real rig, a fifth of that for an exact one, whose vision the real-rig floor
  weighed below the gyro (fused drives worse than vision alone, docs/backend.md).
- ``backend.robust_parameter`` / ``answer_smoothing_s``: the robust kernel's scale and the
  online answer's time constant (``estimator.backend.noise.kernel_scale``,
  ``estimator.backend.answer.answer_time_constant``): 3 and 0 for a real rig; for an exact one,
  whose measurement covariances are consistent, a kernel that leaves a consistent 6-DOF
  measurement at nearly full weight (Cauchy 12.3) and the smoother's lag. The floors, kernel,
  time constant and shared-error factor of an exact rig presume consistent covariances: with the
  isotropic registration (``registration.use_point_sigmas: false``) they keep the real-rig values.
- ``backend.keyframe_error_correlation``: the factor 1 + 2 rho on the fused pose covariance for
  the keyframe-shared error (``estimator.backend.systematic_noise``): 0.5 for an exact rig, 0 for
  a real one, whose fit floor and placement priors already cover it.

Explicit configuration always wins: a frontend field the user set (``model_fields_set`` of the
frontend section) or a backend gain, floor, kernel scale or time constant that is not None is
never replaced.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from estimator.backend.answer import answer_time_constant
from estimator.backend.noise import kernel_scale
from estimator.backend.systematic_noise import (
    calibration_gains,
    fit_floor,
    keyframe_error_correlation,
)
from estimator.config import BackendConfig, FrontendConfig, SwarmvoConfig
from estimator.formats.calibration import StereoRig

__all__ = [
    "FEATURES_PER_PIXEL",
    "MAX_DERIVED_FEATURES",
    "MAX_RELATIVE_DEPTH_ERROR",
    "NARROW_SEARCH_RADIUS_PX",
    "RIG_SETTINGS_KEY",
    "DerivedSetting",
    "FrameIntervalEstimate",
    "apply_rig_settings",
    "backend_with_calibration_gains",
    "derive_calibration_settings",
    "derive_rig_settings",
    "format_settings",
    "interval_dependent",
    "settings_record",
]

# Key of a stored configuration (a service session's) that records what was derived and
# whether the frame interval is still to come from the first frames' stamps.
RIG_SETTINGS_KEY = "rig_settings"
# Settings that need the frame interval (the others follow from the rig alone).
# (min_search_radius_px goes with a search_radius_px that is not configured.)
_INTERVAL_SETTINGS = ("search_radius_px",)
# Back-end fields whose None means "from the rig's calibration accuracy".
_GAIN_FIELDS = ("calibration_rotation_gain", "calibration_translation_gain")
_FLOOR_FIELDS = ("fit_min_rotation_sigma_rad", "fit_min_translation_sigma_m")
# The robust kernel's scale and the online answer's time constant (consistent covariances).
_WEIGHT_FIELDS = ("robust_parameter", "answer_smoothing_s", "keyframe_error_correlation")

# Depth error / depth at the farthest point kept (EuRoC: 30 m with sigma_d = 0.5 px).
MAX_RELATIVE_DEPTH_ERROR = 0.3125  # d_min = 1.6 px at the default sigma_d of 0.5 px
# Features per pixel of the image: 1200 on EuRoC's 752 x 480, for which they were tuned.
FEATURES_PER_PIXEL = 1200.0 / (752 * 480)
MAX_DERIVED_FEATURES = 1600  # a third more corners than EuRoC's, at the most
# Search radius per (focal px x frame interval s): 40 px / (436 px x 0.05 s).
SEARCH_RADIUS_PER_FOCAL_SECOND = 40.0 / (436.0 * 0.05)
# Windows are kept within these bounds (a few px of noise; a third of a small image).
MIN_SEARCH_RADIUS_PX = 20.0
MAX_SEARCH_RADIUS_PX = 250.0
# The floor of the per-point windows: a few px of prediction noise and of the session's first,
# still prior-sized, error level.
NARROW_SEARCH_RADIUS_PX = 10.0
# MH_01's keyframe measurements: rotation error beyond their covariance per unit of image
# motion (benchmarks/chain_link_errors.py).
REAL_RIG_COMMON_ROTATION_BIAS = 0.005


@dataclass(frozen=True)
class DerivedSetting:
    """One rig-derived setting, and whether the configuration's own value won."""

    name: str  # field of the section's config model
    value: float | None  # None: a configured "off" (min_search_radius_px)
    reason: str
    overridden: bool = False  # the user set the field explicitly: their value is used
    section: Literal["frontend", "backend"] = "frontend"


def derive_rig_settings(
    rig: StereoRig, frame_interval_s: float | None, frontend: FrontendConfig
) -> list[DerivedSetting]:
    """Settings that follow from the rig (and the frame interval, when known)."""
    focal = float(rig.rectification.fx)
    baseline = rig.baseline
    width, height = rig.size
    explicit = frontend.model_fields_set
    smallest_disparity = frontend.disparity_sigma_px / MAX_RELATIVE_DEPTH_ERROR
    settings = [
        DerivedSetting(
            "max_depth_m",
            round(focal * baseline / smallest_disparity, 1),
            f"f b / d_min = {focal:.1f} px x {baseline:.3f} m / {smallest_disparity:.2f} px",
        ),
        DerivedSetting(
            "max_features",
            float(min(round(FEATURES_PER_PIXEL * width * height), MAX_DERIVED_FEATURES)),
            f"{FEATURES_PER_PIXEL * 1e3:.3f} per 1000 px x {width} x {height} px, "
            f"<= {MAX_DERIVED_FEATURES}",
        ),
    ]
    if frame_interval_s is not None and frame_interval_s > 0:
        radius = SEARCH_RADIUS_PER_FOCAL_SECOND * focal * frame_interval_s
        radius = min(max(radius, MIN_SEARCH_RADIUS_PX), MAX_SEARCH_RADIUS_PX)
        settings.append(
            DerivedSetting(
                "search_radius_px",
                round(radius, 1),
                f"{SEARCH_RADIUS_PER_FOCAL_SECOND:.3f} x f dt = {focal:.1f} px x "
                f"{frame_interval_s * 1e3:.1f} ms",
            )
        )
    if "search_radius_px" not in explicit:
        # Per point from the first frame, known frame rate or not (the windows follow the
        # prediction's uncertainty; the wide one, derived or not yet, bounds them).
        settings.append(
            DerivedSetting(
                "min_search_radius_px",
                NARROW_SEARCH_RADIUS_PX,
                "per-point windows, within search_radius_px",
            )
        )
    settings.append(common_rotation_bias(rig))
    return [
        DerivedSetting(
            s.name,
            _configured(getattr(frontend, s.name)),
            f"configured; the rig suggests {s.value:g}",
            overridden=True,
        )
        if s.name in explicit
        else s
        for s in settings
    ]


def common_rotation_bias(rig: StereoRig) -> DerivedSetting:
    """``frontend.chain_common_rotation_bias``: a real rig's measurements carry an error that
    grows with their image motion and is common to the estimates a chain combines; an exact
    (rendered) rig's hardly (its keyframe measurements 0.0016 x their motion, noisy loop)."""
    if rig.calibration_exact:
        return DerivedSetting("chain_common_rotation_bias", 0.0, "the rig's calibration is exact")
    return DerivedSetting(
        "chain_common_rotation_bias",
        REAL_RIG_COMMON_ROTATION_BIAS,
        "the rig's calibration is not declared exact",
    )


def _configured(value: float | None) -> float | None:
    return None if value is None else float(value)


def derive_calibration_settings(
    rig: StereoRig, backend: BackendConfig, point_sigmas: bool = True
) -> list[DerivedSetting]:
    """The back end's calibration gains, fit floors and weights: configured (not None), else
    from the rig.

    The floors, the kernel, the answer's time constant and the shared-error factor of an exact
    rig presume consistent measurement covariances, which the stereo (per-point) noise model
    gives and the isotropic registration (``registration.use_point_sigmas: false``) does not:
    with it they keep the real-rig values (rendered flights with broken frames, isotropic front
    end: fused ATE 4.7 / 6.2 / 3.7 mm with them, 6.3 / 7.4 / 3.3 with the exact-rig values).
    """
    fields = _GAIN_FIELDS + _FLOOR_FIELDS + _WEIGHT_FIELDS
    unset = backend.model_copy(update=dict.fromkeys(fields))
    exact = rig.calibration_exact
    consistent = exact and point_sigmas
    suggested = (
        *calibration_gains(unset, exact),
        *fit_floor(unset, consistent),
        kernel_scale(unset.robust_kernel, None, consistent),
        answer_time_constant(unset, consistent),
        keyframe_error_correlation(unset, consistent),
    )
    reason = "the rig's calibration is " + ("exact" if exact else "not declared exact")
    weight_reason = reason
    if exact and not point_sigmas:
        weight_reason = reason + ", but isotropic point noise is not consistent"
    reasons = [reason] * len(_GAIN_FIELDS) + [weight_reason] * (len(fields) - len(_GAIN_FIELDS))
    settings = []
    for name, value, why in zip(fields, suggested, reasons, strict=True):
        configured = getattr(backend, name)
        if configured is None:
            settings.append(DerivedSetting(name, value, why, section="backend"))
        else:
            settings.append(
                DerivedSetting(
                    name,
                    float(configured),
                    f"configured; the rig suggests {value:g}",
                    overridden=True,
                    section="backend",
                )
            )
    return settings


def apply_rig_settings(
    config: SwarmvoConfig, rig: StereoRig, frame_interval_s: float | None
) -> tuple[SwarmvoConfig, list[DerivedSetting]]:
    """``config`` with the derived settings filled in where the user left the default."""
    settings = derive_rig_settings(rig, frame_interval_s, config.frontend)
    updates = {s.name: s.value for s in settings if not s.overridden}
    # Re-validated, with the user's fields-set record kept: derived values are not the user's.
    user = config.frontend.model_fields_set
    frontend = FrontendConfig.model_validate({**config.frontend.model_dump(), **updates})
    frontend = FrontendConfig.model_construct(user, **frontend.model_dump())
    point_sigmas = config.registration.use_point_sigmas
    calibration = derive_calibration_settings(rig, config.backend, point_sigmas)
    backend = backend_with_calibration_gains(config.backend, rig, point_sigmas)
    updated = config.model_copy(update={"frontend": frontend, "backend": backend})
    return updated, settings + calibration


def backend_with_calibration_gains(
    backend: BackendConfig, rig: StereoRig, point_sigmas: bool = True
) -> BackendConfig:
    """``backend`` with the calibration gains it leaves unset (None) derived from the rig."""
    derived = derive_calibration_settings(rig, backend, point_sigmas)
    return backend.model_copy(update={s.name: s.value for s in derived if not s.overridden})


def format_settings(
    rig: StereoRig, frame_interval_s: float | None, settings: list[DerivedSetting]
) -> str:
    """Lines for the console: the rig, then each setting with where its value came from."""
    rate = f", {1.0 / frame_interval_s:.1f} Hz" if frame_interval_s else ""
    lines = [
        f"rig: {rig.size[0]}x{rig.size[1]} px, f {rig.rectification.fx:.1f} px, "
        f"baseline {rig.baseline:.3f} m{rate}; settings derived from it:"
    ]
    for s in settings:
        shown = "none" if s.value is None else f"{s.value:g}"
        lines.append(f"  {s.section}.{s.name} = {shown}  ({s.reason})")
    return "\n".join(lines)


def interval_dependent(config: SwarmvoConfig) -> bool:
    """Settings wait for the frame interval: the user left them to be derived."""
    return any(name not in config.frontend.model_fields_set for name in _INTERVAL_SETTINGS)


def settings_record(
    frame_interval_s: float | None, settings: list[DerivedSetting], from_stamps: bool
) -> dict[str, object]:
    """What a session stores beside its configuration (JSON): rate, settings, what is pending."""
    return {
        "frame_rate_hz": None if not frame_interval_s else round(1.0 / frame_interval_s, 6),
        "settings": [
            {"name": f"{s.section}.{s.name}", "value": s.value, "reason": s.reason,
             "overridden": s.overridden}
            for s in settings
        ],
        "from_stamps": from_stamps,
    }


class FrameIntervalEstimate:
    """The frame interval of a stream whose rate nobody declared, from its first stamps.

    The median of the first ``count`` intervals: one late, early or dropped frame at the start
    does not set the search window for the whole session. ``add`` answers the estimate when it
    is new or has moved by more than ``tolerance`` (relative) since it was last answered.
    """

    def __init__(self, count: int = 9, tolerance: float = 0.1) -> None:
        self.count = count
        self.tolerance = tolerance
        self._last_ns: int | None = None
        self._intervals: list[int] = []
        self._answered: float | None = None

    @property
    def interval_s(self) -> float | None:
        return self._answered

    def add(self, timestamp_ns: int) -> float | None:
        """Take the next frame's stamp; the interval (s) when it is new or has moved."""
        previous, self._last_ns = self._last_ns, int(timestamp_ns)
        if previous is None or len(self._intervals) >= self.count or timestamp_ns <= previous:
            return None
        self._intervals.append(int(timestamp_ns) - previous)
        estimate = float(np.median(self._intervals)) * 1e-9
        answered = self._answered
        if answered is not None and abs(estimate - answered) <= self.tolerance * answered:
            return None
        self._answered = estimate
        return estimate
