"""Re-animation rendering: camera paths, expression sources, the spatial prior's masks for
novel cameras, and video writing (used by `flamenerf render`, `eval` and `bench`)."""
