"""Read and write mesh sequences; atomic, never-overwriting output.

A *mesh sequence* is T frames of one triangle mesh: vertices ``(T, V, 3)`` that move, faces
``(F, 3)`` shared by every frame. :func:`load_sequence` reads one from

* a folder of ``.obj`` / ``.ply`` / ``.off`` frames (natural order: ``2.obj`` before ``10.obj``;
  other files in the folder are ignored),
* an explicit list of mesh files, or a single mesh file (one frame),
* a ``.npz`` with ``vertices`` ``(T, V, 3)``, ``faces`` ``(F, 3)`` and optional ``fps``, ``name``,
  ``vertex_map``,
* a Dyna-style HDF5 file addressed as ``"file.h5:sequence_name"`` (the sequence dataset holds
  vertices ``(V, 3, T)``, dataset ``faces`` the faces),
* the interchange formats of :mod:`meshseq.formats`: glTF morph-target animation
  (``anim.glb``, ``anim.glb:MESH``), MDD/PC2 point caches with a base mesh for the faces
  (``cache.pc2`` with ``cache.obj`` beside it, or ``base.obj:cache.pc2``) and USD
  (``shot.usda``, ``shot.usda:/World/Mesh``).

Every loader ends in :func:`validate_sequence`: bad data raises :class:`MeshseqError` with one
line naming the file or frame; repairs (polygon triangulation, dropping unreferenced vertices)
and suspicions (degenerate triangles, non-manifold edges) warn with :class:`MeshseqWarning`.

Vertex order is preserved exactly as stored in the files (OBJ and OFF are parsed here with
numpy; PLY goes through trimesh with ``process=False``), because every frame's vertex ``i`` must
be the same point of the surface.

:func:`save_sequence` writes ``.npz``, a folder of OBJ/PLY frames, or ``.glb`` / ``.usd(a/c)`` /
``.mdd`` / ``.pc2`` (:mod:`meshseq.formats`); :func:`atomic_output` is the
general "write to a temporary sibling, then rename" context manager that every writer in the
package uses, so an interrupted write never leaves a half-written file and nothing is
overwritten without ``force``.
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np

from meshseq.errors import MeshseqError, MeshseqWarning
from meshseq.meshfiles import (MAX_COORDINATE, MESH_EXTENSIONS, MIN_EXTENT, MeshSequence, _check_mesh_path,  # noqa: F401
                               _obj_writer, _one_line, _ply_writer, _read_mesh, _refuse_existing, atomic_output,
                               check_input_file, check_output, check_writable, json_text, validate_sequence)

HDF5_EXTENSIONS = (".h5", ".hdf5")
SAVE_FORMATS = ("npz", "obj", "ply")


# --------------------------------------------------------------------------------------------
# Loading


def load_sequence(spec: str | os.PathLike | Sequence[str | os.PathLike], *,
                  name: str | None = None) -> MeshSequence:
    """Load a mesh sequence.

    Args:
        spec: a folder of OBJ/PLY/OFF frames, a ``.npz``, ``"file.h5:sequence"``, one mesh file
            (a one-frame sequence), a list of mesh files (one frame each, in the given order), or
            one of :mod:`meshseq.formats` (``.glb``/``.gltf``, ``.usd(a/c)``, ``.mdd``/``.pc2``
            with a base mesh, and their ``FILE:ADDRESS`` forms).
        name: override the sequence name (default: stored name, else file/folder stem).

    Returns:
        :class:`MeshSequence` (vertices float64 ``(T, V, 3)``, faces int64 ``(F, 3)``).

    Raises:
        MeshseqError: one line naming the file/frame and what is wrong.
    """
    if isinstance(spec, (list, tuple)):
        paths = [Path(p) for p in spec]
        if not paths:
            raise MeshseqError("empty list of mesh files")
        for p in paths:
            if is_sequence_spec(p):
                raise MeshseqError(f"{p}: several DATA are the frames of one sequence, so each must be a mesh "
                                   f"file ({', '.join(MESH_EXTENSIONS)}); give the sequence {p} on its own")
            _check_mesh_path(p)
        default = paths[0].parent.name or paths[0].stem
        return _load_frames(paths, name=name or default, source=", ".join(map(str, paths[:2]))
                            + (", ..." if len(paths) > 2 else ""))

    text = os.fspath(spec)
    path = Path(text)
    if path.exists() and not path.is_dir():
        check_input_file(path)
    from meshseq import formats

    special = formats.load(text, name=name)  # glTF, MDD/PC2 caches, USD (files and addresses)
    if special is not None:
        return special
    if not path.exists():
        h5 = _split_h5_address(text)
        if h5 is not None:
            return _load_h5(Path(h5[0]), h5[1], name=name)
        raise MeshseqError(f"{text}: path does not exist")
    if path.is_dir():
        return _load_folder(path, name=name)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return _load_npz(path, name=name)
    if suffix in HDF5_EXTENSIONS:
        return _load_h5(path, None, name=name)
    _check_mesh_path(path)
    return _load_frames([path], name=name or path.stem, source=str(path))


def is_sequence_spec(spec: str | os.PathLike) -> bool:
    """Whether ``spec`` names a whole sequence (folder, .npz, .h5, glTF, USD, point cache, or an
    address such as ``file.h5:NAME``) rather than one mesh file (one frame)."""
    from meshseq import formats

    text = os.fspath(spec)
    suffix = Path(text).suffix.lower()
    return (Path(text).is_dir() or suffix in (".npz",) + HDF5_EXTENSIONS + formats.READ_EXTENSIONS
            or formats.split_address(text) is not None
            or (":" in text and Path(text.rsplit(":", 1)[0]).suffix.lower() in HDF5_EXTENSIONS))


def natural_key(name: str) -> tuple:
    """Sort key putting ``frame2`` before ``frame10`` (digit runs compare as numbers)."""
    parts = re.split(r"(\d+)", name)
    return tuple(int(p) if i % 2 else p.casefold() for i, p in enumerate(parts)), name


def _split_h5_address(text: str) -> tuple[str, str] | None:
    if ":" not in text:
        return None
    file_part, seq_name = text.rsplit(":", 1)
    if Path(file_part).suffix.lower() not in HDF5_EXTENSIONS:
        return None
    check_input_file(Path(file_part))
    return file_part, seq_name


def _load_folder(folder: Path, *, name: str | None) -> MeshSequence:
    files = [p for p in folder.iterdir() if not p.name.startswith(".") and p.is_file()]
    meshes = [p for p in files if p.suffix.lower() in MESH_EXTENSIONS]
    if not meshes:
        others = sorted(p.name for p in files)
        hint = f" (it holds {len(others)} other files, e.g. {others[0]})" if others else " (it is empty)"
        raise MeshseqError(f"{folder}: no mesh files ({', '.join(MESH_EXTENSIONS)}) in folder{hint}")
    kinds = sorted({p.suffix.lower() for p in meshes})
    if len(kinds) > 1:
        raise MeshseqError(f"{folder}: folder mixes {' and '.join(kinds)} frames; keep one format per "
                           "folder or pass an explicit list of files")
    meshes.sort(key=lambda p: natural_key(p.name))
    return _load_frames(meshes, name=name or folder.resolve().name, source=str(folder))


def _load_frames(paths: list[Path], *, name: str, source: str) -> MeshSequence:
    """Read frame files into one sequence; faces must match the first frame's exactly."""
    first = _read_mesh(paths[0])
    ref_vertices, ref_faces = first.vertices, first.faces()
    n_verts = len(ref_vertices)
    vertices = np.empty((len(paths), n_verts, 3), dtype=np.float64)
    vertices[0] = ref_vertices
    for t in range(1, len(paths)):
        frame = _read_mesh(paths[t])
        if len(frame.vertices) != n_verts:
            raise MeshseqError(f"{paths[t]}: {len(frame.vertices)} vertices, expected {n_verts} "
                               f"(as in {paths[0]})")
        if frame.face_key is None or frame.face_key != first.face_key:
            faces = frame.faces()
            if faces.shape != ref_faces.shape:
                raise MeshseqError(f"{paths[t]}: {len(faces)} faces, expected {len(ref_faces)} "
                                   f"(as in {paths[0]})")
            diff = np.flatnonzero((faces != ref_faces).any(axis=1))
            if len(diff):
                k = int(diff[0])
                raise MeshseqError(f"{paths[t]}: faces differ from {paths[0]} ({len(diff)} faces; first "
                                   f"face {k} is {faces[k].tolist()}, expected {ref_faces[k].tolist()})")
        vertices[t] = frame.vertices
    if first.n_polygons:
        warnings.warn(f"{paths[0]}: triangulated {first.n_polygons} non-triangle faces (fan) into "
                      f"{len(ref_faces)} triangles in total", MeshseqWarning, stacklevel=3)
    return validate_sequence(vertices, ref_faces, name=name, source=source,
                             frame_labels=[str(p) for p in paths])


