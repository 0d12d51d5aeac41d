"""Errors that reach the user as one line, never as a traceback."""

import sys


class UserError(Exception):
    """Bad input or a failed precondition; the message names the file and the problem."""


class Interrupted(Exception):
    """Ctrl-C, after the command kept what it could; the CLI prints the message and exits
    with 130, the shell's status for SIGINT, so `train && eval` stops there."""


def warn(message: str) -> None:
    """One line on stderr for something the user should know but that does not stop us."""
    print(f"flamenerf: warning: {message}", file=sys.stderr, flush=True)
