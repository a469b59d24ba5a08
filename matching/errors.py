"""Errors that the CLI turns into one-line messages (never a traceback)."""


class InputError(Exception):
    """Bad user input: a missing, unreadable or malformed file. The message names the file."""
