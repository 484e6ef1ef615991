"""Offscreen rendering of mesh sequences: shaded frames, labelled film strips, GIF/MP4, error heat maps.

Everything up to the writers is pure: vertices ``(T, V, 3)`` and faces ``(F, 3)`` in, ``uint8``
RGB images out (``(H, W, 3)`` for a still, ``(N, H, W, 3)`` for an animation). No display or
GPU is needed: frames are drawn with pyrender on EGL (Mesa's llvmpipe on a machine without a GPU)
and, where EGL is missing, with a slower matplotlib painter's-algorithm renderer (a
``MeshseqWarning`` says so). Both use the same :class:`Camera`, so a picture frames the same
way whichever drew it.

A camera is fixed for a whole picture: :func:`frame_camera` frames every frame of every
sequence shown, so motion reads as motion and sequences side by side share one scale.
Only :func:`save_image` and :func:`save_animation` touch files (atomically, never overwriting
without ``force``).
"""

from __future__ import annotations

import math
import os
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from meshseq.errors import MeshseqError, MeshseqWarning
from meshseq.mesh import vertex_normals

#: Background of every tile (white), RGB 0-255.
BACKGROUND = (255, 255, 255)
#: Base colour of a mesh without per-vertex colours (a light clay grey), RGB 0-1.
MESH_COLOR = (0.60, 0.65, 0.72)
#: Colour map of error heat maps.
ERROR_CMAP = "inferno"
#: Image formats the writers know.
IMAGE_SUFFIXES = (".png",)
ANIMATION_SUFFIXES = (".gif", ".mp4")
#: Most columns a film strip may have (beyond this, pick a larger ``every``).
MAX_COLUMNS = 48

_AXES = {"x": 0, "y": 1, "z": 2}


# ----------------------------------------------------------------------------------------------
# Camera