def _load_npz(path: Path, *, name: str | None) -> MeshSequence:
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except Exception as exc:  # zipfile.BadZipFile, ValueError, OSError, EOFError...
        raise MeshseqError(f"{path}: cannot read .npz ({_one_line(exc)})") from None
    missing = [k for k in ("vertices", "faces") if k not in arrays]
    if missing:
        raise MeshseqError(f"{path}: missing key(s) {', '.join(missing)} (found: "
                           f"{', '.join(sorted(arrays)) or 'nothing'})")
    v, f = arrays["vertices"], arrays["faces"]
    if v.ndim != 3 or v.shape[2] != 3:
        raise MeshseqError(f"{path}: 'vertices' must have shape (T, V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise MeshseqError(f"{path}: 'faces' must have shape (F, 3), got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise MeshseqError(f"{path}: 'faces' must be integers, got dtype {f.dtype}")
    fps = _positive_number(arrays.get("fps"))
    stored_name = str(arrays["name"].reshape(())) if "name" in arrays and arrays["name"].size == 1 else None
    return validate_sequence(v, f, name=name or stored_name or path.stem, source=str(path), fps=fps,
                             vertex_map=arrays.get("vertex_map"))


def _load_h5(path: Path, seq_name: str | None, *, name: str | None) -> MeshSequence:
    import h5py

    try:
        with h5py.File(path, "r") as handle:
            raw, faces, fps = _h5_arrays(handle, path, seq_name)
    except MeshseqError:
        raise
    except Exception as exc:  # a damaged file fails anywhere in h5py (OSError, RuntimeError, KeyError...)
        raise MeshseqError(f"{path}: cannot read HDF5 ({_one_line(exc)}); truncated or corrupt file?") from None
    address = f"{path}:{seq_name}"
    if raw.ndim != 3 or raw.shape[1] != 3:
        raise MeshseqError(f"{address}: expected vertices stored as (V, 3, T), got {raw.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise MeshseqError(f"{path}: 'faces' must be integers of shape (F, 3), got {faces.shape} {faces.dtype}")
    return validate_sequence(np.transpose(raw, (2, 0, 1)), faces, name=name or seq_name, source=address, fps=fps)


def _h5_arrays(handle, path: Path, seq_name: str | None) -> tuple[np.ndarray, np.ndarray, float | None]:
    """``(raw (V, 3, T), faces, fps)`` of sequence ``seq_name`` of an open Dyna-style HDF5 file."""
    import h5py

    names = sorted(k for k in handle.keys() if k != "faces" and isinstance(handle[k], h5py.Dataset))
    few = ", ".join(names[:5]) + (f", ... ({len(names)} in all)" if len(names) > 5 else "")
    if seq_name is None or seq_name == "":
        raise MeshseqError(f"{path}: name the sequence as {path}:NAME (available: {few or 'none'})")
    address = f"{path}:{seq_name}"
    if seq_name not in handle:
        raise MeshseqError(f"{address}: no sequence {seq_name!r} in the file (available: {few or 'none'})")
    if not isinstance(handle[seq_name], h5py.Dataset):
        raise MeshseqError(f"{address}: {seq_name!r} is an HDF5 group, not a sequence dataset "
                           f"(available: {few or 'none'})")
    if not isinstance(handle.get("faces"), h5py.Dataset):
        raise MeshseqError(f"{path}: no 'faces' dataset")
    raw = np.asarray(handle[seq_name][()])
    faces = np.asarray(handle["faces"][()])
    fps = _positive_number(handle[seq_name].attrs.get("fps", handle.attrs.get("fps")))
    return raw, faces, fps


def _positive_number(value) -> float | None:
    """A stored optional scalar such as fps as a positive float; None if absent or not one."""
    a = np.asarray(value) if value is not None else None
    if a is None or a.size != 1 or a.dtype == np.bool_ or not np.issubdtype(a.dtype, np.number) \
            or np.iscomplexobj(a):
        return None
    x = float(a.reshape(()))
    return x if np.isfinite(x) and x > 0 else None


# --------------------------------------------------------------------------------------------
# Saving


def save_sequence(seq: MeshSequence, path: str | os.PathLike, *, format: str | None = None,
                  force: bool = False, precision: int = 9, up: str = "y", normals: bool = True,
                  meters_per_unit: float = 1.0) -> Path:
    """Write a sequence atomically; refuse to overwrite unless ``force``.

    Args:
        seq: the sequence.
        path: ``*.npz`` -> one NumPy archive (float64 vertices, faces, name, fps, vertex_map);
            a path without a suffix (or ending in ``/``) -> a folder of frames
            ``frame_0000.obj`` ... (``format="ply"`` for binary PLY frames, exact float64);
            ``*.obj`` / ``*.ply`` -> a single mesh file (one-frame sequences only);
            ``*.glb`` (morph-target animation), ``*.usd`` / ``*.usda`` / ``*.usdc`` (time-sampled
            mesh), ``*.mdd`` / ``*.pc2`` (point cache, plus the base mesh as ``*.obj`` beside it):
            see :func:`meshseq.formats.save`; they take the sequence's fps (default 24).
        format: ``"npz"``, ``"obj"`` or ``"ply"``; default from the path (folder -> ``"obj"``).
        force: replace an existing output (only once the new one is completely written).
        precision: significant digits of OBJ coordinates (9 round-trips float32 exactly;
            17 round-trips float64).
        up, normals, meters_per_unit: for .glb (up, normals) and USD (up: y or z, meters_per_unit).

    Returns:
        The written path.
    """
    text = os.fspath(path)
    target = Path(text)
    as_folder = text.endswith(("/", os.sep)) or target.suffix == "" or target.is_dir()
    suffix = "" if as_folder else target.suffix.lower().lstrip(".")
    from meshseq import formats

    if suffix and "." + suffix in formats.WRITE_EXTENSIONS:
        if format is not None:
            raise MeshseqError(f"{target}: format={format!r} is only for .npz and frame folders")
        return formats.save(seq, target, force=force, up=up, normals=normals, meters_per_unit=meters_per_unit)
    if format is not None and format not in SAVE_FORMATS:
        raise MeshseqError(f"format {format!r} is not one of {', '.join(SAVE_FORMATS)}")
    if suffix and suffix not in SAVE_FORMATS:
        raise MeshseqError(f"{target}: unsupported output extension .{suffix} (use .npz, .obj, .ply, "
                           ".glb, .usd, .usda, .usdc, .mdd, .pc2 or a folder path)")
    if suffix and format is not None and format != suffix:
        raise MeshseqError(f"{target}: extension .{suffix} contradicts format={format!r}")
    fmt = format or suffix or "obj"
    if as_folder and fmt == "npz":
        raise MeshseqError(f"{target}: format 'npz' needs a file path ending in .npz")

    _refuse_existing(target, force)
    if fmt == "npz":
        arrays = {"vertices": seq.vertices, "faces": seq.faces, "name": np.array(seq.name)}
        if seq.fps is not None:
            arrays["fps"] = np.array(seq.fps, dtype=np.float64)
        if seq.vertex_map is not None:
            arrays["vertex_map"] = seq.vertex_map
        with atomic_output(target, force=force) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)
        return target

    writer = _obj_writer(seq, precision) if fmt == "obj" else _ply_writer(seq)
    if not as_folder:
        if seq.n_frames != 1:
            raise MeshseqError(f"{target}: a .{fmt} file holds one frame but the sequence has {seq.n_frames}; "
                               "give a folder path (e.g. out/) or a .npz")
        with atomic_output(target, force=force) as tmp:
            tmp.write_bytes(writer(0))
        return target

    width = max(4, len(str(seq.n_frames - 1)))
    with atomic_output(target, force=force) as tmp:
        tmp.mkdir()
        for t in range(seq.n_frames):
            (tmp / f"frame_{t:0{width}d}.{fmt}").write_bytes(writer(t))
    return target
