"""The browser viewer (viser): a free camera, expression sliders, track playback, RGB /
depth, progressive quality. Rendering runs in `RenderWorker`'s thread; each finished image
becomes the browser's scene background.

`Viewer` is composed of its parts: what it shows (viewer/state.py), its panel's widgets
(viewer/panels.py), track playback (viewer/player.py) and the browser pages the worker's
images go to (viewer/pages.py); this module starts and stops the server and the threads."""

from __future__ import annotations

import contextlib
import errno
import io
import socket
import threading

from flamenerf.errors import UserError
from flamenerf.viewer.options import ViewerOptions
from flamenerf.viewer.pages import ViewerPages
from flamenerf.viewer.panels import ViewerPanels
from flamenerf.viewer.player import ViewerPlayer
from flamenerf.viewer.renderer import RenderWorker
from flamenerf.viewer.state import ViewerState


def check_port_free(host: str, port: int) -> None:
    """A clear error now instead of viser silently moving to the next free port."""
    if not 0 < port < 65536:
        raise UserError(f"--port {port}: must be in 1..65535")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise UserError(f"--host {host}: cannot resolve it ({e.strerror})") from None
    family, _, _, _, addr = infos[0]
    s = socket.socket(family, socket.SOCK_STREAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as asyncio's server does
        s.bind(addr)
    except OSError as e:
        if e.errno == errno.EADDRINUSE:
            raise UserError(f"port {port} on {host} is already in use "
                            f"(another viewer? pick a free one with --port)") from None
        if e.errno == errno.EADDRNOTAVAIL:
            raise UserError(f"--host {host}: not an address of this machine") from None
        if e.errno == errno.EACCES:
            raise UserError(f"port {port}: permission denied (use a port above 1023)") from None
        raise UserError(f"cannot listen on {host}:{port} ({e.strerror})") from None
    finally:
        s.close()


class Viewer(ViewerState, ViewerPanels, ViewerPlayer, ViewerPages):
    """`Viewer(run, opts).start()`; then `url`, `stop()`. Used by `flamenerf view`."""

    def __init__(self, run, opts: ViewerOptions):
        super().__init__(run, opts)
        omega, phi = run.frame_codes(0)
        self.worker = RenderWorker(run.model, omega, phi, self.masker, self.opening,
                                   self._display, height=self.height, settle_s=opts.settle_s,
                                   on_error=self._render_failed)
        self.server = None
        self._init_pages()
        self._init_player()

    @property
    def url(self) -> str:
        host = self.opts.host
        shown = socket.gethostname() if host in ("0.0.0.0", "::", "") else host
        if ":" in shown:
            shown = f"[{shown}]"
        return f"http://{shown}:{self.port}"

    @property
    def port(self) -> int:
        return self.server.get_port() if self.server is not None else self.opts.port

    def start(self) -> "Viewer":
        import viser

        check_port_free(self.opts.host, self.opts.port)
        with contextlib.redirect_stdout(io.StringIO()) as banner:  # we print our own URL
            server = viser.ViserServer(host=self.opts.host, port=self.opts.port,
                                       label="flamenerf view", verbose=self.opts.verbose)
        if self.opts.verbose:
            print(banner.getvalue(), end="")
        if server.get_port() != self.opts.port:  # lost a race for the port
            server.stop()
            raise UserError(f"port {self.opts.port} on {self.opts.host} is already in use "
                            f"(pick a free one with --port)")
        self.server = server
        server.scene.set_up_direction(tuple(float(x) for x in self.home.up))
        server.scene.world_axes.visible = False
        cam = server.initial_camera
        cam.fov = self.home.fov_y
        cam.position = tuple(float(x) for x in self.home.position)
        cam.look_at = tuple(float(x) for x in self.home.look_at)
        cam.up = tuple(float(x) for x in self.home.up)
        self._build_gui()
        server.on_client_connect(self._on_connect)
        server.on_client_disconnect(self._on_disconnect)
        self.worker.start()
        self._play_thread = threading.Thread(target=self._player, name="flamenerf-play",
                                             daemon=True)
        self._play_thread.start()
        return self

    def stop(self) -> None:
        self._closing = True
        self._play.set()
        self.worker.stop()
        if self.server is not None:
            self.server.stop()
