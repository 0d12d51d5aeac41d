"""flamenerf: FLAME-in-NeRF, expression- and view-controllable NeRFs of portrait videos."""

__version__ = "0.1.0"
