"""Interchange formats of animation tools: glTF morph targets, MDD / PC2 point caches, USD.

:func:`meshseq.io.load_sequence` and :func:`meshseq.io.save_sequence` call :func:`load` and
:func:`save` here for these suffixes, so every command reads and writes them:

=====================  =========================================  ===============================
format                 read (DATA spec)                           write (``-o``)
=====================  =========================================  ===============================
glTF morph animation   ``anim.glb``, ``anim.gltf``,               ``out.glb``
                       ``anim.glb:MESH_NAME``
MDD point cache        ``cache.mdd`` (faces from ``cache.obj``    ``out.mdd`` + ``out.obj``
                       beside it) or ``base.obj:cache.mdd``       (the base mesh, frame 0)
PC2 point cache        ``cache.pc2`` / ``base.obj:cache.pc2``     ``out.pc2`` + ``out.obj``
USD                    ``shot.usd(a/c)``,                         ``out.usd``, ``.usda``, ``.usdc``
                       ``shot.usda:/World/Mesh``
=====================  =========================================  ===============================

A point cache holds positions only; its faces come from a base mesh (OBJ/PLY/OFF) with the same
vertices in the same order: ``base.obj:cache.pc2``, or the mesh file with the cache's stem
beside it (``cache.obj``, ``.ply`` or ``.off``), which is what meshseq writes.
"""

from __future__ import annotations

from pathlib import Path

from meshseq.errors import MeshseqError

CACHE_EXTENSIONS = (".mdd", ".pc2")
GLTF_EXTENSIONS = (".glb", ".gltf")
USD_EXTENSIONS = (".usd", ".usda", ".usdc")
#: suffixes of files that can carry an address after a colon (``file:NAME`` / ``file:/prim``)
ADDRESSABLE = GLTF_EXTENSIONS + USD_EXTENSIONS
READ_EXTENSIONS = CACHE_EXTENSIONS + GLTF_EXTENSIONS + USD_EXTENSIONS
WRITE_EXTENSIONS = CACHE_EXTENSIONS + (".glb",) + USD_EXTENSIONS
DEFAULT_FPS = 24.0


def split_address(text: str) -> tuple[str, str, str] | None:
    """``"base.obj:cache.pc2"`` -> ``("cache", "cache.pc2", "base.obj")``;
    ``"anim.glb:Mesh"`` / ``"shot.usda:/World/Mesh"`` -> ``("address", file, name)``;
    None when ``text`` is neither (it is then an ordinary path)."""
    from meshseq.meshfiles import MESH_EXTENSIONS

    colons = [i for i, ch in enumerate(text) if ch == ":"]
    for i in colons:
        left, right = text[:i], text[i + 1:]
        if Path(left).suffix.lower() in MESH_EXTENSIONS and Path(right).suffix.lower() in CACHE_EXTENSIONS:
            return "cache", right, left
    for i in colons:  # the first colon after a glTF/USD file name (mesh names may hold colons)
        if Path(text[:i]).suffix.lower() in ADDRESSABLE:
            return "address", text[:i], text[i + 1:]
    return None


def load(text: str, *, name: str | None = None):
    """Load ``text`` if it is one of this module's formats (file or address); None otherwise.

    Returns a validated :class:`meshseq.io.MeshSequence` ``(T, V, 3)`` / ``(F, 3)``.
    """
    path = Path(text)
    if path.exists() and not path.is_dir():
        suffix = path.suffix.lower()
        if suffix in CACHE_EXTENSIONS:
            return load_cache(path, None, name=name)
        if suffix in GLTF_EXTENSIONS:
            from meshseq.formats.gltf import load_gltf

            return load_gltf(path, None, name=name)
        if suffix in USD_EXTENSIONS:
            from meshseq.formats.usd import load_usd

            return load_usd(path, None, name=name)
        return None
    if path.exists():
        return None
    split = split_address(text)
    if split is None:
        return None
    kind, file, extra = split
    from meshseq.meshfiles import check_input_file

    check_input_file(Path(file))
    if kind == "cache":
        return load_cache(Path(file), Path(extra), name=name)
    if Path(file).suffix.lower() in GLTF_EXTENSIONS:
        from meshseq.formats.gltf import load_gltf

        return load_gltf(Path(file), extra or None, name=name)
    from meshseq.formats.usd import load_usd

    return load_usd(Path(file), extra or None, name=name)


