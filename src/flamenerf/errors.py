"""Errors that reach the user as one line, never as a traceback."""


class UserError(Exception):
    """Bad input or a failed precondition; the message names the file and the problem."""
