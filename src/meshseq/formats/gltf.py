"""Read a mesh sequence from glTF 2.0 (.glb / .gltf) morph-target animation.

This is what Blender (shape keys), three.js and meshseq's own :mod:`meshseq.export` write: one
mesh whose primitives carry morph targets (POSITION offsets), and an animation whose sampler
drives the mesh node's ``weights``. Frame ``k`` is::

    positions[k] = base (V, 3) + weights[k] (K,) @ targets (K, V, 3)

evaluated at the animation's keyframe times, resampled onto an even grid (the smallest key
spacing) when keys were thinned out; ``fps`` is one over that spacing. Positions are in the
mesh's own coordinates (node transforms, e.g. the up-axis rotation of ``meshseq export --up``,
are not applied), so meshseq's export -> import returns the exported float32 data.

Several primitives of the mesh are concatenated (one vertex list, faces offset). Exporters such
as Blender's split vertices along UV seams and sharp edges; vertices that coincide in every frame
are merged again (warning; ``vertex_map`` gives each kept vertex's index in the file's
concatenated list). Files whose ``asset.generator`` is meshseq are never split, so nothing is
merged in them: a sequence with coincident vertices of its own keeps them.
"""

from __future__ import annotations

import base64
import warnings
from pathlib import Path

import numpy as np

from meshseq.errors import MeshseqError, MeshseqWarning

_COMPONENTS = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


class _Buffers:
    """Raw bytes of a document's buffers (GLB chunk, data: URIs or files beside a .gltf)."""

    def __init__(self, doc, path: Path):
        self.doc, self.path = doc, path
        self._cache: dict[int, bytes] = {}

    def get(self, index: int) -> bytes:
        if index not in self._cache:
            buf = self.doc.buffers[index]
            if buf.uri is None:
                blob = self.doc.binary_blob()
                if blob is None:
                    raise MeshseqError(f"{self.path}: buffer {index} has no data (no GLB binary chunk)")
                data = bytes(blob)
            elif buf.uri.startswith("data:"):
                try:
                    data = base64.b64decode(buf.uri.split(",", 1)[1])
                except Exception:
                    raise MeshseqError(f"{self.path}: buffer {index} has a bad data URI") from None
            else:
                file = self.path.parent / buf.uri
                if not file.is_file():
                    raise MeshseqError(f"{self.path}: buffer {index} refers to {file}, which is not a file")
                try:
                    data = file.read_bytes()
                except OSError:
                    raise MeshseqError(f"{self.path}: buffer {index} refers to {file}, which cannot be read") from None
            if len(data) < buf.byteLength:
                raise MeshseqError(f"{self.path}: buffer {index} holds {len(data)} bytes, its header says "
                                   f"{buf.byteLength}; truncated file?")
            self._cache[index] = data
        return self._cache[index]


def _accessor(doc, buffers: _Buffers, index: int, path: Path) -> np.ndarray:
    """Accessor ``index`` as an array ``(count, width)`` (or ``(count,)`` for SCALAR)."""
    try:
        acc = doc.accessors[index]
    except (IndexError, TypeError):
        raise MeshseqError(f"{path}: accessor {index} does not exist") from None
    if acc.componentType not in _COMPONENTS or acc.type not in _WIDTH:
        raise MeshseqError(f"{path}: accessor {index} has unsupported type {acc.componentType}/{acc.type}")
    dtype = np.dtype(_COMPONENTS[acc.componentType])
    width = _WIDTH[acc.type]
    count = int(acc.count)
    if acc.bufferView is None:
        out = np.zeros((count, width), dtype)
    else:
        view = doc.bufferViews[acc.bufferView]
        data = buffers.get(view.buffer)
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        elem = dtype.itemsize * width
        stride = view.byteStride or elem
        end = start + stride * (count - 1) + elem if count else start
        if end > (view.byteOffset or 0) + view.byteLength or end > len(data):
            raise MeshseqError(f"{path}: accessor {index} reads past the end of its buffer; truncated file?")
        raw = np.frombuffer(data, np.uint8, end - start, offset=start)
        if stride == elem:
            out = raw.view(dtype).reshape(count, width).copy()
        else:
            rows = np.lib.stride_tricks.as_strided(raw, (count, elem), (stride, 1))
            out = np.ascontiguousarray(rows).view(dtype).reshape(count, width)
    if acc.sparse is not None and acc.sparse.count:
        sp = acc.sparse
        n = int(sp.count)
        iv = doc.bufferViews[sp.indices.bufferView]
        idx = np.frombuffer(buffers.get(iv.buffer), np.dtype(_COMPONENTS[sp.indices.componentType]), n,
                            offset=(iv.byteOffset or 0) + (sp.indices.byteOffset or 0))
        vv = doc.bufferViews[sp.values.bufferView]
        vals = np.frombuffer(buffers.get(vv.buffer), dtype, n * width,
                             offset=(vv.byteOffset or 0) + (sp.values.byteOffset or 0)).reshape(n, width)
        out = out.copy()
        out[idx.astype(np.int64)] = vals
    if acc.normalized:
        raise MeshseqError(f"{path}: accessor {index} is normalized (quantized); not supported")
    if out.dtype.kind == "f" and not np.isfinite(out).all():
        raise MeshseqError(f"{path}: accessor {index} holds NaN or infinite values; corrupt file?")
    return out[:, 0] if acc.type == "SCALAR" else out


