"""Ctrl-C as a request to stop at the next step boundary.

A KeyboardInterrupt raised wherever Python happens to be can land between the optimiser
update and the step counter, or after the step drew random numbers: a checkpoint saved then
resumes into a different run. So while training, SIGINT only sets a flag that the loop
reads between steps; the step in flight completes and the checkpoint is an exact resume
point. Pressing again says what is going on; a third press gives up on the step or the save
in flight (raising KeyboardInterrupt), which leaves the last complete checkpoint as it was.
"""

from __future__ import annotations

import signal
import sys
import threading


class StopRequest:
    """Context manager: while active (main thread only), Ctrl-C sets `requested`.

    Outside the main thread signals cannot be caught, and Ctrl-C stays a KeyboardInterrupt.
    The previous handler is restored on exit."""

    def __init__(self, what: str = "the current step"):
        self.presses = 0
        self.what = what
        self._previous = None

    @property
    def requested(self) -> bool:
        return self.presses > 0

    @property
    def active(self) -> bool:
        return self._previous is not None

    def _handle(self, signum, frame) -> None:
        self.presses += 1
        if self.presses == 2:
            print(f"\nflamenerf: finishing {self.what} so that the run can resume exactly; "
                  "Ctrl-C once more to give it up (the last saved checkpoint stays)",
                  file=sys.stderr, flush=True)
        elif self.presses >= 3:
            raise KeyboardInterrupt

    def __enter__(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
            self._previous = None
