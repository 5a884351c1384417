"""The one exception every adapter raises for input it cannot convert."""


class AdapterError(ValueError):
    """A message or array that cannot be converted; the text names the field and the problem."""