def _sample_weights(times: np.ndarray, values: np.ndarray, interpolation: str,
                    grid: np.ndarray) -> np.ndarray:
    """Evaluate a weights sampler (keys ``times (N,)``, ``values (N, K)`` or for CUBICSPLINE
    ``(N, 3, K)`` = in-tangent, value, out-tangent) at ``grid (T,)``; returns ``(T, K)``."""
    vals = values[:, 1] if interpolation == "CUBICSPLINE" else values
    if len(times) == 1:
        return np.repeat(vals[:1], len(grid), axis=0)
    i = np.clip(np.searchsorted(times, grid, side="right") - 1, 0, len(times) - 2)
    t0, t1 = times[i], times[i + 1]
    u = np.clip((grid - t0) / (t1 - t0), 0.0, 1.0)[:, None]
    if interpolation == "STEP":
        return np.where(u >= 1.0, vals[i + 1], vals[i])
    if interpolation == "CUBICSPLINE":
        dt = (t1 - t0)[:, None]
        u2, u3 = u * u, u * u * u
        return ((2 * u3 - 3 * u2 + 1) * vals[i] + (u3 - 2 * u2 + u) * dt * values[i, 2]
                + (-2 * u3 + 3 * u2) * vals[i + 1] + (u3 - u2) * dt * values[i + 1, 0])
    return (1.0 - u) * vals[i] + u * vals[i + 1]


def _time_grid(times: np.ndarray) -> tuple[np.ndarray, float | None]:
    """Even grid through keyframe ``times`` (the smallest spacing) and its rate; the keys
    themselves and None when they do not lie on such a grid."""
    from meshseq.formats.caches import fps_from_times

    if len(times) < 2:
        return times, None
    steps = np.diff(times)
    step = float(steps[steps > 0].min()) if (steps > 0).any() else 0.0
    if step <= 0:
        return times, None
    k = (times - times[0]) / step
    n = int(round(k[-1])) + 1
    if np.abs(k - np.round(k)).max() > 1e-3 or n > 100_000:
        return times, None
    grid = times[0] + np.arange(n) * step
    grid[np.round(k).astype(np.int64)] = times  # the keys exactly
    return grid, fps_from_times(grid)


def load_gltf(path: Path, mesh_name: str | None, *, name: str | None):
    """Read ``path`` (.glb/.gltf); ``mesh_name`` picks a mesh when several have morph targets.

    Returns a validated :class:`meshseq.io.MeshSequence` (vertices ``(T, V, 3)``, faces ``(F, 3)``).
    """
    import pygltflib

    from meshseq.meshfiles import _one_line

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            doc = pygltflib.GLTF2().load(str(path))
    except Exception as exc:
        raise MeshseqError(f"{path}: cannot read glTF ({_one_line(exc)})") from None
    if doc is None:
        raise MeshseqError(f"{path}: cannot read glTF (not a glTF/GLB file?)")
    try:
        return _read_document(doc, path, mesh_name, name)
    except (TypeError, ValueError, IndexError, KeyError, AttributeError) as exc:
        # a field of the wrong type or a missing one (pygltflib does not check the document)
        raise MeshseqError(f"{path}: malformed glTF document ({_one_line(exc)})") from None


