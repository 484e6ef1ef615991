"""MDD and PC2 point caches: per-frame vertex positions, without faces.

Both formats hold only positions ``(T, V, 3)`` (float32 in the file); the faces come from a base
mesh with the same vertices in the same order (an OBJ/PLY/OFF file, see
:func:`meshseq.formats.load_cache`).

* **MDD** (LightWave, Blender's ``io_shape_mdd``, Houdini, Maya plug-ins), big-endian::

      int32 frames, int32 points, float32 times[frames]  (seconds),
      float32 xyz[frames][points][3]

* **PC2** (3ds Max point cache 2, Blender's ``io_export_pc2``), little-endian::

      char[12] "POINTCACHE2\\0", int32 version (1), int32 points, float32 start_frame,
      float32 sample_rate (frames per sample), int32 samples,
      float32 xyz[samples][points][3]

Readers check the header against the file size (a truncated file is a one-line
:class:`MeshseqError`); writers build the whole file in memory and write it atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from meshseq.errors import MeshseqError

PC2_MAGIC = b"POINTCACHE2\0"
_PC2_HEADER = np.dtype([("magic", "S12"), ("version", "<i4"), ("points", "<i4"), ("start", "<f4"),
                        ("rate", "<f4"), ("samples", "<i4")])


def _read(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise MeshseqError(f"{path}: cannot read ({type(exc).__name__}: {exc.strerror or exc})") from None


def fps_from_times(times: np.ndarray) -> float | None:
    """Frames per second of evenly spaced ``times (T,)`` in seconds (None if T < 2 or uneven).

    Files store times as float32, so the rate is rounded to the fewest decimals (0 to 6) whose
    times ``t0 + k / fps`` agree with the stored ones to float32 precision: float32 ``k / 24``
    gives exactly 24 and ``k / 12.5`` exactly 12.5.
    """
    times = np.asarray(times, dtype=np.float64)
    if len(times) < 2:
        return None
    steps = np.diff(times)
    step = (times[-1] - times[0]) / (len(times) - 1)
    if not step > 0 or np.abs(steps - step).max() > 1e-4 * step + 1e-6:
        return None
    fps = 1.0 / step
    k = np.arange(len(times))
    tol = 4 * np.finfo(np.float32).eps * max(np.abs(times).max(), step)
    for decimals in range(7):
        candidate = round(fps, decimals)
        if candidate > 0 and np.abs(times[0] + k / candidate - times).max() <= tol:
            return float(candidate)
    return fps


def read_mdd(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read an MDD file.

    Returns:
        ``(vertices, times)``: vertices ``(T, V, 3)`` float64 (exactly the file's float32
        values), times ``(T,)`` float64 seconds.
    """
    path = Path(path)
    data = _read(path)
    if len(data) < 8:
        raise MeshseqError(f"{path}: MDD file too short for its header ({len(data)} bytes); truncated file?")
    n_frames, n_points = (int(x) for x in np.frombuffer(data, ">i4", 2))
    if n_frames < 1 or n_points < 1:
        raise MeshseqError(f"{path}: MDD header says {n_frames} frames of {n_points} points; not an MDD file?")
    _check_size(path, "MDD", data, 8 + 4 * n_frames + 12 * n_frames * n_points,
                f"{n_frames} frames of {n_points} points", "; not an MDD file?")
    times = np.frombuffer(data, ">f4", n_frames, offset=8).astype(np.float64)
    vertices = np.frombuffer(data, ">f4", 3 * n_frames * n_points, offset=8 + 4 * n_frames)
    return vertices.reshape(n_frames, n_points, 3).astype(np.float64), times


def _check_size(path: Path, kind: str, data: bytes, expected: int, contents: str, extra_hint: str = "") -> None:
    """One-line error unless a cache file is exactly the ``expected`` bytes its header promises."""
    if len(data) < expected:
        raise MeshseqError(f"{path}: {kind} header promises {contents} ({expected} bytes) but the file has "
                           f"{len(data)} bytes; truncated file?")
    if len(data) > expected:
        raise MeshseqError(f"{path}: {kind} file has {len(data) - expected} bytes more than its header "
                           f"({contents}) describes{extra_hint}")


def mdd_bytes(vertices: np.ndarray, fps: float) -> bytes:
    """MDD file content of ``vertices (T, V, 3)`` (stored as float32) with times ``t / fps``."""
    v = np.asarray(vertices)
    if v.ndim != 3 or v.shape[2] != 3:
        raise MeshseqError(f"MDD: vertices must have shape (T, V, 3), got {v.shape}")
    if not (np.isfinite(fps) and fps > 0):
        raise MeshseqError(f"--fps {fps}: must be a positive number")
    n_frames, n_points = v.shape[:2]
    times = (np.arange(n_frames, dtype=np.float64) / fps).astype(">f4")
    return (np.array([n_frames, n_points], ">i4").tobytes() + times.tobytes()
            + np.ascontiguousarray(v, dtype=">f4").tobytes())


def read_pc2(path: str | os.PathLike) -> tuple[np.ndarray, float, float]:
    """Read a PC2 file.

    Returns:
        ``(vertices, start_frame, sample_rate)``: vertices ``(T, V, 3)`` float64 (exactly the
        file's float32 values); the first sample's frame number and the frames between samples.
    """
    path = Path(path)
    data = _read(path)
    if len(data) < _PC2_HEADER.itemsize:
        raise MeshseqError(f"{path}: PC2 file too short for its header ({len(data)} bytes); truncated file?")
    head = np.frombuffer(data, _PC2_HEADER, 1)[0]
    if bytes(head["magic"]).rstrip(b"\0") != PC2_MAGIC.rstrip(b"\0"):
        raise MeshseqError(f"{path}: not a PC2 file (it does not start with 'POINTCACHE2')")
    n_points, n_samples = int(head["points"]), int(head["samples"])
    if n_points < 1 or n_samples < 1:
        raise MeshseqError(f"{path}: PC2 header says {n_samples} samples of {n_points} points")
    _check_size(path, "PC2", data, _PC2_HEADER.itemsize + 12 * n_points * n_samples,
                f"{n_samples} samples of {n_points} points")
    vertices = np.frombuffer(data, "<f4", 3 * n_points * n_samples, offset=_PC2_HEADER.itemsize)
    return (vertices.reshape(n_samples, n_points, 3).astype(np.float64), float(head["start"]),
            float(head["rate"]))


def pc2_bytes(vertices: np.ndarray, *, start_frame: float = 0.0, sample_rate: float = 1.0) -> bytes:
    """PC2 file content of ``vertices (T, V, 3)`` (stored as float32), version 1."""
    v = np.asarray(vertices)
    if v.ndim != 3 or v.shape[2] != 3:
        raise MeshseqError(f"PC2: vertices must have shape (T, V, 3), got {v.shape}")
    head = np.zeros(1, _PC2_HEADER)
    head[0] = (PC2_MAGIC, 1, v.shape[1], start_frame, sample_rate, v.shape[0])
    return head.tobytes() + np.ascontiguousarray(v, dtype="<f4").tobytes()
