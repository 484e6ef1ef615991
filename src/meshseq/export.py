"""glTF 2.0 export of a mesh sequence as one animated mesh (.glb).

The first frame is the mesh; every later frame is a morph target (its position and normal
offsets from the first frame), and an animation drives the morph weights: at time ``t / fps``
target ``t`` has weight 1 and all others 0, linearly interpolated in between, so a player
shows frame after frame. Blender imports it as shape keys with an action; three.js, Babylon.js
and the Khronos sample viewers play it in a browser.

:func:`gltf_document` and :func:`glb_bytes` are pure (arrays in, document or bytes out);
:func:`save_glb` writes a file atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from meshseq.errors import MeshseqError
from meshseq.mesh import vertex_normals

_ARRAY_BUFFER = 34962
_ELEMENT_ARRAY_BUFFER = 34963
_FLOAT = 5126
_UNSIGNED_SHORT = 5123
_UNSIGNED_INT = 5125
_TRIANGLES = 4


def _up_rotation(up: str) -> list[float] | None:
    """Quaternion ``[x, y, z, w]`` turning the data's ``up`` axis into glTF's +y (None for y)."""
    table = {
        "y": None,
        "-y": [1.0, 0.0, 0.0, 0.0],  # 180 degrees about x
        "z": [-np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)],  # -90 degrees about x: +z -> +y
        "-z": [np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)],
        "x": [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)],  # +90 degrees about z: +x -> +y
        "-x": [0.0, 0.0, -np.sqrt(0.5), np.sqrt(0.5)],
    }
    key = up.lower().lstrip("+")
    if key not in table:
        raise MeshseqError(f"--up {up!r}: expected one of x, y, z, -x, -y, -z")
    q = table[key]
    return None if q is None else [float(c) for c in q]


def _unit_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Float32 unit normals ``(T, V, 3)``; a vertex without one (no or degenerate faces) gets +y."""
    n = vertex_normals(vertices, faces).astype(np.float32)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(length > 1e-6, n / np.maximum(length, 1e-30), np.array([0.0, 1.0, 0.0], np.float32))
    return n.astype(np.float32)


