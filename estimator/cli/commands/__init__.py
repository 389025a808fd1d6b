"""Sub-commands of the ``swarmvo`` CLI, one module each (``add_arguments`` + ``run``)."""
