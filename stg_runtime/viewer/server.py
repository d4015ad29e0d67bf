"""The viewer application on viser: `Viewer` serves a Player to browsers; `serve` runs `stg-view`.

Every browser gets its own picture (a `frames.ClientStream` thread following its camera) and shares
the controls: the time (slider, play / pause, loop, speed), the render mode, jumps to the training
cameras, an info panel, a screenshot and camera-path downloads. `Viewer.set_model` swaps the model
being shown (the training viewer refreshes it as it trains) and `Viewer.set_status` shows a status
text (the training progress).
"""
from __future__ import annotations

import errno
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
import viser

from ..camera import Camera, camera_path_json
from ..model import Model
from ..player import Player
from ..video import encode_png
from .camera import scaled, viser_pose
from .frames import ClientStream, RenderThread, ViewSettings, client_camera, modes_for, render_image
from .keyframes import interpolate_path
from .playback import Playback

#: Ticks per second of the slider while playing (a browser's stream takes a new time for every frame).
PLAYBACK_HZ = 30


class PortInUse(OSError):
    """The viewer's port is taken (by another viewer, say)."""


def check_port_free(host: str, port: int) -> None:
    """PortInUse naming host:port when something already listens there (viser itself would quietly
    move to the next free port)."""
    if port == 0:
        return
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as servers do: TIME_WAIT is no conflict
        try:
            s.bind((host, port))
        except OSError as e:
            if e.errno in (errno.EADDRINUSE, errno.EACCES):
                raise PortInUse(f"port {port} on {host} is in use") from None
            raise


def look_distance(camera: Camera, bounds) -> float:
    """How far ahead of `camera` the orbit pivot goes: the depth of the centre of the model's bounds
    ((3,) min, (3,) max) when it is in front, else 1."""
    if bounds is None:
        return 1.0
    centre = 0.5 * (np.asarray(bounds[0], float) + np.asarray(bounds[1], float))
    depth = float((camera.R @ centre + camera.t)[2])
    return depth if np.isfinite(depth) and depth > 1e-3 else 1.0


def model_info(player: Player) -> str:
    """The info panel's model lines (markdown)."""
    m = player.model
    counts = ", ".join(f"{s.count:,}" for s in m.segments)
    size = f"{m.cameras[0].width}x{m.cameras[0].height}" if m.cameras else "-"
    return (f"**{m.kind}** model, {len(m.segments)} segment{'s' * (len(m.segments) != 1)}  \n"
            f"Gaussians per segment: {counts}  \n"
            f"{player.num_frames} frames at {player.fps:g} fps ({player.duration:.2f} s)  \n"
            f"training image size: {size}, device: {player.device}")