def gltf_document(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    fps: float = 24.0,
    name: str = "sequence",
    normals: bool = True,
    up: str = "y",
):
    """A ``pygltflib.GLTF2`` document (binary blob attached) of ``vertices (T, V, 3)`` with
    ``faces (F, 3)``: frame 0 as the mesh, frames 1..T-1 as morph targets named ``frame_t``,
    and (for T > 1) one animation ``name`` of T keyframes at ``fps`` driving their weights.

    ``normals``: also store vertex normals (and their per-frame offsets), for smooth shading.
    ``up``: the data's up axis; a node rotation makes it glTF's +y.
    """
    import pygltflib as gl

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 3 or v.shape[-1] != 3 or v.shape[0] < 1 or v.shape[1] < 1:
        raise MeshseqError(f"{name}: vertices must be (T, V, 3) with T, V >= 1, got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] < 1:
        raise MeshseqError(f"{name}: faces must be (F, 3) with F >= 1, got {f.shape}")
    if f.min() < 0 or f.max() >= v.shape[1]:
        raise MeshseqError(f"{name}: faces index vertices outside 0..{v.shape[1] - 1}")
    if not np.all(np.isfinite(v)):
        t = int(np.argmax(~np.isfinite(v).reshape(v.shape[0], -1).all(axis=1)))
        raise MeshseqError(f"{name}: frame {t} has non-finite vertex coordinates")
    if not (np.isfinite(fps) and fps > 0):
        raise MeshseqError(f"--fps {fps}: must be a positive number")
    rotation = _up_rotation(up)
    n_frames, n_verts = v.shape[:2]

    blob = bytearray()
    views: list = []
    accessors: list = []

    def add(array: np.ndarray, component: int, kind: str, target: int | None, minmax: bool) -> int:
        data = np.ascontiguousarray(array)
        while len(blob) % 4:
            blob.append(0)
        views.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=data.nbytes, target=target))
        blob.extend(data.tobytes())
        count = data.size if kind == "SCALAR" else data.shape[0]
        acc = gl.Accessor(bufferView=len(views) - 1, byteOffset=0, componentType=component, count=count, type=kind)
        if minmax:
            flat = data.reshape(count, -1)
            acc.min = [float(x) for x in flat.min(axis=0)]
            acc.max = [float(x) for x in flat.max(axis=0)]
        accessors.append(acc)
        return len(accessors) - 1

    pos = v.astype(np.float32)
    nrm = _unit_normals(v, f) if normals else None
    index_type = np.uint16 if n_verts <= 65535 else np.uint32
    index_component = _UNSIGNED_SHORT if index_type is np.uint16 else _UNSIGNED_INT

    i_idx = add(f.astype(index_type).reshape(-1), index_component, "SCALAR", _ELEMENT_ARRAY_BUFFER, False)
    i_pos = add(pos[0], _FLOAT, "VEC3", _ARRAY_BUFFER, True)
    attributes = gl.Attributes(POSITION=i_pos)
    if nrm is not None:
        attributes.NORMAL = add(nrm[0], _FLOAT, "VEC3", _ARRAY_BUFFER, False)
    targets = []
    for t in range(1, n_frames):
        target = {"POSITION": add(pos[t] - pos[0], _FLOAT, "VEC3", _ARRAY_BUFFER, True)}
        if nrm is not None:
            target["NORMAL"] = add(nrm[t] - nrm[0], _FLOAT, "VEC3", _ARRAY_BUFFER, False)
        targets.append(target)

    primitive = gl.Primitive(attributes=attributes, indices=i_idx, mode=_TRIANGLES, material=0)
    material = gl.Material(
        name="clay",
        doubleSided=True,
        pbrMetallicRoughness=gl.PbrMetallicRoughness(
            baseColorFactor=[0.60, 0.65, 0.72, 1.0], metallicFactor=0.0, roughnessFactor=0.8
        ),
    )
    mesh = gl.Mesh(name=name, primitives=[primitive])
    if targets:
        primitive.targets = targets
        mesh.weights = [0.0] * len(targets)
        mesh.extras = {"targetNames": [f"frame_{t}" for t in range(1, n_frames)]}
    node = gl.Node(name=name, mesh=0, rotation=rotation)

    animations = []
    if targets:
        times = (np.arange(n_frames, dtype=np.float64) / fps).astype(np.float32)
        weights = np.zeros((n_frames, n_frames - 1), dtype=np.float32)
        weights[np.arange(1, n_frames), np.arange(n_frames - 1)] = 1.0
        i_time = add(times, _FLOAT, "SCALAR", None, True)
        i_weight = add(weights.reshape(-1), _FLOAT, "SCALAR", None, False)
        animations.append(
            gl.Animation(
                name=name,
                samplers=[gl.AnimationSampler(input=i_time, output=i_weight, interpolation="LINEAR")],
                channels=[gl.AnimationChannel(sampler=0, target=gl.AnimationChannelTarget(node=0, path="weights"))],
            )
        )

    while len(blob) % 4:
        blob.append(0)
    doc = gl.GLTF2(
        asset=gl.Asset(version="2.0", generator="meshseq"),
        scene=0,
        scenes=[gl.Scene(name=name, nodes=[0])],
        nodes=[node],
        meshes=[mesh],
        materials=[material],
        accessors=accessors,
        bufferViews=views,
        buffers=[gl.Buffer(byteLength=len(blob))],
        animations=animations,
    )
    doc.set_binary_blob(bytes(blob))
    return doc


def glb_bytes(vertices: np.ndarray, faces: np.ndarray, **kwargs) -> bytes:
    """The .glb file content of :func:`gltf_document` (same arguments)."""
    return b"".join(gltf_document(vertices, faces, **kwargs).save_to_bytes())


def save_glb(
    path: str | os.PathLike,
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    force: bool = False,
    **kwargs,
) -> Path:
    """Write :func:`glb_bytes` to ``path`` (must end in .glb) atomically; returns the path."""
    from meshseq.meshfiles import atomic_output

    target = Path(path)
    if target.suffix.lower() != ".glb":
        raise MeshseqError(f"{target}: a glTF export must end in .glb")
    data = glb_bytes(vertices, faces, **kwargs)  # build fully before touching the file system
    with atomic_output(target, force=force) as tmp:
        tmp.write_bytes(data)
    return target
