"""``inkdiag label``: (being written)."""

HELP = "label (not yet available)"
DESCRIPTION = HELP


def add_arguments(parser) -> None:
    pass


def run(args) -> int:
    raise NotImplementedError("inkdiag label is not available yet")
