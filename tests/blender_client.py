"""Blender-side half of tests/test_blender.py: run inside Blender, never by pytest.

    blender -b --factory-startup --python tests/blender_client.py -- COMMAND OUT_DIR [ARGS]

Commands (all files go to / come from OUT_DIR):

* ``make``: build a deforming mesh (an icosphere with three animated shape keys, Bezier keys,
  frames 1..FRAMES at 24 fps), save its evaluated positions per frame as ``blender_positions.npy``
  ``(T, V, 3)`` and its polygons as ``blender_faces.npy`` ``(F, 3)``, and export it with Blender's
  own exporters: ``anim.mdd`` (io_shape_mdd), ``anim.pc2`` (io_export_pc2, world space, no x90
  rotation), ``anim.glb`` (io_scene_gltf2, y-up, shape keys as morph targets) and the base mesh
  ``base.obj`` (wm.obj_export, no axis change).
* ``import-mdd BASE.obj CACHE.mdd FRAMES``: import the base mesh (no axis change), apply the MDD
  with Blender's importer from frame 0, save evaluated local positions of frames 0..FRAMES-1 as
  ``imported_mdd.npy``.
* ``import-glb FILE.glb FRAMES``: import with Blender's glTF importer, save evaluated local
  positions of FRAMES frames from the first key as ``imported_glb.npy``.

Debian's Blender 3.4 glTF importer uses ``numpy.bool`` (gone since numpy 1.24), hence the alias.
"""

import sys
from pathlib import Path

import bpy
import numpy

if not hasattr(numpy, "bool"):  # numpy 1.24-1.26 (Debian's); numpy 2 has it back
    numpy.bool = bool  # Blender 3.4's glTF importer still uses it
np = numpy

FPS = 24


def evaluated_positions(obj, frames) -> np.ndarray:
    """Local positions ``(len(frames), V, 3)`` of ``obj``'s evaluated mesh at each frame."""
    scene = bpy.context.scene
    out = []
    for f in frames:
        scene.frame_set(f)
        dg = bpy.context.evaluated_depsgraph_get()
        mesh = obj.evaluated_get(dg).to_mesh()
        co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
        mesh.vertices.foreach_get("co", co)
        out.append(co.reshape(-1, 3).astype(np.float64))
        obj.evaluated_get(dg).to_mesh_clear()
    return np.stack(out)


def clear_scene():
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj, do_unlink=True)


def select_only(obj):
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj


def make(out: Path, n_frames: int) -> None:
    clear_scene()
    scene = bpy.context.scene
    scene.render.fps = FPS
    scene.frame_start, scene.frame_end = 1, n_frames
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=3, radius=1.0)
    obj = bpy.context.active_object
    obj.name = "Blob"
    mesh = obj.data
    n = len(mesh.vertices)
    co = np.empty(n * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    obj.shape_key_add(name="Basis")
    shapes = {
        "stretch": co * np.array([1.0, 1.0, 1.6], np.float32),
        "bulge": co + 0.3 * co * (co[:, :1] > 0),
        "twist": np.stack([co[:, 0] * np.cos(co[:, 2]) - co[:, 1] * np.sin(co[:, 2]),
                           co[:, 0] * np.sin(co[:, 2]) + co[:, 1] * np.cos(co[:, 2]), co[:, 2]], 1),
    }
    for k, (name, pos) in enumerate(shapes.items()):
        key = obj.shape_key_add(name=name)
        key.data.foreach_set("co", np.ascontiguousarray(pos, np.float32).ravel())
        # each key rises and falls at its own pace (Bezier in between the keys)
        for f in range(1, n_frames + 1, 3):
            key.value = float(0.5 + 0.5 * np.sin(0.4 * f + 2.0 * k))
            key.keyframe_insert("value", frame=f)
    select_only(obj)
    frames = list(range(1, n_frames + 1))
    np.save(out / "blender_positions.npy", evaluated_positions(obj, frames))
    poly = np.empty(len(mesh.polygons) * 3, np.int64)
    mesh.polygons.foreach_get("vertices", poly)
    np.save(out / "blender_faces.npy", poly.reshape(-1, 3))

    for module in ("io_shape_mdd", "io_export_pc2"):
        bpy.ops.preferences.addon_enable(module=module)
    scene.frame_set(1)
    bpy.ops.export_shape.mdd(filepath=str(out / "anim.mdd"), fps=FPS, frame_start=1, frame_end=n_frames)
    bpy.ops.export_shape.pc2(filepath=str(out / "anim.pc2"), range_start=1, range_end=n_frames, sampling="1",
                             world_space=True, rot_x90=False, apply_modifiers=True)
    scene.frame_set(1)
    bpy.ops.export_scene.gltf(filepath=str(out / "anim.glb"), export_format="GLB", use_selection=True,
                              export_yup=True, export_animations=True, export_morph=True,
                              export_morph_normal=False, export_force_sampling=True)
    bpy.ops.wm.obj_export(filepath=str(out / "base.obj"), export_selected_objects=True,
                          export_animation=False, apply_modifiers=False, export_uv=False,
                          export_normals=False, export_materials=False, forward_axis="Y", up_axis="Z")


def import_mdd(out: Path, base: str, cache: str, n_frames: int) -> None:
    clear_scene()
    bpy.ops.preferences.addon_enable(module="io_shape_mdd")
    bpy.ops.wm.obj_import(filepath=base, forward_axis="Y", up_axis="Z")
    obj = bpy.context.selected_objects[0]
    select_only(obj)
    bpy.ops.import_shape.mdd(filepath=cache, frame_start=0, frame_step=1)
    np.save(out / "imported_mdd.npy", evaluated_positions(obj, range(n_frames)))


def import_glb(out: Path, glb: str, n_frames: int) -> None:
    clear_scene()
    bpy.context.scene.render.fps = FPS
    bpy.ops.import_scene.gltf(filepath=glb)
    obj = [o for o in bpy.context.scene.objects if o.type == "MESH"][0]
    action = obj.data.shape_keys.animation_data.action
    first = int(round(action.frame_range[0]))
    np.save(out / "imported_glb.npy", evaluated_positions(obj, range(first, first + n_frames)))
    np.save(out / "imported_glb_world.npy", np.array(obj.matrix_world))


def main() -> None:
    argv = sys.argv[sys.argv.index("--") + 1:]
    command, out = argv[0], Path(argv[1])
    if command == "make":
        make(out, int(argv[2]))
    elif command == "import-mdd":
        import_mdd(out, argv[2], argv[3], int(argv[4]))
    elif command == "import-glb":
        import_glb(out, argv[2], int(argv[3]))
    else:
        raise SystemExit(f"unknown command {command}")
    print("BLENDER_CLIENT_OK")


main()
