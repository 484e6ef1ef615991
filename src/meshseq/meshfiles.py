"""Mesh files below :mod:`meshseq.io`: the sequence type and its validation, the OBJ / OFF / PLY
frame readers and writers, and atomic, never-overwriting output.

:mod:`meshseq.io` (``load_sequence``, ``save_sequence``) and :mod:`meshseq.formats` build on this
module; it imports neither, so the formats can use these pieces without an import cycle.
:func:`validate_sequence` ends every loader: bad data raises :class:`MeshseqError` with one line
naming the file or frame; repairs and suspicions warn with :class:`MeshseqWarning`.

Vertex order is preserved exactly as stored in the files (OBJ and OFF are parsed here with
numpy; PLY goes through trimesh with ``process=False``), because every frame's vertex ``i`` must
be the same point of the surface. :func:`atomic_output` is the general "write to a temporary
sibling, then rename" context manager that every writer in the package uses, so an interrupted
write never leaves a half-written file and nothing is overwritten without ``force``.
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import shutil
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from meshseq.errors import MeshseqError, MeshseqWarning

MESH_EXTENSIONS = (".obj", ".ply", ".off")
#: Coordinates beyond +-MAX_COORDINATE, or frames smaller than MIN_EXTENT (their largest bounding-box
#: side; 0, a frame collapsed to one point, is allowed), are refused: the geometry multiplies up
#: to four coordinates (areas, Gram matrices, determinants), which overflows float64 from about
#: 1e77 and underflows below about 1e-77; 1e30 leaves a wide margin for the sums over a mesh.
MAX_COORDINATE = 1e30
MIN_EXTENT = 1e-30


# --------------------------------------------------------------------------------------------
# The sequence type and its validation


@dataclass(eq=False)
class MeshSequence:
    """T frames of one triangle mesh.

    Attributes:
        vertices: ``(T, V, 3)`` float64 positions.
        faces: ``(F, 3)`` int64 vertex indices, shared by every frame.
        name: short human name (file or folder stem, or the stored name).
        fps: frames per second if known.
        vertex_map: ``(V,)`` int64 index of each vertex in the source file when unreferenced
            vertices were dropped on load; None when vertices are exactly the file's.
        source: where the sequence came from (path or address), for messages.

    Construction coerces dtypes and checks shapes (MeshseqError if wrong); the full data checks
    and repairs live in :func:`validate_sequence`, which every loader calls.
    """

    vertices: np.ndarray
    faces: np.ndarray
    name: str = "sequence"
    fps: float | None = None
    vertex_map: np.ndarray | None = None
    source: str = ""

    def __post_init__(self) -> None:
        label = self.source or self.name
        v = np.asarray(self.vertices)
        f = np.asarray(self.faces)
        if v.ndim != 3 or v.shape[2] != 3 or v.shape[0] < 1 or v.shape[1] < 1:
            raise MeshseqError(f"{label}: vertices must have shape (T, V, 3) with T, V >= 1, got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] < 1:
            raise MeshseqError(f"{label}: faces must have shape (F, 3) with F >= 1, got {f.shape}")
        if not np.issubdtype(f.dtype, np.integer):
            raise MeshseqError(f"{label}: faces must be integers, got dtype {f.dtype}")
        if v.dtype == np.bool_ or not (np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer)):
            raise MeshseqError(f"{label}: vertices must be real numbers (float or int), got dtype {v.dtype}")
        self.vertices = np.ascontiguousarray(v, dtype=np.float64)
        self.faces = np.ascontiguousarray(f, dtype=np.int64)
        if self.fps is not None:
            self.fps = float(self.fps)
        if self.vertex_map is not None:
            if not np.issubdtype(np.asarray(self.vertex_map).dtype, np.integer):
                raise MeshseqError(f"{label}: vertex_map must be integers, got dtype {np.asarray(self.vertex_map).dtype}")
            vm = np.ascontiguousarray(self.vertex_map, dtype=np.int64)
            if vm.shape != (v.shape[1],):
                raise MeshseqError(f"{label}: vertex_map must have shape ({v.shape[1]},), got {vm.shape}")
            self.vertex_map = vm
        self.name = str(self.name)
        self.source = str(self.source)

    @property
    def n_frames(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[1])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    def __repr__(self) -> str:
        return (f"MeshSequence(name={self.name!r}, frames={self.n_frames}, vertices={self.n_vertices}, "
                f"faces={self.n_faces}, fps={self.fps}, source={self.source!r})")


def validate_sequence(vertices: np.ndarray, faces: np.ndarray, *, name: str, source: str,
                      fps: float | None = None, vertex_map: np.ndarray | None = None,
                      frame_labels: Sequence[str] | None = None) -> MeshSequence:
    """Check loaded arrays and build a :class:`MeshSequence` (the last step of every loader).

    Args:
        vertices: ``(T, V, 3)`` float.
        faces: ``(F, 3)`` int, triangles (polygons must be triangulated by the reader).
        name, source, fps, vertex_map: as in :class:`MeshSequence`.
        frame_labels: T strings naming each frame in messages (e.g. the frame files);
            default ``"<source> frame t"``.

    Raises MeshseqError for wrong shapes, NaN/Inf coordinates (naming the first bad frame and
    vertex) and faces that index missing vertices. Drops unreferenced vertices (warning; the
    result's ``vertex_map`` gives their original indices). Warns about degenerate triangles
    (in the first frame) and non-manifold edges.
    """
    from meshseq.mesh import Topology, degenerate_faces

    seq = MeshSequence(vertices, faces, name=name, fps=fps, vertex_map=vertex_map, source=source)
    v, f = seq.vertices, seq.faces
    n_frames, n_verts = v.shape[:2]

    def frame_label(t: int) -> str:
        if frame_labels is not None:
            return str(frame_labels[t])
        return f"{source} frame {t}" if n_frames > 1 else source

    if not np.isfinite(v.reshape(n_frames, -1)).all():  # (contiguous rows: 6x faster than per vertex)
        finite = np.isfinite(v).all(axis=2)  # (T, V)
        t, i = np.argwhere(~finite)[0]
        count = int((~finite[t]).sum())
        raise MeshseqError(f"{frame_label(int(t))}: non-finite (NaN/Inf) coordinates at vertex {int(i)} "
                           f"({count} vertices in this frame)")
    _check_magnitudes(v, frame_label)
    lo, hi = int(f.min()), int(f.max())
    if lo < 0 or hi >= n_verts:
        bad = np.flatnonzero(((f < 0) | (f >= n_verts)).any(axis=1))[0]
        raise MeshseqError(f"{source}: face {int(bad)} uses vertex {f[bad].tolist()} but there are only "
                           f"{n_verts} vertices (indices 0..{n_verts - 1})")

    used = np.zeros(n_verts, dtype=bool)
    used[f.ravel()] = True
    if not used.all():
        kept = np.flatnonzero(used)
        dropped = n_verts - len(kept)
        remap = np.cumsum(used) - 1
        f = remap[f]
        v = np.ascontiguousarray(v[:, kept])
        vm = kept if seq.vertex_map is None else seq.vertex_map[kept]
        warnings.warn(f"{source}: dropped {dropped} unreferenced vertices (no face uses them; "
                      f"first {int(np.flatnonzero(~used)[0])}); vertex_map keeps the original indices",
                      MeshseqWarning, stacklevel=3)
        seq = MeshSequence(v, f, name=seq.name, fps=seq.fps, vertex_map=vm, source=seq.source)

    n_degenerate = int(degenerate_faces(seq.vertices[0], seq.faces).sum())
    if n_degenerate:
        warnings.warn(f"{frame_label(0)}: {n_degenerate} degenerate (zero-area) triangles of {seq.n_faces}",
                      MeshseqWarning, stacklevel=3)
    n_nonmanifold = Topology.from_faces(seq.faces, seq.n_vertices).nonmanifold_edge_count
    if n_nonmanifold:
        warnings.warn(f"{source}: {n_nonmanifold} non-manifold edges (shared by more than 2 faces)",
                      MeshseqWarning, stacklevel=3)
    return seq


def _check_magnitudes(v: np.ndarray, frame_label) -> None:
    """MeshseqError naming the first frame whose coordinates are too large or whose extent is too
    small to compute with (see MAX_COORDINATE); ``v`` is ``(T, V, 3)`` and finite."""
    rows = v.reshape(len(v), -1)  # reductions along contiguous rows: 30x faster than over axis 1 of (T, V, 3)
    big = np.maximum(rows.max(axis=1), -rows.min(axis=1)) > MAX_COORDINATE  # (T,)
    if big.any():
        t = int(np.flatnonzero(big)[0])
        i = int(np.abs(v[t]).max(axis=1).argmax())
        raise MeshseqError(f"{frame_label(t)}: coordinate {np.abs(v[t, i]).max():.3g} at vertex {i} is beyond "
                           f"+-{MAX_COORDINATE:g}, too large to compute with; rescale the data")
    by_axis = np.ascontiguousarray(v.transpose(0, 2, 1))  # (T, 3, V)
    extent = (by_axis.max(axis=2) - by_axis.min(axis=2)).max(axis=1)  # (T,) largest bounding-box side
    small = (extent > 0) & (extent < MIN_EXTENT)
    if small.any():
        t = int(np.flatnonzero(small)[0])
        raise MeshseqError(f"{frame_label(t)}: the mesh is only {extent[t]:.3g} across, too small to compute "
                           f"with (at least {MIN_EXTENT:g}); rescale the data")


def check_input_file(path: Path) -> None:
    """MeshseqError unless ``path`` is an existing regular file (reading a FIFO or a device
    would wait forever or never end)."""
    if not path.exists():
        raise MeshseqError(f"{path}: path does not exist")
    if path.is_dir():
        raise MeshseqError(f"{path}: is a folder, expected a file")
    if not path.is_file():
        raise MeshseqError(f"{path}: not a regular file (a FIFO, socket or device); give a file")


def _check_mesh_path(path: Path) -> None:
    if path.is_dir():
        raise MeshseqError(f"{path}: is a folder, expected a mesh file")
    check_input_file(path)
    if path.suffix.lower() not in MESH_EXTENSIONS:
        raise MeshseqError(f"{path}: unsupported extension {path.suffix!r} "
                           f"(mesh frames: {', '.join(MESH_EXTENSIONS)}; sequences: .npz, .h5:NAME, "
                           ".glb/.gltf, .usd/.usda/.usdc, .mdd/.pc2 with a base mesh)")


def _one_line(exc: BaseException) -> str:
    try:
        text = " ".join(str(exc).split())
    except Exception:  # some library exceptions cannot even be printed (undecodable bytes)
        text = ""
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


# --------------------------------------------------------------------------------------------
# Mesh file readers (one frame each)


class _Frame:
    """One parsed frame: vertices ``(V, 3)`` now; faces parsed lazily (identical face text in
    every frame of a sequence is compared as bytes and parsed only once)."""

    def __init__(self, vertices: np.ndarray, face_key: bytes | None, parse_faces, n_polygons: int = 0):
        self.vertices = vertices
        self.face_key = face_key
        self._parse_faces = parse_faces
        self._faces: np.ndarray | None = None
        self.n_polygons = n_polygons

    def faces(self) -> np.ndarray:
        if self._faces is None:
            self._faces, self.n_polygons = self._parse_faces()
        return self._faces


def _read_mesh(path: Path) -> _Frame:
    suffix = path.suffix.lower()
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise MeshseqError(f"{path}: cannot read ({_one_line(exc)})") from None
    if not data.strip():
        raise MeshseqError(f"{path}: file is empty")
    if suffix == ".obj":
        frame = _read_obj(data, path)
    elif suffix == ".off":
        frame = _read_off(data, path)
    elif suffix == ".ply":
        frame = _read_ply(data, path)
    else:  # pragma: no cover - callers check extensions first
        raise MeshseqError(f"{path}: unsupported extension {path.suffix!r}")
    return frame


_OBJ_V = re.compile(rb"^[ \t]*v[ \t]+([^\n]*)", re.M)  # line body after the tag
_OBJ_F = re.compile(rb"^[ \t]*f[ \t]+([^\n]*)", re.M)
_OBJ_SLASH = re.compile(rb"/[^\s]*")


def _parse_ints(tokens: list[bytes], path: Path, what: str) -> np.ndarray:
    try:
        return np.array(tokens, dtype=np.int64)
    except ValueError as exc:
        raise MeshseqError(f"{path}: bad {what} ({_one_line(exc)})") from None
    except OverflowError:
        raise MeshseqError(f"{path}: {what} beyond 64-bit integers ({max(tokens, key=len)[:30].decode(errors='replace')}); "
                           "corrupt file?") from None


def _parse_floats(text: bytes, path: Path, what: str) -> np.ndarray:
    try:
        return np.array(text.split(), dtype=np.float64)
    except ValueError as exc:
        raise MeshseqError(f"{path}: bad number in {what} ({_one_line(exc)})") from None


def _obj_lines(data: bytes, tag: bytes, pattern: re.Pattern) -> tuple[bytes, int]:
    """All ``tag`` lines of an OBJ (tag included), joined by newlines, and how many there are.

    Fast path: the lines form one contiguous block (as every exporter writes them), found with
    ``find``/``count``; otherwise a regex collects them from anywhere in the file.
    """
    start = 0 if data.startswith(tag) else data.find(b"\n" + tag) + 1
    unusual = b"\n " in data or b"\n\t" in data or b"\n" + tag[:1] + b"\t" in data  # indents, tabs
    if (start > 0 or data.startswith(tag)) and not unusual:
        last = data.rfind(b"\n" + tag) + 1
        end = data.find(b"\n", max(last, start))
        block = data[start:end if end >= 0 else len(data)]
        n = block.count(b"\n" + tag) + 1
        if block.count(b"\n") + 1 == n and n == data.count(b"\n" + tag) + int(start == 0):
            return block, n
    lines = pattern.findall(data)
    return b"\n".join(tag + ln for ln in lines), len(lines)


def _read_obj(data: bytes, path: Path) -> _Frame:
    vblock, n_v = _obj_lines(data, b"v ", _OBJ_V)
    if n_v == 0:
        raise MeshseqError(f"{path}: no vertices ('v' lines) in OBJ file")
    coords = _parse_floats(vblock.replace(b"v", b" "), path, "vertex coordinates")
    if len(coords) == 3 * n_v:
        vertices = coords.reshape(-1, 3)
    else:  # some lines carry w or colours (or are broken): parse line by line
        vlines = vblock.split(b"\n")
        counts = np.fromiter(map(len, map(bytes.split, vlines)), dtype=np.int64, count=n_v) - 1
        if counts.sum() != len(coords):
            raise MeshseqError(f"{path}: a 'v' line holds a stray 'v' among its coordinates; corrupt file?")
        short = np.flatnonzero(counts < 3)
        if len(short):
            k = int(short[0])
            raise MeshseqError(f"{path}: vertex {k} has {int(counts[k])} coordinates, expected 3 "
                               f"(line {vlines[k].decode(errors='replace').strip()!r}); truncated file?")
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        vertices = coords[starts[:, None] + np.arange(3)]

    face_text, n_f = _obj_lines(data, b"f ", _OBJ_F)

    def parse_faces():
        if n_f == 0:
            raise MeshseqError(f"{path}: no faces ('f' lines) in OBJ file")
        stripped = _OBJ_SLASH.sub(b"", face_text).replace(b"f", b" ")
        idx = _parse_ints(stripped.split(), path, "face index")
        if (idx == 0).any():
            raise MeshseqError(f"{path}: face index 0 (OBJ indices start at 1); truncated or corrupt file?")
        if len(idx) == 3 * n_f:
            counts = None
        else:
            counts = np.fromiter(map(len, map(bytes.split, stripped.split(b"\n"))), dtype=np.int64,
                                 count=n_f)
        if (idx < 0).any():  # relative indices: -1 is the last vertex defined before the face
            v_pos = np.array([m.start() for m in _OBJ_V.finditer(data)])
            f_pos = np.array([m.start() for m in _OBJ_F.finditer(data)])
            defined = np.searchsorted(v_pos, f_pos)  # vertices before each face line
            per_index = np.repeat(defined, 3 if counts is None else counts)
            idx = np.where(idx < 0, idx + per_index + 1, idx)
        idx = idx - 1
        return _polygons_to_triangles(idx, counts, path)

    return _Frame(vertices, face_text, parse_faces)


def _polygons_to_triangles(idx: np.ndarray, counts: np.ndarray | None, path: Path) -> tuple[np.ndarray, int]:
    """Flat polygon indices + per-polygon sizes -> fan triangles ``(F, 3)`` and #non-triangles."""
    if counts is None:
        return idx.reshape(-1, 3), 0
    small = np.flatnonzero(counts < 3)
    if len(small):
        k = int(small[0])
        raise MeshseqError(f"{path}: face {k} has {int(counts[k])} vertices, need at least 3; truncated file?")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    n_tri = counts - 2
    poly = np.repeat(np.arange(len(counts)), n_tri)
    local = np.arange(int(n_tri.sum())) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)  # 0..k-3
    base = starts[poly]
    tris = np.stack([idx[base], idx[base + local + 1], idx[base + local + 2]], axis=1)
    return tris, int((counts > 3).sum())