def _find_base(cache: Path) -> Path:
    from meshseq.meshfiles import MESH_EXTENSIONS

    found = [cache.with_suffix(s) for s in MESH_EXTENSIONS if cache.with_suffix(s).is_file()]
    if not found:
        raise MeshseqError(f"{cache}: a point cache holds no faces; give the base mesh as BASE.obj:{cache} "
                           f"or put {cache.with_suffix('.obj').name} beside it")
    if len(found) > 1:
        raise MeshseqError(f"{cache}: several base meshes beside it ({', '.join(p.name for p in found)}); "
                           f"name one as BASE:{cache}")
    return found[0]


def load_cache(cache: Path, base: Path | None, *, name: str | None = None):
    """An MDD/PC2 cache with the faces of the ``base`` mesh file (default: found beside it).

    Returns a validated :class:`meshseq.io.MeshSequence`: vertices ``(T, V, 3)`` from the cache,
    faces ``(F, 3)`` from the base mesh, whose vertex count must be the cache's ``V``.
    """
    from meshseq.formats.caches import fps_from_times, read_mdd, read_pc2
    from meshseq.meshfiles import _check_mesh_path, _read_mesh, validate_sequence

    if base is None:
        base = _find_base(cache)
    _check_mesh_path(base)
    if cache.suffix.lower() == ".mdd":
        vertices, times = read_mdd(cache)
        fps = fps_from_times(times)
    else:
        vertices, _start, _rate = read_pc2(cache)
        fps = None  # PC2 counts frames, not seconds
    frame = _read_mesh(base)
    faces = frame.faces()
    if len(frame.vertices) != vertices.shape[1]:
        raise MeshseqError(f"{cache}: {vertices.shape[1]} points per frame but the base mesh {base} has "
                           f"{len(frame.vertices)} vertices; the cache belongs to another mesh")
    return validate_sequence(vertices, faces, name=name or cache.stem, source=f"{base}:{cache}", fps=fps)


def save(seq, target: Path, *, force: bool = False, up: str = "y", normals: bool = True,
         meters_per_unit: float = 1.0) -> Path:
    """Write ``seq`` to ``target`` in the format of its suffix (one of :data:`WRITE_EXTENSIONS`).

    .mdd / .pc2 also write the base mesh (frame 0 and the faces) as ``target`` with suffix .obj.
    ``up`` is the data's up axis (.glb: a node rotation; USD: the stage's upAxis, y or z);
    ``normals``: .glb only; ``meters_per_unit``: USD only. Returns ``target``.
    """
    from meshseq.meshfiles import _obj_writer, _refuse_existing, atomic_output

    suffix = target.suffix.lower()
    fps = seq.fps or DEFAULT_FPS
    if suffix == ".glb":
        from meshseq.export import save_glb

        return save_glb(target, seq.vertices, seq.faces, force=force, fps=fps, name=seq.name,
                        normals=normals, up=up)
    if suffix in USD_EXTENSIONS:
        from meshseq.formats.usd import save_usd

        return save_usd(target, seq.vertices, seq.faces, fps=fps, name=seq.name, up=up,
                        meters_per_unit=meters_per_unit, force=force)
    if suffix in CACHE_EXTENSIONS:
        from meshseq.formats.caches import mdd_bytes, pc2_bytes

        base = target.with_suffix(".obj")
        _refuse_existing(target, force)
        _refuse_existing(base, force)
        data = mdd_bytes(seq.vertices, fps) if suffix == ".mdd" else pc2_bytes(seq.vertices)
        with atomic_output(base, force=force) as tmp:
            tmp.write_bytes(_obj_writer(seq, 9)(0))
        with atomic_output(target, force=force) as tmp:
            tmp.write_bytes(data)
        return target
    raise MeshseqError(f"{target}: unsupported output extension {suffix!r}")  # pragma: no cover


__all__ = ["load", "save", "load_cache", "split_address", "READ_EXTENSIONS", "WRITE_EXTENSIONS",
           "CACHE_EXTENSIONS", "GLTF_EXTENSIONS", "USD_EXTENSIONS"]
