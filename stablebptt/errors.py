"""The one exception type that means: the user's input is wrong, say so in one line."""


class InputError(ValueError):
    """Bad user input. Scripts print its message as one line and exit with code 2."""
