"""The ``inkdiag`` subcommands, one module each (see :mod:`inkdiag_ros.cli`)."""