def _read_off(data: bytes, path: Path) -> _Frame:
    lines = [ln.split(b"#", 1)[0].strip() for ln in data.split(b"\n")]
    lines = [ln for ln in lines if ln]
    if not lines:
        raise MeshseqError(f"{path}: not an OFF file (nothing but comments)")
    header = lines[0].split()
    if not header or not header[0].endswith(b"OFF"):
        raise MeshseqError(f"{path}: not an OFF file (first line {lines[0][:20]!r})")
    if header[0] != b"OFF" and header[0] not in (b"COFF", b"NOFF", b"CNOFF"):
        raise MeshseqError(f"{path}: unsupported OFF variant {header[0].decode(errors='replace')}")
    rest = header[1:]
    body = lines[1:]
    if not rest:
        if not body:
            raise MeshseqError(f"{path}: OFF header has no vertex/face counts")
        rest, body = body[0].split(), body[1:]
    try:
        n_v, n_f = int(rest[0]), int(rest[1])
    except (ValueError, IndexError):
        raise MeshseqError(f"{path}: bad OFF counts line {b' '.join(rest)[:40]!r}") from None
    if n_v < 1 or n_f < 0:
        raise MeshseqError(f"{path}: OFF header declares {n_v} vertices and {n_f} faces; corrupt file?")
    if len(body) < n_v + n_f:
        raise MeshseqError(f"{path}: OFF header promises {n_v} vertices and {n_f} faces but the file has "
                           f"only {len(body)} data lines; truncated file?")
    vlines = body[:n_v]
    coords = _parse_floats(b"\n".join(vlines), path, "vertex coordinates")
    if len(coords) == 3 * n_v:
        vertices = coords.reshape(-1, 3)
    else:
        counts = np.fromiter(map(len, map(bytes.split, vlines)), dtype=np.int64, count=n_v)
        if (counts < 3).any():
            k = int(np.flatnonzero(counts < 3)[0])
            raise MeshseqError(f"{path}: vertex {k} has {int(counts[k])} coordinates, expected 3")
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        vertices = coords[starts[:, None] + np.arange(3)]
    flines = body[n_v:n_v + n_f]
    face_text = b"\n".join(flines)

    def parse_faces():
        if n_f == 0:
            raise MeshseqError(f"{path}: OFF file has no faces")
        rows = [ln.split() for ln in flines]
        sizes = _parse_ints([r[0] for r in rows], path, "face size")
        if (sizes < 3).any():
            k = int(np.flatnonzero(sizes < 3)[0])
            raise MeshseqError(f"{path}: face {k} has {int(sizes[k])} vertices, need at least 3; corrupt file?")
        idx = _parse_ints([x for r, k in zip(rows, sizes) for x in r[1:1 + k]], path, "face index")
        if len(idx) != sizes.sum():
            raise MeshseqError(f"{path}: a face line lists fewer indices than its count; truncated file?")
        return _polygons_to_triangles(idx, None if (sizes == 3).all() else sizes, path)

    return _Frame(vertices, face_text, parse_faces)


