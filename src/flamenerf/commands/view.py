"""`flamenerf view`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import tyro


def view(
    run: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN")],
    port: int = 8080,
    host: str = "127.0.0.1",
    track: Annotated[tuple[Path, ...], tyro.conf.UseAppendAction] = (),
    resolution: int = 0,
    max_resolution: int = 1024,
    progressive: bool = True,
    dataset: Path | None = None,
    device: str = "auto",
    threads: int = 0,
) -> None:
    """Explore a trained run in the browser: move the camera, set the expression.

    Serves a viewer at http://localhost:PORT (open it in a browser): drag to orbit, scroll
    to zoom, right-drag to pan; the camera starts at the capture's first frame. One
    slider per expression control, `Reset to neutral`, playback of an expression track
    (the dataset's own sequences, or a `flamenerf track` file given with --track), RGB or
    depth, and a resolution control: while the view changes it renders at 1/4 of the
    chosen resolution and refines when still. Every image uses frame 0's deformation and
    appearance codes and the face mesh of frame 0 as the spatial prior. Ctrl-C stops it.

    The server listens on 127.0.0.1 only; `--host 0.0.0.0` serves every network
    interface (anyone who can reach the port can use the viewer).

    Example: flamenerf view runs/fast --track drive.json

    Args:
        run: Run directory made by `flamenerf train`.
        port: TCP port to serve on.
        host: Address to listen on (default: this machine only).
        track: Expression track JSON from `flamenerf track` (repeat for several).
        resolution: Height in pixels of the refined image (0: the run's training height).
        max_resolution: Upper end of the resolution slider.
        progressive: Render coarse first while the view changes, refine when still.
        dataset: Dataset to read cameras, face mesh and tracks from (default: the run's).
        device: `auto` (CUDA when present), `cpu` or `cuda`.
        threads: CPU threads for torch (0 = torch's default).
    """
    import time

    from flamenerf.errors import UserError

    if not run.is_dir():
        raise UserError(f"{run}: run directory does not exist")
    if not (run / "config.json").exists():
        raise UserError(f"{run}: not a trained run (no config.json; make one with "
                        f"`flamenerf train`)")
    if resolution < 0 or max_resolution < 8:
        raise UserError("--resolution must be >= 0 and --max-resolution >= 8")

    from flamenerf.viewer.app import ViewerOptions, check_port_free

    check_port_free(host, port)  # before the slow model load

    from flamenerf.runtime import set_threads

    set_threads(threads)

    from flamenerf.training.run import load_run
    from flamenerf.viewer.app import Viewer

    r = load_run(run, device=device)
    opts = ViewerOptions(host=host, port=port, height=resolution,
                         max_height=max_resolution, progressive=progressive,
                         tracks=tuple(track), dataset=dataset, verbose=False)
    viewer = Viewer(r, opts).start()
    print(f"flamenerf view: {r.run_dir} (step {r.step}, {len(r.expression_names)} "
          f"expression controls) at {viewer.url}  (Ctrl-C to stop)", flush=True)
    if host not in ("127.0.0.1", "localhost", "::1"):
        print(f"flamenerf view: listening on {host}: reachable from other machines",
              flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        print("flamenerf view: stopped", flush=True)
    finally:
        viewer.stop()
