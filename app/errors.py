"""Errors the user can act on: each carries a one-line message naming what is wrong."""


class InputError(Exception):
    """Bad input (a file, a parameter, a layout): the CLI prints the message, no traceback, exit 2."""