_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
              "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def _ply_header(data: bytes, path: Path) -> tuple[bytes, list[tuple[str, int, list[str]]], int]:
    """``(format, elements, body_start)`` of a PLY file: elements as ``(name, count, property
    types)`` in file order (a list property's type is ``"list"``); MeshseqError if malformed."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise MeshseqError(f"{path}: not a PLY file (no 'ply' ... 'end_header' header)")
    newline = data.find(b"\n", end)
    body_start = len(data) if newline < 0 else newline + 1
    fmt, elements = b"", []
    for line in data[:end].split(b"\n")[1:]:
        words = line.split()
        if not words:
            continue
        if words[0] == b"format" and len(words) > 1:
            fmt = words[1]
        elif words[0] == b"element":
            if len(words) != 3 or not words[2].isdigit():
                raise MeshseqError(f"{path}: bad PLY header line {line.strip()[:40]!r}")
            elements.append((words[1].decode(errors="replace"), int(words[2]), []))
        elif words[0] == b"property" and elements:
            if len(words) < 3:
                raise MeshseqError(f"{path}: bad PLY header line {line.strip()[:40]!r}")
            kind = "list" if words[1] == b"list" else words[1].decode(errors="replace")
            elements[-1][2].append((kind, words[-1].decode(errors="replace")))
    return fmt, elements, body_start


def _read_ply(data: bytes, path: Path) -> _Frame:
    import io as _io

    import trimesh

    fmt, elements, body_start = _ply_header(data, path)
    counts = {name: count for name, count, _ in elements}
    declared_vertices, declared_faces = counts.get("vertex", 0), counts.get("face", 0)
    if "vertex" not in counts:
        raise MeshseqError(f"{path}: no 'element vertex' in the PLY header")
    vertex_props = next(props for name, _, props in elements if name == "vertex")
    names = [n for _, n in vertex_props]
    missing = [axis for axis in "xyz" if axis not in names]
    if missing:
        raise MeshseqError(f"{path}: PLY vertices have no {', '.join(missing)} propert{'ies' if len(missing) > 1 else 'y'} "
                           f"(they have {', '.join(names) or 'none'})")
    body = data[body_start:]
    if fmt == b"ascii":
        available = len(body.split())  # numbers: a vertex takes one per property
        needed = declared_vertices * len(vertex_props)
    elif elements[0][0] == "vertex" and all(t in _PLY_SIZES for t, _ in vertex_props):
        available = len(body)
        needed = declared_vertices * sum(_PLY_SIZES[t] for t, _ in vertex_props)
    else:
        available = needed = 0  # no simple size to check (lists in the vertices, or elements first)
    if available < needed:
        raise MeshseqError(f"{path}: header declares {declared_vertices} vertices but the file holds too little "
                           f"data for them; truncated file?")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = trimesh.load(_io.BytesIO(data), file_type="ply", process=False, maintain_order=True,
                                force="mesh")
        vertices = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    except Exception as exc:
        raise MeshseqError(f"{path}: cannot read PLY ({_one_line(exc)}); truncated or corrupt file?") from None
    if len(vertices) == 0:
        raise MeshseqError(f"{path}: no vertices in PLY file")
    if len(vertices) < declared_vertices:
        raise MeshseqError(f"{path}: header declares {declared_vertices} vertices, read {len(vertices)}; "
                           "truncated or corrupt file?")
    if declared_faces and len(faces) < declared_faces:
        raise MeshseqError(f"{path}: header declares {declared_faces} faces, read {len(faces)}; "
                           "truncated or corrupt file?")

    def parse_faces():
        if len(faces) == 0:
            raise MeshseqError(f"{path}: no faces in PLY file (a point cloud is not a mesh)")
        # trimesh fans polygons into triangles itself; the extra triangles count the polygons
        # exactly for quads (an upper bound for larger polygons)
        return faces, max(0, len(faces) - declared_faces)

    return _Frame(vertices, None, parse_faces)


# --------------------------------------------------------------------------------------------
# Atomic output


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, *, force: bool = False) -> Iterator[Path]:
    """Write a file or folder atomically: yield a temporary sibling path, rename it onto ``path``.

    Usage::

        with atomic_output("out/model.safetensors", force=args.force) as tmp:
            save_file(tensors, tmp)          # write a file at tmp ...
        with atomic_output("out/frames") as tmp:
            tmp.mkdir(); ...                 # ... or create a folder at tmp and fill it

    * ``path`` existing (file or folder) without ``force`` -> MeshseqError before anything is
      written (and again at the end, if it appeared meanwhile).
    * The temporary path is in the same folder (same file system, so the rename is atomic) and
      ends with ``path``'s name, so suffix-sensitive writers (``np.savez``, image writers) see the
      right extension. Missing parent folders are created.
    * On success the temporary is renamed onto ``path`` with ``os.replace``; an existing folder
      (with ``force``) is moved aside first and deleted only after the new one is in place.
    * On any exception (KeyboardInterrupt included) the temporary is removed, ``path`` is left
      exactly as it was, and the exception propagates.
    """
    target = Path(path)
    _refuse_existing(target, force)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MeshseqError(f"{target}: cannot create its folder ({exc.strerror or _one_line(exc)})") from None
    token = secrets.token_hex(4)
    tmp = target.parent / f".tmp-{token}-{target.name}"
    try:
        yield tmp
        if not os.path.lexists(tmp):
            raise RuntimeError(f"atomic_output: nothing was written to the temporary path for {target}")
        _refuse_existing(target, force)
        if target.is_dir() and not target.is_symlink() or (os.path.lexists(target) and tmp.is_dir()):
            old = target.parent / f".old-{token}-{target.name}"
            os.replace(target, old)
            try:
                os.replace(tmp, target)
            except BaseException:
                os.replace(old, target)
                raise
            _remove(old)
        else:
            os.replace(tmp, target)
    except BaseException:
        _remove(tmp)
        raise


def check_output(path: str | os.PathLike, *, force: bool = False) -> Path:
    """Fail early (MeshseqError, suggesting --force) if ``path`` exists and ``force`` is off.

    Call it before a long computation whose result will go to ``path``; :func:`atomic_output`
    checks again when it writes. Returns ``path`` as a Path.
    """
    target = Path(path)
    _refuse_existing(target, force)
    if target.suffix.lower() in (".mdd", ".pc2"):  # a point cache comes with its base mesh
        _refuse_existing(target.with_suffix(".obj"), force)
    check_writable(target, target.parent)
    return target


def check_writable(target: str | os.PathLike, folder: str | os.PathLike) -> None:
    """MeshseqError naming ``target`` unless files can be created in ``folder`` (or, where it
    does not exist yet, in its nearest existing ancestor, below which it would be created).

    Refuses a path through a file (``-o notes.txt/out.npz``), a read-only folder or file system
    and /proc, before any work starts: it creates and removes an empty temporary file there.
    """
    probe = Path(os.path.abspath(folder))
    while not os.path.lexists(probe) and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise MeshseqError(f"{target}: cannot write there, {probe} is a file, not a folder")
    try:
        fd, name = tempfile.mkstemp(prefix=".tmp-probe-", dir=probe)
    except OSError as exc:
        raise MeshseqError(f"{target}: cannot write in {probe} ({exc.strerror or _one_line(exc)})") from None
    os.close(fd)
    os.remove(name)


def _refuse_existing(target: Path, force: bool) -> None:
    if not force and os.path.lexists(target):
        kind = "folder" if target.is_dir() else "file"
        raise MeshseqError(f"{target}: output {kind} already exists; use --force (force=True) to overwrite it")


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif os.path.lexists(path):
        with contextlib.suppress(OSError):
            os.remove(path)


def json_text(obj, *, indent: int | None = 2) -> str:
    """Strict JSON text of ``obj`` for everything meshseq prints or writes as JSON.

    NaN and +-inf (which ``json.dumps`` writes as the invalid tokens ``NaN``/``Infinity``) become
    ``null``; numpy scalars and arrays become numbers and lists.
    """
    import json

    def clean(x):
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, np.ndarray):
            return clean(x.tolist())
        if isinstance(x, (bool, np.bool_)):
            return bool(x)
        if isinstance(x, np.integer):
            return int(x)
        if isinstance(x, (float, np.floating)):
            return float(x) if np.isfinite(x) else None
        return x

    return json.dumps(clean(obj), indent=indent, allow_nan=False)


def _obj_writer(seq: MeshSequence, precision: int):
    head = f"# meshseq: {seq.name}, {seq.n_vertices} vertices, {seq.n_faces} faces\n".encode()
    face_text = (("f %d %d %d\n" * seq.n_faces) % tuple((seq.faces + 1).ravel().tolist())).encode()
    line = f"v %.{precision}g %.{precision}g %.{precision}g\n" * seq.n_vertices

    def write(t: int) -> bytes:
        return head + (line % tuple(seq.vertices[t].ravel().tolist())).encode() + face_text

    return write


def _ply_writer(seq: MeshSequence):
    header = (f"ply\nformat binary_little_endian 1.0\ncomment meshseq: {seq.name}\n"
              f"element vertex {seq.n_vertices}\nproperty double x\nproperty double y\nproperty double z\n"
              f"element face {seq.n_faces}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    face_rec = np.empty(seq.n_faces, dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    face_rec["n"] = 3
    face_rec["idx"] = seq.faces
    face_bytes = face_rec.tobytes()

    def write(t: int) -> bytes:
        return header + seq.vertices[t].astype("<f8").tobytes() + face_bytes

    return write
