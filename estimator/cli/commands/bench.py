"""``swarmvo bench NAME``: dispatch to the benchmark modules in ``estimator.bench``."""

from __future__ import annotations

import argparse
import importlib

# benchmark name -> module in estimator.bench providing add_arguments(parser) and run(args)
BENCHMARKS: dict[str, str] = {
    "registration": "estimator.bench.registration",
    "frontend": "estimator.bench.frontend",
    "odometry": "estimator.bench.odometry",
    "backend": "estimator.bench.backend",
    "consistency": "estimator.bench.consistency",
    "driving": "estimator.bench.driving",
    "rigs": "estimator.bench.rigs",
    "perturbations": "estimator.bench.perturbations",
    "report": "estimator.bench.report",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    subparsers = parser.add_subparsers(dest="benchmark", required=True)
    for name, module_name in BENCHMARKS.items():
        sub = subparsers.add_parser(name)
        sub.set_defaults(_bench_module=module_name)
        importlib.import_module(module_name).add_arguments(sub)


def run(args: argparse.Namespace) -> int:
    return int(importlib.import_module(args._bench_module).run(args) or 0)
