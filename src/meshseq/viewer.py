"""Interactive web viewer: mesh sequences side by side in the browser, with play/pause and a frame slider.

Built on viser (a small web server with a three.js client). The server binds to 127.0.0.1
only, so the viewer is reachable from this machine (forward the port over SSH to look from
another). Usage from Python::

    viewer = Viewer([seq_a, seq_b], port=8080)   # MeshSequence objects (meshseq.io)
    print(viewer.url)
    ...                                          # the page plays until
    viewer.stop()

``meshseq view SEQ [SEQ2 ...]`` does the same from the command line and runs until Ctrl-C.
"""

from __future__ import annotations

import errno
import socket
import threading
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from meshseq.errors import MeshseqError
from meshseq.render import check_same_connectivity, frame_camera, up_vector

#: Colours of the sequences, in order (RGB 0-255).
PALETTE = ((150, 165, 185), (214, 140, 100), (120, 175, 130), (175, 135, 190), (200, 180, 100))


@dataclass(frozen=True)
class ViewItem:
    """One sequence to show: ``vertices (T, V, 3)``, ``faces (F, 3)``, a label."""

    vertices: np.ndarray
    faces: np.ndarray
    name: str


def _as_item(seq) -> ViewItem:
    if isinstance(seq, ViewItem):
        return seq
    return ViewItem(np.asarray(seq.vertices, dtype=np.float64), np.asarray(seq.faces), str(seq.name))


def check_port_free(host: str, port: int) -> None:
    """Raise MeshseqError when ``host:port`` cannot be bound (in use, or not allowed)."""
    if not 0 < int(port) < 65536:
        raise MeshseqError(f"--port {port}: must be between 1 and 65535")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        # As the server will: reuse a port whose old connections linger in TIME_WAIT, but not
        # one that something is listening on.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, int(port)))
        except OSError as err:
            if err.errno == errno.EADDRINUSE:
                raise MeshseqError(f"--port {port}: {host}:{port} is already in use; choose another port") from None
            raise MeshseqError(f"--port {port}: cannot listen on {host}:{port} ({err.strerror})") from None


def side_by_side_offsets(items: Sequence[ViewItem], direction: np.ndarray, gap: float = 0.15) -> np.ndarray:
    """Offsets ``(N, 3)`` that place the sequences next to each other along ``direction`` (unit
    vector), each sequence's whole motion in its own slab, ``gap`` (a fraction of the widest
    slab) apart; the first sequence stays in place."""
    lo = np.array([float((it.vertices @ direction).min()) for it in items])
    hi = np.array([float((it.vertices @ direction).max()) for it in items])
    widths = hi - lo
    space = gap * float(widths.max())
    starts = lo[0] + np.concatenate([[0.0], np.cumsum(widths[:-1] + space)])
    shift = starts - lo  # the first sequence stays where it is
    return shift[:, None] * direction[None, :]


class Viewer:
    """A running viser server showing ``sequences`` side by side.

    ``sequences``: objects with ``vertices (T, V, 3)``, ``faces (F, 3)`` and ``name``
    (:class:`meshseq.io.MeshSequence` or :class:`ViewItem`); all must share one connectivity.
    ``port`` on ``host`` (127.0.0.1) must be free (MeshseqError otherwise). Playback starts at
    ``fps`` frames per second, playing unless ``playing=False``.
    """

    def __init__(
        self,
        sequences: Sequence,
        *,
        port: int = 8080,
        host: str = "127.0.0.1",
        fps: float = 24.0,
        up: str = "y",
        playing: bool = True,
    ) -> None:
        items = [_as_item(s) for s in sequences]
        if not items:
            raise MeshseqError("nothing to view: no sequence given")
        check_same_connectivity(items)
        if not fps > 0:
            raise MeshseqError(f"--fps {fps}: must be positive")
        upv = up_vector(up)  # validates --up before anything starts
        check_port_free(host, port)

        import viser

        camera = frame_camera([it.vertices for it in items], up=up)
        right = camera.pose[:3, 0]
        offsets = side_by_side_offsets(items, right)
        self._items = items
        self._placed = [(it.vertices + off).astype(np.float32) for it, off in zip(items, offsets)]
        self.n_frames = max(it.vertices.shape[0] for it in items)
        self._stop = threading.Event()
        self._lock = threading.Lock()

        server = viser.ViserServer(host=host, port=port, verbose=False)
        if server.get_port() != port:  # lost a race for the port after our check
            server.stop()
            raise MeshseqError(f"--port {port}: {host}:{port} is already in use; choose another port")
        self.server = server
        self.host, self.port = host, port
        sign = "-" if up.startswith("-") else "+"
        server.scene.set_up_direction(f"{sign}{up.lstrip('+-').lower()}")

        # Frame for a squarish window (the browser's shape is unknown) with room to spare.
        framed = frame_camera(self._placed, up=up, max_aspect=1.0, yfov_degrees=45.0, margin=0.12,
                              view_from=camera.pose[:3, 2])
        server.initial_camera.position = tuple(float(x) for x in framed.pose[:3, 3])
        server.initial_camera.look_at = tuple(float(x) for x in framed.target)
        server.initial_camera.fov = float(framed.yfov)

        self._meshes = []
        for i, (it, verts) in enumerate(zip(items, self._placed)):
            handle = server.scene.add_mesh_simple(
                f"/seq{i}",
                verts[0],
                np.asarray(it.faces, dtype=np.uint32),
                color=PALETTE[i % len(PALETTE)],
                side="double",
            )
            self._meshes.append(handle)
            top = verts.reshape(-1, 3) @ upv
            label_pos = verts[0].mean(axis=0) + upv * (float(top.max()) - float(verts[0].mean(axis=0) @ upv))
            server.scene.add_label(f"/seq{i}_label", it.name, position=tuple(float(x) for x in label_pos),
                                   anchor="bottom-center")

        with server.gui.add_folder("Playback"):
            self.play_button = server.gui.add_button("Pause" if playing else "Play", icon=None)
            self.frame_slider = server.gui.add_slider(
                "Frame", min=0, max=max(self.n_frames - 1, 1), step=1, initial_value=0,
                disabled=self.n_frames < 2,
            )
            self.fps_slider = server.gui.add_slider("FPS", min=1, max=60, step=1, initial_value=int(round(min(fps, 60))))
        self.playing = playing and self.n_frames > 1

        @self.play_button.on_click
        def _(_event) -> None:
            self.set_playing(not self.playing)

        @self.frame_slider.on_update
        def _(_event) -> None:
            self._show(int(self.frame_slider.value))

        self._thread = threading.Thread(target=self._play_loop, name="meshseq-viewer-playback", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    def set_playing(self, playing: bool) -> None:
        """Start or pause playback (what the Play/Pause button does)."""
        self.playing = bool(playing) and self.n_frames > 1
        self.play_button.label = "Pause" if self.playing else "Play"

    def set_frame(self, t: int) -> None:
        """Show frame ``t`` (what the slider does); a shorter sequence holds its last frame."""
        self.frame_slider.value = int(t) % max(self.n_frames, 1)

    def _show(self, t: int) -> None:
        with self._lock:
            for handle, verts in zip(self._meshes, self._placed):
                handle.vertices = verts[min(t, verts.shape[0] - 1)]

    def _play_loop(self) -> None:
        while not self._stop.wait(1.0 / max(float(self.fps_slider.value), 1.0)):
            if self.playing:
                self.set_frame((int(self.frame_slider.value) + 1) % self.n_frames)

    def stop(self) -> None:
        """Stop playback and the server (the port is free again afterwards)."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.server.stop()

    def __enter__(self) -> "Viewer":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
