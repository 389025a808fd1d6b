"""The command line the ground-truth diagnostics share: a dataset folder and the estimator's
seed, the folder opened into a sequence with a ground truth or refused with one clear error."""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

from estimator.formats.datasets import Sequence, open_sequence


def clip_parser(description: str) -> argparse.ArgumentParser:
    """A parser with the dataset folder and ``--seed``; the caller adds its own options."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    return parser


def quiet_sequence(path: Path) -> Sequence:
    """``open_sequence(path)`` without its warnings: unpaired camera rows are expected in
    EuRoC, and the diagnostics report on the clip, not on its files."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return open_sequence(path)


def open_clip(parser: argparse.ArgumentParser, path: Path) -> Sequence:
    """The sequence at ``path``; a folder that cannot be read or has no ground truth ends the
    program through ``parser.error`` (one line, no traceback)."""
    try:
        sequence = quiet_sequence(path)
    except (OSError, ValueError) as error:
        parser.error(f"cannot read {path}: {error}")
    if sequence.ground_truth is None:
        parser.error(f"{path} has no ground truth")
    return sequence
