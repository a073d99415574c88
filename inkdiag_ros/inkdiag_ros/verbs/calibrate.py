"""``inkdiag calibrate``: (being written)."""

HELP = "calibrate (not yet available)"
DESCRIPTION = HELP


def add_arguments(parser) -> None:
    pass


def run(args) -> int:
    raise NotImplementedError("inkdiag calibrate is not available yet")
