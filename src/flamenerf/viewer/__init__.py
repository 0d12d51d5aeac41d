"""`flamenerf view`: the browser viewer (viser) of a trained run; see docs/viewer.md."""
