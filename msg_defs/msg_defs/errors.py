"""The one exception of the wire contract."""

__all__ = ["MessageError"]


class MessageError(ValueError):
    """A message that does not follow inkdiag's wire contract.

    The text says what was expected and what arrived. Subclasses
    ``ValueError`` so callers can catch the builtin.
    """
