"""``python -m estimator.compiled``: build the kernels ahead of time (see build.py).

The build must declare the kernels as just-in-time dispatchers, and the kernel modules may
already have been imported in another mode on the way here (``estimator`` imports them): it
runs in a fresh interpreter with ``SWARMVO_KERNELS=build``.
"""

import os
import sys

from estimator.compiled import MODE_VARIABLE, KernelMode, active_mode

if __name__ == "__main__":
    if active_mode() is not KernelMode.BUILD:
        environment = {**os.environ, MODE_VARIABLE: KernelMode.BUILD.value}
        arguments = [sys.executable, "-m", "estimator.compiled", *sys.argv[1:]]
        os.execve(sys.executable, arguments, environment)
    from estimator.compiled.build import main

    raise SystemExit(main())