class Viewer:
    """Serves `source` (a Player, a Model or a .stg path) to browsers at http://host:port.

    device: of the Player when `source` is not one. Raises PortInUse when the port is taken. The
    initial view is training camera 0 at the model's first frame. close() stops the server."""

    def __init__(self, source: Player | Model | str | Path, host: str = "127.0.0.1", port: int = 8080,
                 device: str = "auto", settings: ViewSettings | None = None, verbose: bool = False):
        self.player = source if isinstance(source, Player) else Player(source, device=device)
        self.settings = settings or ViewSettings()
        self.version = 0
        self.playback = Playback.of(self.player)
        self.renderer = RenderThread()
        self.keyframes: list[Camera] = []
        self.streams: dict[int, ClientStream] = {}
        self._errors: set[str] = set()
        self._closed = threading.Event()
        check_port_free(host, port)
        self.server = viser.ViserServer(host=host, port=port, label="stg-view", verbose=verbose)
        if port and self.server.get_port() != port:  # taken between the check and viser's bind
            self.server.stop()
            raise PortInUse(f"port {port} on {host} is in use")
        self.host, self.port = host, self.server.get_port()
        self._set_initial_camera()
        self._build_gui()
        self.server.on_client_connect(self.connect)
        self.server.on_client_disconnect(self._disconnect)
        self._clock = threading.Thread(target=self._run_clock, name="stg-view clock", daemon=True)
        self._clock.start()

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    # -- the model and the status -----------------------------------------------------------------
    def set_model(self, source: Player | Model) -> None:
        """Show another model (a newer snapshot in training, or the next segment: the time is kept,
        clamped to its frames); every browser re-renders."""
        player = source if isinstance(source, Player) else Player(source, device=self.player.device)
        old, playback = self.playback, Playback.of(player)
        playback.playing, playback.loop, playback.speed = old.playing, old.loop, old.speed
        playback.seek(old.time)
        # no lock (training must not wait for a render): the player is replaced before the version is
        # bumped and _source reads them in the other order, so a frame of the old player never carries
        # the new version
        self.playback, self.player = playback, player
        self.version += 1
        if (old.first, old.last) != (self.playback.first, self.playback.last):  # another segment's frames
            self._time.min, self._time.max = self.playback.first, max(self.playback.last, self.playback.first + 1e-3)
        self._wake_all()

    def set_status(self, markdown: str) -> None:
        """Show `markdown` in the status panel (the training progress)."""
        self._status.content = markdown
        self._status.visible = True

    # -- frames -----------------------------------------------------------------------------------
    def _source(self):
        version = self.version
        return self.player, version, self.playback.tick()

    def connect(self, client) -> None:
        """Stream pictures to a browser (viser calls it for each one that connects)."""
        stream = ClientStream(client, self._source, self.settings, self.renderer)
        self.streams[client.client_id] = stream
        threading.Thread(target=stream.run, kwargs={"on_error": self._report}, daemon=True,
                         name=f"stg-view client {client.client_id}").start()

    def _disconnect(self, client) -> None:
        stream = self.streams.pop(client.client_id, None)
        if stream is not None:
            stream.stop()

    def _report(self, error: Exception) -> None:
        message = f"stg-view: a frame failed: {error}"
        if message not in self._errors:  # once per distinct failure
            self._errors.add(message)
            print(message, file=sys.stderr)

    def _wake_all(self) -> None:
        for stream in list(self.streams.values()):
            stream.wake()

    def _run_clock(self) -> None:
        """Advance the playback while playing, move the slider, refresh the info panel once a second."""
        last_info = 0.0
        while not self._closed.wait(1.0 / PLAYBACK_HZ):
            now = time.monotonic()
            t = self.playback.tick(now)
            if self.playback.playing:
                self._time.value = round(t, 4)
                self._wake_all()
            if now - last_info > 1.0:
                last_info = now
                self._update_info()

    # -- the initial view and camera jumps ----------------------------------------------------------
    def _pose(self, camera: Camera):
        return viser_pose(camera, look_distance(camera, self.player.model.bounds))

    def _set_initial_camera(self) -> None:
        cameras = self.player.cameras
        if not cameras:
            return
        ups = np.array([-c.R[1] for c in cameras]).mean(axis=0)
        if np.linalg.norm(ups) > 1e-6:
            self.server.scene.set_up_direction(ups / np.linalg.norm(ups))
        pose = self._pose(cameras[0])
        initial = self.server.initial_camera
        initial.position, initial.look_at = pose.position, pose.look_at
        initial.up, initial.fov = pose.up_direction, pose.fov

    def show_camera(self, client, camera: Camera) -> None:
        """Move a browser's view to `camera` (its pose and vertical field of view)."""
        pose = self._pose(camera)
        with client.atomic():
            client.camera.fov = pose.fov
            client.camera.position = pose.position
            client.camera.look_at = pose.look_at
            client.camera.up_direction = pose.up_direction

    # -- downloads --------------------------------------------------------------------------------
    def screenshot(self, client) -> bytes | None:
        """A PNG of the browser's view at full size (the current mode and time), sent to it; None
        before its camera is known."""
        view = client_camera(client)
        if view is None:
            return None
        camera = scaled(view[1], self.settings.max_pixels)
        image = self.renderer.run(render_image, self.player, camera, self.playback.time, self.settings.mode)
        png = encode_png(image)
        client.send_file_download(f"stg-view-{self.playback.frame:05d}.png", png, save_immediately=True)
        return png

    def camera_path(self, client, keyframes: bool) -> str | None:
        """The browser's current camera (keyframes False) or the keyframes interpolated with the
        "frames between" setting, as camera-path JSON (stg-render --path), sent to it."""
        if keyframes:
            if not self.keyframes:
                client.add_notification("no keyframes", "add keyframes first", auto_close_seconds=4.0)
                return None
            cameras = interpolate_path(self.keyframes, int(self._between.value))
        else:
            view = client_camera(client)
            if view is None:
                return None
            cameras = [view[1]]
        text = camera_path_json(cameras)
        name = "camera-path.json" if keyframes else "camera.json"
        client.send_file_download(name, text.encode(), save_immediately=True)
        return text

    def add_keyframe(self, client) -> None:
        view = client_camera(client)
        if view is not None:
            self.keyframes.append(view[1])
            self._keyframe_count.content = f"keyframes: {len(self.keyframes)}"

    # -- the panel --------------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui, p = self.server.gui, self.playback
        with gui.add_folder("Time"):
            self._time = gui.add_slider("time (s)", min=p.first, max=max(p.last, p.first + 1e-3), step=0.001,
                                        initial_value=p.first)
            self._frame = gui.add_markdown(self._frame_text())
            play = gui.add_button_group("playback", ["play", "pause"])
            self._loop = gui.add_checkbox("loop", initial_value=True)
            self._speed = gui.add_slider("speed", min=0.1, max=4.0, step=0.1, initial_value=1.0)
        with gui.add_folder("View"):
            self._mode = gui.add_dropdown("render mode", modes_for(self.player.kind), initial_value="rgb")
            names = [c.name or f"camera {i}" for i, c in enumerate(self.player.cameras)]
            cams = gui.add_button_group("training cameras", names) if names else None
        with gui.add_folder("Save"):
            shot = gui.add_button("screenshot (PNG)")
            save_camera = gui.add_button("save camera (JSON)")
            add_key = gui.add_button("add keyframe")
            clear_keys = gui.add_button("clear keyframes")
            self._between = gui.add_number("frames between keyframes", initial_value=30, min=0, max=10000, step=1)
            save_path = gui.add_button("save camera path (JSON)")
            self._keyframe_count = gui.add_markdown("keyframes: 0")
        with gui.add_folder("Info"):
            self._info = gui.add_markdown(model_info(self.player))
            self._status = gui.add_markdown("", visible=False)

        @self._time.on_update
        def _(event) -> None:
            if event.client is None:  # the clock moving the slider while playing
                return
            self.playback.seek(self._time.value)
            self._frame.content = self._frame_text()
            self._wake_all()

        @play.on_click
        def _(event) -> None:
            self.playback.playing = event.target.value == "play"

        @self._loop.on_update
        def _(_event) -> None:
            self.playback.loop = bool(self._loop.value)

        @self._speed.on_update
        def _(_event) -> None:
            self.playback.speed = float(self._speed.value)

        @self._mode.on_update
        def _(_event) -> None:
            self.settings.mode = self._mode.value
            self._wake_all()

        if cams is not None:
            @cams.on_click
            def _(event) -> None:
                if event.client is not None:
                    self.show_camera(event.client, self.player.cameras[names.index(event.target.value)])

        for button, action in ((shot, self.screenshot), (save_camera, lambda c: self.camera_path(c, False)),
                               (add_key, self.add_keyframe), (save_path, lambda c: self.camera_path(c, True))):
            button.on_click(lambda event, action=action: event.client is not None and action(event.client))

        @clear_keys.on_click
        def _(_event) -> None:
            self.keyframes.clear()
            self._keyframe_count.content = "keyframes: 0"

    def _frame_text(self) -> str:
        p = self.playback
        return f"frame {p.frame} of {self.player.model.start_frame}..{self.player.model.start_frame + self.player.num_frames - 1}"

    def _update_info(self) -> None:
        self._frame.content = self._frame_text()
        lines = [model_info(self.player)]
        for client_id, stream in sorted(self.streams.items()):
            s = stream.stats
            if s.camera is None:
                continue
            fps = 1.0 / float(np.mean(s.intervals)) if s.intervals else 0.0
            lines.append(f"client {client_id}: {s.camera.width}x{s.camera.height}{' (preview)' * s.preview}, "
                         f"render {1000 * s.render_seconds:.0f} ms, {fps:.1f} FPS")
        self._info.content = "  \n".join(lines)

    # -- life cycle ---------------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the clock, every stream and the server."""
        self._closed.set()
        for stream in list(self.streams.values()):
            stream.stop()
        self.renderer.close()
        self._clock.join(timeout=5)  # it must not update the panel of a stopped server
        self.server.stop()


def serve(model: str | Path, host: str = "127.0.0.1", port: int = 8080, device: str = "auto",
          settings: ViewSettings | None = None, ready=None) -> None:
    """`stg-view`: serve `model` until interrupted (Ctrl-C or SIGTERM), then stop cleanly. ready(viewer)
    is called once it serves. Raises FormatError, PortInUse, RuntimeError (no GPU for "cuda")."""
    import signal

    viewer = Viewer(model, host=host, port=port, device=device, settings=settings)
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        if ready is not None:
            ready(viewer)
        while not stop.wait(0.2):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, previous)
        viewer.close()
