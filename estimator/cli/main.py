"""``swarmvo`` command line: a thin dispatcher over one module per sub-command.

Each module named in ``COMMANDS`` provides ``add_arguments(parser)`` and ``run(args) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings
from importlib.metadata import PackageNotFoundError, version

from estimator.compiled.built import BuiltKernelsError

DESCRIPTION = (
    "Stereo visual odometry: stereo frame pairs (and IMU samples) in, the robot's pose out. "
    "Run it over a recorded sequence, render test sequences, benchmark it, or serve it."
)

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "bench": ("estimator.cli.commands.bench", "run a benchmark (tables + JSON + PNG)"),
    "serve": ("service.cli", "run the HTTP/WebSocket odometry service"),
    "run": ("estimator.cli.commands.run", "run the odometry over a EuRoC/KITTI sequence"),
    "synth": ("estimator.cli.commands.synth", "render a stereo + IMU sequence with ground truth"),
    "config": (
        "estimator.cli.commands.config",
        "print the configuration (defaults or a file) as YAML",
    ),
}


def package_version() -> str:
    try:
        return version("swarmvo")
    except PackageNotFoundError:  # running from a source tree that was never installed
        return "unknown"


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The full parser, or with ``only`` just that command's options loaded.

    Loading a command's module can import the whole estimator; ``swarmvo serve`` then keeps
    a few hundred MB in the server process that only its workers need.
    """
    parser = argparse.ArgumentParser(prog="swarmvo", description=DESCRIPTION)
    parser.add_argument("--version", action="version", version=f"swarmvo {package_version()}")
    subparsers = parser.add_subparsers(dest="command", required=True)
    for name, (module_name, help_text) in COMMANDS.items():
        # Only the chosen command's module is imported (`swarmvo serve` must not load the
        # estimator's numba and GTSAM); its user-facing DESCRIPTION / EPILOG when it has one.
        module = importlib.import_module(module_name) if only in (None, name) else None
        sub = subparsers.add_parser(
            name,
            help=help_text,
            description=getattr(module, "DESCRIPTION", help_text),
            epilog=getattr(module, "EPILOG", None),
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        sub.set_defaults(_module=module_name)
        if module is not None:
            module.add_arguments(sub)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one plain line: the user needs the message, not our source line."""
    print(f"swarmvo: warning: {message}", file=file or sys.stderr)


def main(argv: list[str] | None = None) -> int:
    words = sys.argv[1:] if argv is None else argv
    command = words[0] if words and words[0] in COMMANDS else None
    try:
        # The commands' modules load the compiled kernels: a bad SWARMVO_KERNELS, or a build
        # that SWARMVO_KERNELS=aot insists on and that does not fit, is one line here.
        parser = build_parser(only=command)
    except (ValueError, BuiltKernelsError) as error:
        print(f"swarmvo: error: {error}", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    warnings.showwarning = _show_warning
    module = importlib.import_module(args._module)
    try:
        return int(module.run(args) or 0)
    except (ValueError, FileNotFoundError, NotADirectoryError) as error:
        one_line = " ".join(str(error).split())  # a user's error is one line, never a dump
        print(f"swarmvo {args.command}: error: {one_line}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader went away (`swarmvo config | head`): not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
