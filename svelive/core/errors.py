"""The one exception type the library raises for bad input."""


class SveliveError(ValueError):
    """Bad input or configuration; the message is one line and names what was wrong."""