def _read_document(doc, path: Path, mesh_name: str | None, name: str | None):
    """The sequence of a parsed glTF document (see :func:`load_gltf`)."""
    from meshseq.meshfiles import _polygons_to_triangles, validate_sequence

    meshes = doc.meshes or []
    morphed = [i for i, m in enumerate(meshes) if m.primitives and all(p.targets for p in m.primitives)]
    label = f"{path}:{mesh_name}" if mesh_name else str(path)
    names = ", ".join(repr(meshes[i].name or f"mesh {i}") for i in morphed)
    if mesh_name:
        pick = [i for i in morphed if (meshes[i].name or f"mesh {i}") == mesh_name]
        if not pick:
            raise MeshseqError(f"{label}: no mesh {mesh_name!r} with morph targets "
                               f"(meshes with morph targets: {names or 'none'})")
        m_index = pick[0]
    else:
        if not morphed:
            raise MeshseqError(f"{path}: no mesh with morph targets ({len(meshes)} meshes); meshseq reads "
                               "animated morph targets (shape keys), not a static mesh or skinning")
        if len(morphed) > 1:
            raise MeshseqError(f"{path}: {len(morphed)} meshes have morph targets ({names}); pick one as "
                               f"{path}:MESH_NAME")
        m_index = morphed[0]
    mesh = meshes[m_index]
    buffers = _Buffers(doc, path)

    bases, targets, faces = [], [], []
    offset = 0
    n_targets = len(mesh.primitives[0].targets)
    for p_i, prim in enumerate(mesh.primitives):
        mode = 4 if prim.mode is None else prim.mode
        if mode != 4:
            raise MeshseqError(f"{label}: primitive {p_i} has mode {mode}; only triangles (mode 4) are supported")
        pos_index = prim.attributes.POSITION
        if pos_index is None:
            raise MeshseqError(f"{label}: primitive {p_i} has no POSITION")
        base = _accessor(doc, buffers, pos_index, path).astype(np.float64)
        if len(prim.targets) != n_targets:
            raise MeshseqError(f"{label}: primitive {p_i} has {len(prim.targets)} morph targets, "
                               f"primitive 0 has {n_targets}")
        tgt = np.zeros((n_targets,) + base.shape)
        for k, t in enumerate(prim.targets):
            t_pos = t.get("POSITION") if isinstance(t, dict) else getattr(t, "POSITION", None)
            if t_pos is not None:
                tgt[k] = _accessor(doc, buffers, t_pos, path)
        if prim.indices is None:
            idx = np.arange(len(base), dtype=np.int64)
        else:
            idx = _accessor(doc, buffers, prim.indices, path).astype(np.int64)
        if len(idx) % 3:
            raise MeshseqError(f"{label}: primitive {p_i} has {len(idx)} indices, not a multiple of 3")
        tris, _ = _polygons_to_triangles(idx, None, path)
        bases.append(base)
        targets.append(tgt)
        faces.append(tris + offset)
        offset += len(base)
    base = np.concatenate(bases)
    target = np.concatenate(targets, axis=1)  # (K, V, 3)
    faces_all = np.concatenate(faces)

    nodes = {i for i, n in enumerate(doc.nodes or []) if n.mesh == m_index}
    found = []
    for a_i, anim in enumerate(doc.animations or []):
        for ch in anim.channels:
            if ch.target is not None and ch.target.path == "weights" and ch.target.node in nodes:
                found.append((a_i, anim, anim.samplers[ch.sampler]))
                break
    if not found:
        raise MeshseqError(f"{label}: no animation drives the morph weights of mesh "
                           f"{mesh.name or m_index!r}; nothing to read as frames")
    a_i, anim, sampler = found[0]
    if len(found) > 1:
        warnings.warn(f"{label}: {len(found)} animations drive the mesh; reading the first, "
                      f"{anim.name or a_i!r}", MeshseqWarning, stacklevel=3)
    times = _accessor(doc, buffers, sampler.input, path).astype(np.float64)
    values = _accessor(doc, buffers, sampler.output, path).astype(np.float64).reshape(-1)
    interp = sampler.interpolation or "LINEAR"
    per_key = n_targets * (3 if interp == "CUBICSPLINE" else 1)
    if len(values) != len(times) * per_key:
        raise MeshseqError(f"{label}: animation {anim.name or a_i!r} has {len(values)} weight values for "
                           f"{len(times)} keys of {n_targets} targets ({interp})")
    if len(times) > 1 and np.any(np.diff(times) <= 0):
        raise MeshseqError(f"{label}: animation {anim.name or a_i!r} key times are not increasing")
    values = values.reshape(len(times), 3, n_targets) if interp == "CUBICSPLINE" \
        else values.reshape(len(times), n_targets)
    grid, fps = _time_grid(times)
    if fps is None and len(times) > 1:
        warnings.warn(f"{label}: animation keys are not evenly spaced; the frames are its {len(times)} "
                      "keys and the frame rate is unknown", MeshseqWarning, stacklevel=3)
    n_verts = len(base)
    with np.errstate(over="ignore", invalid="ignore"):  # overflow -> inf, named by validate_sequence
        weights = _sample_weights(times, values, interp, grid)  # (T, K)
        vertices = base[None] + (weights @ target.reshape(n_targets, -1)).reshape(len(grid), n_verts, 3)

    # merge vertices that the exporter split but that coincide in every frame (meshseq's own
    # files are written unsplit: they are read as they are, duplicates in the data included)
    vertex_map = None
    written_by_meshseq = (getattr(doc.asset, "generator", None) or "").startswith("meshseq")
    first = np.arange(n_verts)
    if not written_by_meshseq:
        flat = np.ascontiguousarray(vertices.transpose(1, 0, 2)).reshape(n_verts, -1)
        _, first, inverse = np.unique(flat, axis=0, return_index=True, return_inverse=True)
    if len(first) < n_verts:
        new_of_unique = np.empty(len(first), dtype=np.int64)
        new_of_unique[np.argsort(first)] = np.arange(len(first))
        faces_all = new_of_unique[inverse.reshape(-1)[faces_all]]
        vertex_map = np.sort(first)
        vertices = vertices[:, vertex_map]
        warnings.warn(f"{label}: merged {n_verts - len(first)} vertices that the exporter split (seams) "
                      f"and that coincide in every frame; {len(first)} remain", MeshseqWarning, stacklevel=3)
    seq_name = name or mesh.name or path.stem
    return validate_sequence(vertices, faces_all, name=seq_name, source=label, fps=fps, vertex_map=vertex_map)
