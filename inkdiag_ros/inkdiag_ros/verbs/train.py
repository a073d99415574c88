"""``inkdiag train``: (being written)."""

HELP = "train (not yet available)"
DESCRIPTION = HELP


def add_arguments(parser) -> None:
    pass


def run(args) -> int:
    raise NotImplementedError("inkdiag train is not available yet")