@dataclass(frozen=True)
class Camera:
    """A perspective pinhole camera and the image size it renders.

    ``pose`` is the ``(4, 4)`` camera-to-world transform in OpenGL convention (the camera looks
    down its local -z axis with +y up); ``yfov`` is the vertical field of view in radians.
    """

    pose: np.ndarray
    yfov: float
    width: int
    height: int
    znear: float
    zfar: float
    target: np.ndarray | None = None  # the point the camera looks at (framed centre), (3,)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates ``(..., 2)`` (x right, y down, pixel centres at +0.5) and depth
        ``(...)`` (distance along the viewing axis, positive in front) of ``points (..., 3)``."""
        p = np.asarray(points, dtype=np.float64)
        rot, t = self.pose[:3, :3], self.pose[:3, 3]
        pc = (p - t) @ rot  # camera coordinates, = R^T (p - t)
        depth = -pc[..., 2]
        f = 1.0 / math.tan(self.yfov / 2.0)
        safe = np.where(np.abs(depth) < 1e-12, 1e-12, depth)
        x = 0.5 * self.width + 0.5 * self.height * f * pc[..., 0] / safe
        y = 0.5 * self.height - 0.5 * self.height * f * pc[..., 1] / safe
        return np.stack([x, y], axis=-1), depth


def up_vector(up: str) -> np.ndarray:
    """Unit vector of an axis name: ``"x"``, ``"y"``, ``"z"``, optionally with a ``-`` sign."""
    sign = -1.0 if up.startswith("-") else 1.0
    axis = up.lstrip("+-").lower()
    if axis not in _AXES:
        raise MeshseqError(f"--up {up!r}: expected one of x, y, z, -x, -y, -z")
    vec = np.zeros(3)
    vec[_AXES[axis]] = sign
    return vec


def frame_camera(
    points: np.ndarray | Sequence[np.ndarray],
    *,
    up: str = "y",
    azimuth: float = 30.0,
    elevation: float = 15.0,
    height: int = 240,
    yfov_degrees: float = 30.0,
    margin: float = 0.05,
    max_aspect: float = 3.0,
    view_from: np.ndarray | None = None,
) -> Camera:
    """A camera that frames all of ``points`` (any arrays ``(..., 3)``: whole sequences).

    The view is a side view: the camera looks across the narrower horizontal principal axis of
    the points (so a walking animal or person is seen from the side), turned by ``azimuth``
    degrees about ``up`` and raised by ``elevation`` degrees. The image is ``height`` pixels
    tall and as wide as the framed points need (aspect clamped to ``[1/2, max_aspect]``, width
    even); the distance is the smallest that keeps every point inside the image with ``margin``
    (a fraction of the half-size) to spare. ``view_from`` (a direction from the points towards
    the camera, not parallel to ``up``) replaces the automatic side view and the two angles.
    """
    if isinstance(points, np.ndarray):
        pts = points.reshape(-1, 3).astype(np.float64)
    else:
        pts = np.concatenate([np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in points])
    if pts.shape[0] == 0 or not np.all(np.isfinite(pts)):
        raise MeshseqError("cannot frame a camera: the vertices are empty or not finite")
    upv = up_vector(up)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre = 0.5 * (lo + hi)
    # Horizontal principal axes (the plane orthogonal to up).
    helper = np.eye(3)[np.argmin(np.abs(upv))]
    h1 = np.cross(upv, helper)
    h1 /= np.linalg.norm(h1)
    h2 = np.cross(upv, h1)
    rel = pts - centre
    hc = np.stack([rel @ h1, rel @ h2], axis=1)
    cov = hc.T @ hc
    evals, evecs = np.linalg.eigh(cov)
    minor = evecs[:, 0]  # smallest spread: look along it for a side view
    minor = minor if minor[np.argmax(np.abs(minor))] >= 0 else -minor
    side = minor[0] * h1 + minor[1] * h2
    az, el = math.radians(azimuth), math.radians(elevation)
    along = np.cross(upv, side)  # the other horizontal direction
    back = math.cos(el) * (math.cos(az) * side + math.sin(az) * along) + math.sin(el) * upv
    if view_from is not None:
        back = np.asarray(view_from, dtype=np.float64)
        if abs(back @ upv) > 0.999 * np.linalg.norm(back):
            raise MeshseqError("view direction must not be parallel to the up axis")
    back /= np.linalg.norm(back)
    right = np.cross(upv, back)
    right /= np.linalg.norm(right)
    cam_up = np.cross(back, right)

    x, y = rel @ right, rel @ cam_up
    cx, cy = 0.5 * (x.min() + x.max()), 0.5 * (y.min() + y.max())
    centre = centre + cx * right + cy * cam_up
    rel = pts - centre
    x, y, z = rel @ right, rel @ cam_up, rel @ back
    extent_x, extent_y = float(np.ptp(x)), float(np.ptp(y))
    scale = max(extent_x, extent_y, 1e-12)
    aspect = np.clip((extent_x + 0.02 * scale) / (extent_y + 0.02 * scale), 0.5, max_aspect)
    height = int(height)
    width = int(2 * round(height * aspect / 2))
    yfov = math.radians(yfov_degrees)
    tan_y = math.tan(yfov / 2.0) * (1.0 - margin)
    tan_x = tan_y * width / height
    dist = float(np.max(np.maximum(z + np.abs(x) / tan_x, z + np.abs(y) / tan_y)))
    dist = max(dist, float(z.max()) + 1e-3 * scale)
    nearest, farthest = dist - float(z.max()), dist - float(z.min())
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = right, cam_up, back
    pose[:3, 3] = centre + dist * back
    return Camera(
        pose=pose,
        yfov=yfov,
        width=width,
        height=height,
        znear=max(0.5 * nearest, 1e-4 * scale),
        zfar=2.0 * farthest + scale,
        target=centre,
    )


# ----------------------------------------------------------------------------------------------
# Colours


def vertex_errors(vertices: np.ndarray, ground_truth: np.ndarray) -> np.ndarray:
    """Per-vertex Euclidean distance ``(T, V)`` between ``vertices (T, V, 3)`` and the first
    ``T`` frames of ``ground_truth (T', V, 3)``, ``T' >= T``."""
    v = np.asarray(vertices, dtype=np.float64)
    g = np.asarray(ground_truth, dtype=np.float64)[: v.shape[0]]
    return np.linalg.norm(v - g, axis=-1)


def error_colormap(cmap: str = ERROR_CMAP):
    """The matplotlib colour map of heat maps: ``cmap`` without its darkest eighth, so a
    zero-error surface still shows its shading."""
    from matplotlib import colormaps
    from matplotlib.colors import ListedColormap

    return ListedColormap(colormaps[cmap](np.linspace(0.12, 1.0, 256)), name=f"{cmap}_error")


def error_colors(errors: np.ndarray, vmax: float, cmap: str = ERROR_CMAP) -> np.ndarray:
    """RGB colours ``(..., 3)`` in [0, 1] of ``errors (...)`` on :func:`error_colormap` from 0
    to ``vmax`` (values above ``vmax`` get the top colour)."""
    norm = np.clip(np.asarray(errors, dtype=np.float64) / max(float(vmax), 1e-300), 0.0, 1.0)
    return error_colormap(cmap)(norm)[..., :3]


# ----------------------------------------------------------------------------------------------
# Frame renderers

_EGL_STATE: dict[str, object] = {}


def egl_available() -> tuple[bool, str]:
    """Whether pyrender can render offscreen here (EGL), and why not if it cannot."""
    if "ok" not in _EGL_STATE:
        if "OpenGL" not in sys.modules:
            os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
        try:
            import pyrender

            renderer = pyrender.OffscreenRenderer(8, 8)
            renderer.delete()
            _EGL_STATE["ok"], _EGL_STATE["why"] = True, ""
        except Exception as err:  # noqa: BLE001 - any failure means: use the fallback
            msg = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            _EGL_STATE["ok"], _EGL_STATE["why"] = False, msg
    return bool(_EGL_STATE["ok"]), str(_EGL_STATE["why"])


def _pick_backend(backend: str) -> str:
    if backend not in ("auto", "pyrender", "matplotlib"):
        raise MeshseqError(f"renderer {backend!r}: expected auto, pyrender or matplotlib")
    if backend == "matplotlib":
        return backend
    ok, why = egl_available()
    if ok:
        return "pyrender"
    if backend == "pyrender":
        raise MeshseqError(f"renderer pyrender: offscreen OpenGL (EGL) is not available here ({why})")
    warnings.warn(
        f"offscreen OpenGL (EGL) is not available ({why}); rendering with the slower matplotlib "
        "renderer (install libegl1 and libgl1-mesa-dri for pyrender)",
        MeshseqWarning,
        stacklevel=3,
    )
    return "matplotlib"


def _light_dirs(camera: Camera) -> list[tuple[np.ndarray, float]]:
    """World directions the light travels in, with intensities: a key light from the camera's
    upper left and a weaker fill from its right."""
    rot = camera.pose[:3, :3]
    key = rot @ np.array([0.45, -0.55, -1.0])
    fill = rot @ np.array([-0.6, 0.1, -1.0])
    return [(key / np.linalg.norm(key), 1.0), (fill / np.linalg.norm(fill), 0.35)]


def _rotation_to(direction: np.ndarray) -> np.ndarray:
    """A ``(4, 4)`` pose whose -z axis points along ``direction`` (pyrender's light direction)."""
    z = -direction / np.linalg.norm(direction)
    helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = x, y, z
    return pose


def _render_pyrender(vertices, faces, colors, camera: Camera) -> np.ndarray:
    import pyrender

    scene = pyrender.Scene(bg_color=np.array(BACKGROUND + (255,)) / 255.0, ambient_light=(0.12,) * 3)
    cam = pyrender.PerspectiveCamera(
        yfov=camera.yfov, aspectRatio=camera.width / camera.height, znear=camera.znear, zfar=camera.zfar
    )
    scene.add(cam, pose=camera.pose)
    for direction, strength in _light_dirs(camera):
        scene.add(pyrender.DirectionalLight(color=np.ones(3), intensity=2.2 * strength), pose=_rotation_to(direction))
    material = pyrender.MetallicRoughnessMaterial(
        baseColorFactor=(1.0, 1.0, 1.0, 1.0), metallicFactor=0.0, roughnessFactor=0.75, doubleSided=True
    )
    faces32 = np.ascontiguousarray(faces, dtype=np.uint32)
    renderer = pyrender.OffscreenRenderer(camera.width, camera.height)
    out = np.empty((vertices.shape[0], camera.height, camera.width, 3), dtype=np.uint8)
    try:
        for t in range(vertices.shape[0]):
            prim = pyrender.Primitive(
                positions=vertices[t].astype(np.float32),
                normals=vertex_normals(vertices[t], faces).astype(np.float32),
                color_0=np.concatenate([colors[t], np.ones((colors.shape[1], 1))], axis=1).astype(np.float32),
                indices=faces32,
                material=material,
            )
            node = scene.add(pyrender.Mesh([prim]))
            color, _ = renderer.render(scene)
            out[t] = color[..., :3]
            scene.remove_node(node)
    finally:
        renderer.delete()
    return out


def _render_matplotlib(vertices, faces, colors, camera: Camera) -> np.ndarray:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import PolyCollection
    from matplotlib.figure import Figure

    w, h = camera.width, camera.height
    lights = _light_dirs(camera)
    out = np.empty((vertices.shape[0], h, w, 3), dtype=np.uint8)
    for t in range(vertices.shape[0]):
        v = vertices[t]
        pix, depth = camera.project(v)
        tri = v[faces]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
        shade = np.full(len(faces), 0.32)
        for direction, strength in lights:
            shade += 0.75 * strength * np.abs(fn @ direction)  # two-sided Lambert
        base = colors[t][faces].mean(axis=1)
        rgb = np.clip(base * shade[:, None], 0.0, 1.0)
        fdepth = depth[faces].mean(axis=1)
        keep = np.all(depth[faces] > camera.znear, axis=1)
        order = np.argsort(-fdepth[keep], kind="stable")  # far first: painter's algorithm
        polys = pix[faces][keep][order]
        rgb = rgb[keep][order]
        fig = Figure(figsize=(w / 100.0, h / 100.0), dpi=100)
        canvas = FigureCanvasAgg(fig)
        ax = fig.add_axes((0, 0, 1, 1))
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.axis("off")
        fig.patch.set_facecolor(np.array(BACKGROUND) / 255.0)
        ax.add_collection(PolyCollection(polys, facecolors=rgb, edgecolors=rgb, linewidths=0.25))
        canvas.draw()
        img = np.asarray(canvas.buffer_rgba())[..., :3]
        out[t] = img[:h, :w]
    return out


def render_frames(
    vertices: np.ndarray,
    faces: np.ndarray,
    camera: Camera,
    *,
    vertex_colors: np.ndarray | None = None,
    backend: str = "auto",
) -> np.ndarray:
    """Shaded images ``(T, H, W, 3)`` uint8 of ``vertices (T, V, 3)`` with ``faces (F, 3)``.

    ``vertex_colors``: RGB in [0, 1], ``(V, 3)`` or ``(T, V, 3)``; default a uniform clay grey.
    ``backend``: ``"auto"`` (pyrender on EGL, else matplotlib with a warning), ``"pyrender"``
    or ``"matplotlib"``.
    """
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim == 2:
        v = v[None]
    f = np.asarray(faces, dtype=np.int64)
    if vertex_colors is None:
        colors = np.broadcast_to(np.asarray(MESH_COLOR), v.shape)
    else:
        colors = np.broadcast_to(np.asarray(vertex_colors, dtype=np.float64), v.shape)
    if _pick_backend(backend) == "pyrender":
        return _render_pyrender(v, f, colors, camera)
    return _render_matplotlib(v, f, colors, camera)


# ----------------------------------------------------------------------------------------------
# Layout: labels, colour bar, tiles


@dataclass(frozen=True)
class ColorBar:
    """A colour bar beside a picture: ``cmap`` from 0 to ``vmax``, titled ``label``."""

    vmax: float
    label: str = "per-vertex error"
    cmap: str = ERROR_CMAP


def _text_width(text: str, fontsize_px: float) -> int:
    return int(math.ceil(0.62 * fontsize_px * len(text)))


def layout_canvas(
    n_rows: int,
    n_cols: int,
    tile_width: int,
    tile_height: int,
    *,
    row_labels: Sequence[str] | None = None,
    col_labels: Sequence[str] | None = None,
    title: str | None = None,
    colorbar: ColorBar | None = None,
    header_px: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """A white canvas ``(H, W, 3)`` uint8 with labels, title and colour bar drawn, and the
    top-left pixel ``(row, col)`` of each tile slot, ``(n_rows, n_cols, 2)`` int.

    ``header_px`` reserves a blank band at the top (for a frame counter drawn later).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    font_px = 15.0  # 11 pt at 100 dpi
    pad, gap = 10, 4
    left = pad
    if row_labels:
        left = pad + min(max(_text_width(s, font_px) for s in row_labels), 260) + 10
    top = pad + header_px
    if title:
        top += 28
    if col_labels:
        top += 22
    right = pad + (105 if colorbar is not None else 0)
    width = left + n_cols * tile_width + (n_cols - 1) * gap + right
    height = top + n_rows * tile_height + (n_rows - 1) * gap + pad
    slots = np.zeros((n_rows, n_cols, 2), dtype=np.int64)
    slots[..., 0] = top + np.arange(n_rows)[:, None] * (tile_height + gap)
    slots[..., 1] = left + np.arange(n_cols)[None, :] * (tile_width + gap)

    fig = Figure(figsize=(width / 100.0, height / 100.0), dpi=100)
    canvas = FigureCanvasAgg(fig)
    fig.patch.set_facecolor(np.array(BACKGROUND) / 255.0)

    def fx(px: float) -> float:
        return px / width

    def fy(py: float) -> float:  # pixel rows count down, figure coordinates up
        return 1.0 - py / height

    if title:
        fig.text(fx(width / 2), fy(pad + header_px + 12), title, ha="center", va="center", fontsize=13)
    if col_labels:
        for c, label in enumerate(col_labels):
            fig.text(fx(slots[0, c, 1] + tile_width / 2), fy(top - 11), label, ha="center", va="center", fontsize=11)
    if row_labels:
        for r, label in enumerate(row_labels):
            fig.text(fx(left - 10), fy(slots[r, 0, 0] + tile_height / 2), label, ha="right", va="center", fontsize=11)
    if colorbar is not None:
        bar_top = top + 6
        bar_h = n_rows * tile_height + (n_rows - 1) * gap - 12
        x0 = width - right + 12
        cax = fig.add_axes((fx(x0), fy(bar_top + bar_h), fx(16), bar_h / height))
        sm = ScalarMappable(norm=Normalize(0.0, colorbar.vmax), cmap=error_colormap(colorbar.cmap))
        cb = fig.colorbar(sm, cax=cax)
        cb.set_label(colorbar.label, fontsize=10)
        cb.ax.tick_params(labelsize=9)
        cb.formatter.set_powerlimits((-2, 3))
        cb.update_ticks()
    canvas.draw()
    img = np.asarray(canvas.buffer_rgba())[..., :3].copy()
    return img[:height, :width], slots


def _paste(canvas: np.ndarray, tile: np.ndarray, at: np.ndarray) -> None:
    r, c = int(at[0]), int(at[1])
    canvas[r : r + tile.shape[0], c : c + tile.shape[1]] = tile


def _draw_text(image: np.ndarray, text: str, xy: tuple[int, int], size: int = 14) -> np.ndarray:
    """``image`` with ``text`` written at pixel ``xy`` (left, top) in dark grey."""
    from PIL import Image, ImageDraw, ImageFont

    pil = Image.fromarray(image)
    try:
        font = ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: fixed bitmap font
        font = ImageFont.load_default()
    ImageDraw.Draw(pil).text(xy, text, fill=(40, 40, 40), font=font)
    return np.asarray(pil)


# ----------------------------------------------------------------------------------------------
# Pictures


def _check_sequences(sequences: Sequence[np.ndarray], faces: np.ndarray, labels: Sequence[str]) -> list[np.ndarray]:
    seqs = [np.asarray(s, dtype=np.float64) for s in sequences]
    if not seqs:
        raise MeshseqError("nothing to render: no sequence given")
    f = np.asarray(faces)
    for s, label in zip(seqs, labels):
        if s.ndim != 3 or s.shape[-1] != 3 or s.shape[0] == 0:
            raise MeshseqError(f"{label}: vertices must be (T, V, 3) with T >= 1, got {s.shape}")
        if f.size and (f.max() >= s.shape[1] or f.min() < 0):
            raise MeshseqError(f"{label}: faces index vertex {int(f.max())} but it has {s.shape[1]} vertices")
        if not np.all(np.isfinite(s)):
            t = int(np.argmax(~np.isfinite(s).reshape(s.shape[0], -1).all(axis=1)))
            raise MeshseqError(f"{label}: frame {t} has non-finite vertex coordinates")
    return seqs


def check_same_connectivity(sequences: Sequence) -> None:
    """MeshseqError unless every sequence (objects with ``vertices (T, V, 3)``, ``faces (F, 3)``
    and ``name``) has the first one's vertex count and faces."""
    first = sequences[0]
    v0, f0 = np.shape(first.vertices)[1], np.asarray(first.faces)
    for seq in sequences[1:]:
        v, f = np.shape(seq.vertices)[1], np.asarray(seq.faces)
        if v != v0 or not np.array_equal(f, f0):
            raise MeshseqError(
                f"{seq.name}: its connectivity ({v} vertices, {len(f)} faces) differs from "
                f"{first.name} ({v0} vertices, {len(f0)} faces); sequences shown together must share one mesh"
            )


def _default_labels(n: int, labels: Sequence[str] | None) -> list[str]:
    if labels is None:
        return [f"sequence {i + 1}" for i in range(n)]
    if len(labels) != n:
        raise MeshseqError(f"{len(labels)} labels given for {n} sequences")
    return list(labels)


def _error_setup(seqs, labels, ground_truth, gt_label):
    """Rows with ground truth first, per-row colours and the colour bar (or no errors)."""
    if ground_truth is None:
        return seqs, labels, [None] * len(seqs), None
    gt = _check_sequences([ground_truth], np.zeros((0, 3), dtype=np.int64), [gt_label])[0]
    errors = []
    for s, label in zip(seqs, labels):
        if s.shape[1] != gt.shape[1]:
            raise MeshseqError(
                f"{label}: {s.shape[1]} vertices, but the ground truth {gt_label} has {gt.shape[1]}"
            )
        if s.shape[0] > gt.shape[0]:
            raise MeshseqError(
                f"{label}: {s.shape[0]} frames, but the ground truth {gt_label} has only {gt.shape[0]}"
            )
        errors.append(vertex_errors(s, gt))
    vmax = max(float(e.max()) for e in errors)
    vmax = vmax if vmax > 0 else 1.0
    colors = [None] + [error_colors(e, vmax) for e in errors]
    return [gt] + seqs, [gt_label] + list(labels), colors, ColorBar(vmax=vmax)


def film_strip(
    sequences: Sequence[np.ndarray],
    faces: np.ndarray,
    *,
    labels: Sequence[str] | None = None,
    every: int | None = None,
    max_columns: int = 8,
    ground_truth: np.ndarray | None = None,
    ground_truth_label: str = "ground truth",
    camera: Camera | None = None,
    tile_height: int = 200,
    up: str = "y",
    title: str | None = None,
    first_frame: int = 0,
    backend: str = "auto",
) -> np.ndarray:
    """A labelled film strip ``(H, W, 3)`` uint8: one row per sequence, one column per shown frame.

    ``sequences``: vertices ``(T_i, V, 3)`` sharing ``faces (F, 3)``; the columns are frames
    ``0, every, 2 every, ...`` of the longest (a shorter sequence leaves its tail blank);
    ``every`` defaults to the step that shows at most ``max_columns`` frames. With
    ``ground_truth (T', V, 3)`` (``T' >= T_i``), its row comes first and every other row is
    coloured by its per-vertex distance to it, with a colour bar. ``camera`` defaults to
    :func:`frame_camera` of all rows. ``first_frame``: the number the column labels give
    frame 0 (when the sequences are a window of longer ones).
    """
    labels = _default_labels(len(sequences), labels)
    seqs = _check_sequences(sequences, faces, labels)
    rows, row_labels, colors, colorbar = _error_setup(seqs, labels, ground_truth, ground_truth_label)
    n_frames = max(s.shape[0] for s in rows)
    if every is None:
        every = max(1, math.ceil(n_frames / max_columns))
    if every < 1:
        raise MeshseqError(f"--every {every}: must be at least 1")
    frames = np.arange(0, n_frames, every)
    if len(frames) > MAX_COLUMNS:
        raise MeshseqError(
            f"--every {every} gives {len(frames)} columns (at most {MAX_COLUMNS}); use --every "
            f"{math.ceil(n_frames / MAX_COLUMNS)} or more"
        )
    if camera is None:
        camera = frame_camera(rows, up=up, height=tile_height)
    canvas, slots = layout_canvas(
        len(rows),
        len(frames),
        camera.width,
        camera.height,
        row_labels=row_labels,
        col_labels=[f"frame {t + first_frame}" for t in frames],
        title=title,
        colorbar=colorbar,
    )
    for r, (s, col) in enumerate(zip(rows, colors)):
        shown = frames[frames < s.shape[0]]
        tiles = render_frames(
            s[shown], faces, camera, vertex_colors=None if col is None else col[shown], backend=backend
        )
        for c, tile in enumerate(tiles):
            _paste(canvas, tile, slots[r, c])
    return canvas


def animation_frames(
    sequences: Sequence[np.ndarray],
    faces: np.ndarray,
    *,
    labels: Sequence[str] | None = None,
    every: int = 1,
    ground_truth: np.ndarray | None = None,
    ground_truth_label: str = "ground truth",
    camera: Camera | None = None,
    tile_height: int = 240,
    up: str = "y",
    first_frame: int = 0,
    backend: str = "auto",
) -> np.ndarray:
    """Frames ``(N, H, W, 3)`` uint8 of an animation: the sequences side by side, labelled, with a
    frame counter; frames ``0, every, ...`` of the longest (a shorter one holds its last frame).
    ``ground_truth`` and ``first_frame`` as in :func:`film_strip` (the ground truth shown
    first, the others as error heat maps)."""
    labels = _default_labels(len(sequences), labels)
    seqs = _check_sequences(sequences, faces, labels)
    if every < 1:
        raise MeshseqError(f"--every {every}: must be at least 1")
    cols, col_labels, colors, colorbar = _error_setup(seqs, labels, ground_truth, ground_truth_label)
    n_frames = max(s.shape[0] for s in cols)
    frames = np.arange(0, n_frames, every)
    if camera is None:
        camera = frame_camera(cols, up=up, height=tile_height)
    canvas, slots = layout_canvas(
        1, len(cols), camera.width, camera.height, col_labels=col_labels, colorbar=colorbar, header_px=20
    )
    out = np.broadcast_to(canvas, (len(frames),) + canvas.shape).copy()
    for c, (s, col) in enumerate(zip(cols, colors)):
        idx = np.minimum(frames, s.shape[0] - 1)
        tiles = render_frames(s[idx], faces, camera, vertex_colors=None if col is None else col[idx], backend=backend)
        for n, tile in enumerate(tiles):
            _paste(out[n], tile, slots[0, c])
    for n, t in enumerate(frames):
        out[n] = _draw_text(out[n], f"frame {t + first_frame} / {n_frames - 1 + first_frame}", (10, 8))
    return out


# ----------------------------------------------------------------------------------------------
# Writers (the only functions here that touch files)


def check_output_suffix(path: str | os.PathLike, allowed: Sequence[str]) -> str:
    """The lower-case suffix of ``path`` if it is one of ``allowed``, else a MeshseqError."""
    suffix = Path(path).suffix.lower()
    if suffix not in allowed:
        raise MeshseqError(f"{path}: unknown output extension {suffix or '(none)'!r}; expected one of {', '.join(allowed)}")
    return suffix


def save_image(path: str | os.PathLike, image: np.ndarray, *, force: bool = False) -> Path:
    """Write ``image (H, W, 3)`` uint8 to a PNG at ``path`` atomically; returns the path."""
    from PIL import Image

    from meshseq.io import atomic_output

    check_output_suffix(path, IMAGE_SUFFIXES)
    with atomic_output(path, force=force) as tmp:
        Image.fromarray(np.ascontiguousarray(image)).save(tmp, format="PNG", optimize=True)
    return Path(path)


def save_animation(path: str | os.PathLike, frames: np.ndarray, *, fps: float = 24.0, force: bool = False) -> Path:
    """Write ``frames (N, H, W, 3)`` uint8 as a looping GIF or an H.264 MP4 (by ``path``'s
    extension) atomically; returns the path."""
    from meshseq.io import atomic_output

    suffix = check_output_suffix(path, ANIMATION_SUFFIXES)
    if not fps > 0:
        raise MeshseqError(f"--fps {fps}: must be positive")
    frames = np.ascontiguousarray(frames, dtype=np.uint8)
    with atomic_output(path, force=force) as tmp:
        if suffix == ".gif":
            from PIL import Image

            images = [Image.fromarray(f) for f in frames]
            images[0].save(
                tmp,
                format="GIF",
                save_all=True,
                append_images=images[1:],
                duration=max(int(round(1000.0 / fps)), 20),
                loop=0,
                optimize=False,
            )
        else:
            import imageio.v2 as imageio

            pad_h, pad_w = frames.shape[1] % 2, frames.shape[2] % 2  # yuv420p needs even sizes
            if pad_h or pad_w:
                frames = np.pad(frames, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), constant_values=255)
            writer = imageio.get_writer(
                str(tmp), format="FFMPEG", mode="I", fps=fps, codec="libx264",
                pixelformat="yuv420p", macro_block_size=2, quality=8,
                output_params=["-movflags", "+faststart"],
            )  # fmt: skip
            try:
                for f in frames:
                    writer.append_data(f)
            finally:
                writer.close()
    return Path(path)
