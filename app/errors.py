"""Errors the user can act on: each carries a one-line message naming what is wrong."""


class InputError(Exception):
    """Bad input (a file, a parameter, a layout): the CLI prints the message, no traceback, exit 2."""


class Stalled(Exception):
    """An offline run that cannot go on: a stage on the bus finishes nothing, or a worker
    never comes on the bus (the message names it and the frame). The worker exits with
    ``EXIT_STALLED``; the launcher ends the run incomplete (exit 1) with the message."""
