"""USD (.usd / .usda / .usdc) mesh sequences through Pixar's ``usd-core`` (``pip install
'meshseq[usd]'``).

Reading: a ``UsdGeom.Mesh`` whose ``points`` attribute has time samples; every time sample is a
frame (``(T, V, 3)``, in the mesh's own coordinates: its transforms are not applied), faces from
``faceVertexCounts`` / ``faceVertexIndices`` (polygons fanned into triangles; a ``leftHanded``
mesh has its triangles reversed). ``fps`` is the stage's ``timeCodesPerSecond`` times the
spacing of the samples. Address a mesh as ``stage.usda:/World/Body`` when a stage holds several.

Writing: one ``Mesh`` prim ``/<name>`` (the stage's default prim) with ``points`` and ``extent``
sampled at time codes ``0 .. T-1``, ``timeCodesPerSecond`` = ``framesPerSecond`` = the
sequence's fps, the stage's ``upAxis`` (Y or Z) and ``metersPerUnit`` stated, and
``subdivisionScheme = "none"`` (the triangles are the surface). Points are float32 (USD's
``point3f[]``), so a round trip returns the float32 values of the data.
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np

from meshseq.errors import MeshseqError, MeshseqWarning

USD_EXTENSIONS = (".usd", ".usda", ".usdc")


def _pxr():
    try:
        from pxr import Sdf, Usd, UsdGeom, Vt
    except ImportError:
        raise MeshseqError("USD needs Pixar's usd-core: pip install usd-core (or 'meshseq[usd]')") from None
    return Sdf, Usd, UsdGeom, Vt


def load_usd(path: Path, prim_path: str | None, *, name: str | None):
    """Read a time-sampled mesh of the stage at ``path`` (``prim_path`` picks one of several).

    Returns a validated :class:`meshseq.io.MeshSequence` (vertices ``(T, V, 3)``, faces ``(F, 3)``).
    """
    from meshseq.meshfiles import _one_line

    Sdf, Usd, UsdGeom, _ = _pxr()
    label = f"{path}:{prim_path}" if prim_path else str(path)
    try:
        layer = Sdf.Layer.Find(str(path))
        if layer is not None:  # a layer of this path is still loaded: see the file as it is now
            layer.Reload(force=True)
        stage = Usd.Stage.Open(str(path))
    except Exception as exc:
        raise MeshseqError(f"{path}: cannot open USD stage ({_one_line(exc)})") from None
    if stage is None:
        raise MeshseqError(f"{path}: cannot open USD stage")
    from pxr import Tf

    try:
        return _read_stage(stage, path, prim_path, name)
    except (TypeError, ValueError, IndexError, KeyError, AttributeError, Tf.ErrorException) as exc:
        # an attribute of the wrong type or shape in a hand-edited or damaged stage
        raise MeshseqError(f"{label}: malformed USD stage ({_one_line(exc)})") from None


def _read_stage(stage, path: Path, prim_path: str | None, name: str | None):
    """The sequence of an open stage (see :func:`load_usd`)."""
    from meshseq.meshfiles import _polygons_to_triangles, validate_sequence

    Sdf, Usd, UsdGeom, _ = _pxr()
    label = f"{path}:{prim_path}" if prim_path else str(path)
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    if prim_path:
        valid = prim_path.startswith("/") and Sdf.Path.IsValidPathString(prim_path)
        prim = stage.GetPrimAtPath(prim_path) if valid else None
        if prim is None or not prim.IsValid():
            listed = ", ".join(str(p.GetPath()) for p in meshes[:5]) or "none"
            raise MeshseqError(f"{label}: no prim {prim_path} in the stage (meshes: {listed})")
        if not prim.IsA(UsdGeom.Mesh):
            raise MeshseqError(f"{label}: prim is a {prim.GetTypeName() or 'typeless prim'}, not a Mesh")
    else:
        if not meshes:
            raise MeshseqError(f"{path}: the stage has no Mesh prim")
        animated = [p for p in meshes if UsdGeom.Mesh(p).GetPointsAttr().GetNumTimeSamples() > 1]
        candidates = animated or meshes
        if len(candidates) > 1:
            listed = ", ".join(str(p.GetPath()) for p in candidates[:5])
            raise MeshseqError(f"{path}: {len(candidates)} {'animated ' if animated else ''}meshes ({listed}); "
                               f"pick one as {path}:/PRIM/PATH")
        prim = candidates[0]
        label = f"{path}:{prim.GetPath()}"
    mesh = UsdGeom.Mesh(prim)
    points = mesh.GetPointsAttr()
    times = np.array(points.GetTimeSamples(), dtype=np.float64)
    if len(times) == 0:
        raise MeshseqError(f"{label}: points have no time samples (a static mesh, not a sequence)")
    frames = []
    for t in times:  # one Vt array per frame
        value = points.Get(float(t))
        arr = np.asarray(value, dtype=np.float64).reshape(-1, 3) if value is not None else np.zeros((0, 3))
        if frames and len(arr) != len(frames[0]):
            raise MeshseqError(f"{label}: {len(arr)} points at time {t:g}, {len(frames[0])} at time {times[0]:g}")
        frames.append(arr)
    if len(frames[0]) == 0:
        raise MeshseqError(f"{label}: points are empty")
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
    if len(counts) == 0 or len(indices) == 0:
        raise MeshseqError(f"{label}: no faces (faceVertexCounts / faceVertexIndices are empty)")
    if counts.sum() != len(indices):
        raise MeshseqError(f"{label}: faceVertexCounts add up to {int(counts.sum())} but there are "
                           f"{len(indices)} faceVertexIndices")
    faces, n_poly = _polygons_to_triangles(indices, None if (counts == 3).all() else counts, path)
    if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        faces = faces[:, ::-1]
    if n_poly:
        warnings.warn(f"{label}: triangulated {n_poly} non-triangle faces (fan) into {len(faces)} triangles",
                      MeshseqWarning, stacklevel=3)
    fps = None
    tcps = stage.GetTimeCodesPerSecond()
    if len(times) > 1 and tcps > 0:
        from meshseq.formats.caches import fps_from_times

        fps = fps_from_times(times / tcps)
    return validate_sequence(np.stack(frames), faces, name=name or prim.GetName() or path.stem,
                             source=label, fps=fps)


def save_usd(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, *, fps: float = 24.0,
             name: str = "sequence", up: str = "y", meters_per_unit: float = 1.0,
             force: bool = False) -> Path:
    """Write ``vertices (T, V, 3)`` with ``faces (F, 3)`` as a USD stage (format from the suffix:
    .usda text, .usdc / .usd binary crate), atomically; returns the path."""
    from meshseq.meshfiles import atomic_output

    Sdf, Usd, UsdGeom, Vt = _pxr()
    target = Path(path)
    if target.suffix.lower() not in USD_EXTENSIONS:
        raise MeshseqError(f"{target}: a USD output must end in {', '.join(USD_EXTENSIONS)}")
    axis = {"y": UsdGeom.Tokens.y, "z": UsdGeom.Tokens.z}.get(up.lower().lstrip("+"))
    if axis is None:
        raise MeshseqError(f"--up {up!r}: a USD stage's up axis is y or z")
    if not (np.isfinite(fps) and fps > 0):
        raise MeshseqError(f"--fps {fps}: must be a positive number")
    if not (np.isfinite(meters_per_unit) and meters_per_unit > 0):
        raise MeshseqError(f"--meters-per-unit {meters_per_unit}: must be a positive number")
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    f = np.ascontiguousarray(faces, dtype=np.int32)
    prim_name = re.sub(r"\W", "_", name) or "sequence"
    if prim_name[0].isdigit():
        prim_name = "_" + prim_name
    with atomic_output(target, force=force) as tmp:
        stage = Usd.Stage.CreateNew(str(tmp))
        UsdGeom.SetStageUpAxis(stage, axis)
        UsdGeom.SetStageMetersPerUnit(stage, float(meters_per_unit))
        stage.SetTimeCodesPerSecond(float(fps))
        stage.SetFramesPerSecond(float(fps))
        stage.SetStartTimeCode(0)
        stage.SetEndTimeCode(len(v) - 1)
        mesh = UsdGeom.Mesh.Define(stage, f"/{prim_name}")
        stage.SetDefaultPrim(mesh.GetPrim())
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        mesh.CreateDoubleSidedAttr(True)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(f), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(f.reshape(-1)))
        points = mesh.CreatePointsAttr()
        extent = mesh.CreateExtentAttr()
        lo, hi = v.min(axis=1), v.max(axis=1)  # (T, 3)
        for t in range(len(v)):  # one time sample per frame
            points.Set(Vt.Vec3fArray.FromNumpy(v[t]), float(t))
            extent.Set(Vt.Vec3fArray.FromNumpy(np.stack([lo[t], hi[t]])), float(t))
        stage.GetRootLayer().documentation = f"meshseq: {name}, {len(v)} frames at {fps:g} fps"
        stage.GetRootLayer().Save()
        del stage
    return target
