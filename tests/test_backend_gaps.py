"""The back end across vision gaps on the real MH_01 clip: fused no worse than vision alone."""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

import pytest

from estimator.formats.datasets import open_sequence
from estimator.pipeline import build_config, run_sequence, summarize
from estimator.rendered.perturb import PERTURBATIONS, perturb_sequence


def _black_every_tenth(path: Path, frames: int) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unpaired camera rows of the recording
        sequence = open_sequence(path)
    perturbed = perturb_sequence(sequence, replace(PERTURBATIONS["black every 10th"], seed=0))
    config = build_config(seed=0, imu=True, backend=True)
    backend = config.backend.model_copy(update={"old_reference": "prior-after-gap"})
    config = config.model_copy(update={"backend": backend})
    summary, _ = summarize(run_sequence(perturbed, config, frames, use_imu=True))
    return summary


@pytest.mark.slow
@pytest.mark.euroc
def test_fused_is_no_worse_than_vision_alone_after_black_frames(euroc_mh01_moving: Path) -> None:
    """Frames 9, 19, ... are black; the frame after each is measured against a keyframe that has
    left the smoother's window. Placed from that keyframe (as the front end's own chain does),
    the fused answer stays within the vision-alone chain's error, which the chain through the
    IMU-carried neighbours did not (3.7 against 3.1 mm over these 60 frames). The front end
    does not use the back end's answers, so its trajectory in this run is vision alone's."""
    summary = _black_every_tenth(euroc_mh01_moving, 60)
    fused, vision = summary["fused"]["ate_rmse_m"], summary["frontend"]["ate_rmse_m"]
    assert fused <= vision, (fused, vision)
    assert summary["fused"]["rpe_rot_rmse_deg"] < 0.015
