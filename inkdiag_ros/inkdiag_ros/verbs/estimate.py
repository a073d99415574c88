"""``inkdiag estimate``: (being written)."""

HELP = "estimate (not yet available)"
DESCRIPTION = HELP


def add_arguments(parser) -> None:
    pass


def run(args) -> int:
    raise NotImplementedError("inkdiag estimate is not available yet")
