"""``swarmvo config``: the configuration the odometry would run with, as YAML.

Without arguments it prints every key with its default, so that a user can see what exists
and start a config file from it; with ``--config FILE`` it prints that file merged onto the
defaults (and refuses it with one line per problem when it is invalid).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import yaml

from estimator.config import SwarmvoConfig
from estimator.pipeline import load_config


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config", type=Path, help="a JSON or YAML config file to check and show merged"
    )


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config) if args.config is not None else SwarmvoConfig()
    yaml.safe_dump(config.model_dump(mode="json"), sys.stdout, sort_keys=False)
    return 0
