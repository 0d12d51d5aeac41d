"""The browser pages and the RenderWorker between them: a page's camera to the worker, the
worker's images and failures to the page (its background and its status line).

One part of `Viewer` (viewer/app.py; why mixins: viewer/state.py)."""

from __future__ import annotations

import time

import numpy as np

from flamenerf.gpu_kernels import fault_advice, first_line, gpu_faulted
from flamenerf.viewer.camera import HomeCamera, c2w_from_viser, home_camera
from flamenerf.viewer.renderer import Frame

STATUS_PREFIX = "Render"


class ViewerPages:
    """Each connected page (by its client id): its client, status line and camera."""

    def _init_pages(self) -> None:
        self._clients: dict[int, object] = {}
        self._status: dict[int, object] = {}
        self._synced_after: dict[int, float] = {}
        self.sync_s = 10.0

    def reset_camera(self, client, to: HomeCamera | None = None) -> None:
        """A page's camera to frame 0's (or `to`)."""
        to = self.home if to is None else to
        cam = client.camera
        with client.atomic():
            cam.fov = to.fov_y
            cam.up_direction = tuple(float(x) for x in to.up)
            cam.position = tuple(float(x) for x in to.position)
            cam.look_at = tuple(float(x) for x in to.look_at)

    def frame_camera(self) -> HomeCamera | None:
        """Every page's camera to the one the track's current frame was filmed from (a
        track of the clip's frames; None and nothing moved for another)."""
        t = self.current_track()
        if t is None or not t.clip:
            return None
        k = int(min(max(self.g_frame.value, 0), t.num_frames - 1))
        to = home_camera(self.ds, t.clip[k].position)
        for client in list(self._clients.values()):
            self.reset_camera(client, to)
        return to

    def _on_connect(self, client) -> None:
        self._clients[client.client_id] = client
        with self.view_folder:
            status = client.gui.add_markdown(f"{STATUS_PREFIX}: waiting for the first image",
                                             order=-1.0)
        self._status[client.client_id] = status
        # A new page reports three.js's default camera before the initial one applies:
        # put it at frame 0's camera, render that view right away, and ignore the page's
        # camera until it reports that pose (or for at most `sync_s`).
        self._synced_after[client.client_id] = time.monotonic() + self.sync_s

        def on_camera(cam) -> None:
            self._camera_changed(client)

        client.camera.on_update(on_camera)
        self.reset_camera(client)
        try:
            aspect = float(client.camera.aspect)
        except (AssertionError, ZeroDivisionError):
            aspect = self.ds.intrinsics.w / self.ds.intrinsics.h
        self.worker.set_camera(client.client_id, self.home.c2w, self.home.fov_y, aspect)

    def _camera_changed(self, client) -> None:
        cam = client.camera
        try:
            aspect = float(cam.aspect)
            if not np.isfinite(aspect) or aspect <= 0:
                return
            c2w = c2w_from_viser(cam.wxyz, cam.position)
            fov = float(cam.fov)
        except (AssertionError, ZeroDivisionError):  # no camera message yet
            return
        until = self._synced_after.get(client.client_id)
        if until is not None:
            at_home = (np.allclose(c2w, self.home.c2w, atol=1e-4)
                       and abs(fov - self.home.fov_y) < 1e-4)
            if not at_home and time.monotonic() < until:
                return  # still the page's default camera
            self._synced_after.pop(client.client_id, None)
        self.worker.set_camera(client.client_id, c2w, fov, aspect)

    def capture_note(self, client) -> str:
        """' · outside the capture (N cm)' when the browser's camera stands where no training
        camera filmed from (views there extrapolate: rendering/cameras.py), else ''."""
        try:
            eye = np.asarray(client.camera.position, np.float64)
        except (AssertionError, AttributeError):
            return ""
        if not np.all(np.isfinite(eye)) or self.rig.near_capture(eye[None])[0]:
            return ""
        d = np.linalg.norm(self.rig.captured_eyes() - eye, axis=1).min()
        return f" · outside the capture ({100 * d:.0f} cm from its cameras)"

    def _on_disconnect(self, client) -> None:
        self._clients.pop(client.client_id, None)
        self._status.pop(client.client_id, None)
        self._synced_after.pop(client.client_id, None)
        self.worker.remove_view(client.client_id)

    def _render_failed(self, key, err: BaseException) -> None:
        status = self._status.get(key)
        if status is not None:
            msg = first_line(err)[:160]
            # a lost CUDA context fails every image after it: say how to get going again
            after = ("the GPU cannot render in this process again: "
                     + fault_advice("restart the viewer") if gpu_faulted(err)
                     else "see the terminal")
            status.content = (f"{STATUS_PREFIX}: failed ({type(err).__name__}: {msg}); "
                              f"{after}")

    def _display(self, key, frame: Frame) -> None:
        client = self._clients.get(key)
        if client is None:
            return
        fmt = "png" if frame.final else "jpeg"
        client.scene.set_background_image(frame.image, format=fmt, jpeg_quality=90)
        status = self._status.get(key)
        if status is not None:
            state = "final" if frame.final else f"preview {frame.level + 1}"
            if frame.extras.get("filmed") is not None:
                state += f" · frame {frame.extras['filmed']} " + (
                    "as filmed" if frame.extras.get("own_codes") else "with frame 0's codes")
            status.content = (f"{STATUS_PREFIX}: {frame.seconds * 1000:.0f} ms · "
                              f"{frame.intr.w}×{frame.intr.h} px · {state} · "
                              f"#{frame.count}{self.capture_note(client)}")
        self.last_frame = frame
