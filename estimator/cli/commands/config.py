"""``swarmvo config``: the configuration the odometry would run with, as YAML.

Without arguments it prints every key with its default, so that a user can see what exists
and start a config file from it; with ``--config FILE`` it prints that file merged onto the
defaults (and refuses it with one line per problem when it is invalid). With a dataset folder
it prints what ``swarmvo run DATASET`` would use: the frontend settings derived from that
dataset's rig and frame rate filled in (``estimator.rig_settings``; configured values win),
under a comment header saying where each derived value came from. The output is a valid
config file.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import yaml

from estimator.config import SwarmvoConfig
from estimator.formats.datasets import open_sequence
from estimator.pipeline import frame_interval_s, load_config
from estimator.rig_settings import apply_rig_settings, format_settings


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "dataset", type=Path, nargs="?",
        help="a EuRoC or KITTI folder: also show the settings derived from its rig and rate",
    )
    parser.add_argument(
        "--data", type=Path, dest="data_option", metavar="DATASET", help="same as DATASET"
    )
    parser.add_argument(
        "--config", type=Path, help="a JSON or YAML config file to check and show merged"
    )
    parser.add_argument("--format", choices=("euroc", "kitti"), help="dataset format (detected)")


def run(args: argparse.Namespace) -> int:
    if args.dataset is not None and args.data_option is not None:
        raise ValueError("give the dataset once: as DATASET or as --data")
    dataset = args.dataset if args.dataset is not None else args.data_option
    if dataset is None:
        config = load_config(args.config) if args.config is not None else SwarmvoConfig()
        yaml.safe_dump(config.model_dump(mode="json"), sys.stdout, sort_keys=False)
        return 0
    sequence = open_sequence(dataset, args.format)
    interval = frame_interval_s(sequence)
    config = load_config(args.config, interval) if args.config is not None else SwarmvoConfig()
    config, derived = apply_rig_settings(config, sequence.rig, interval)
    print(f"# {sequence.name} ({len(sequence.frames)} frames)")
    for line in format_settings(sequence.rig, interval, derived).splitlines():
        print(f"# {line}")
    yaml.safe_dump(config.model_dump(mode="json"), sys.stdout, sort_keys=False)
    return 0
