"""`flamenerf view`."""

from __future__ import annotations

# what the command runs is imported inside its function: the CLI imports every command
# module to build its --help (cli.py), which stays quick that way

from pathlib import Path
from typing import Annotated

import tyro

from flamenerf.viewer.options import ViewerOptions


def view(
    run: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN")],
    opts: Annotated[ViewerOptions, tyro.conf.OmitArgPrefixes, tyro.conf.arg(name="")],
    device: str = "auto",
    threads: int = 0,
) -> None:
    """Explore a trained run in the browser: move the camera, set the expression.

    Serves a viewer at http://localhost:PORT (open it in a browser): drag to orbit, scroll
    to zoom, right-drag to pan; the camera starts at the capture's first frame. One
    slider per expression control, `Reset to neutral`, playback of an expression track
    (a tour of the controls, the dataset's own sequences, or a `flamenerf track` file or
    an ARKit take (Live Link Face CSV) given with --track; its Edit box changes every frame of a track as `render --edit`
    does), head-pose sliders for runs trained with head poses, RGB or
    depth, and a resolution control: while the camera moves it renders at 1/4 of the
    chosen resolution (1/2 after other changes) and refines when still. Images use frame
    0's deformation and appearance codes, except the capture's frames shown As filmed
    (each with its own codes, head pose and mesh, as `render --split capture`); the
    spatial prior is the face mesh of the expression shown.
    Ctrl-C stops it.

    The server listens on 127.0.0.1 only; `--host 0.0.0.0` serves every network
    interface (anyone who can reach the port can use the viewer).

    Example: flamenerf view runs/fast --track drive.json

    Args:
        run: Run directory made by `flamenerf train`.
        device: `auto` (CUDA when present), `cpu` or `cuda`.
        threads: CPU threads for torch (0 = torch's default).
    """
    import time

    from flamenerf.errors import UserError

    if run.exists() and not run.is_dir():
        raise UserError(f"{run}: is a file; give the run directory made by `flamenerf train`")
    if not run.is_dir():
        raise UserError(f"{run}: run directory does not exist")
    if not (run / "config.json").exists():
        raise UserError(f"{run}: not a trained run (no config.json; make one with "
                        f"`flamenerf train`)")
    if opts.resolution < 0 or opts.max_resolution < 8:
        raise UserError("--resolution must be >= 0 and --max-resolution >= 8")

    from flamenerf.viewer.app import check_port_free

    check_port_free(opts.host, opts.port)  # before the slow model load

    from flamenerf.runtime import set_threads

    set_threads(threads)

    from flamenerf.training.run import load_run
    from flamenerf.viewer.app import Viewer

    r = load_run(run, device=device)
    viewer = Viewer(r, opts).start()
    print(f"flamenerf view: {r.run_dir} (step {r.step}, {len(r.expression_names)} "
          f"expression controls) at {viewer.url}  (Ctrl-C to stop)", flush=True)
    if opts.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"flamenerf view: listening on {opts.host}: reachable from other machines",
              flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        print("flamenerf view: stopped", flush=True)
    finally:
        viewer.stop()
