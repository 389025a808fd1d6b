"""``python -m estimator.cli``: the ``swarmvo`` command without the installed script."""

import sys

from estimator.cli.main import main

sys.exit(main())
