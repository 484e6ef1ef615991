"""Blender-side half of tests/test_blender_addon.py: run inside Blender, never by pytest.

    blender -b --factory-startup --python tests/blender_addon_client.py -- COMMAND OUT_DIR ZIP MESHSEQ RUN

Every command installs and enables the add-on from ZIP (in the user folders that the test points
BLENDER_USER_CONFIG / BLENDER_USER_SCRIPTS at), sets its meshseq command to MESHSEQ, builds an
animated icosphere "Blob" (642 vertices, three shape keys keyed over frames 1..FRAMES) and saves
its evaluated positions as ``source.npy`` ``(FRAMES, V, 3)`` and triangles as ``faces.npy``.

* ``train``: the Train operator (3 iterations) on Blob and a second animated copy of its mesh
  (both selected) into RUN; then Train again without Replace (its report), and a long training
  into RUN-cancel started and stopped with the Cancel operator.
  Writes ``train.json``.
* ``ops``: Complete between markers KEYS, Predict PRED_FRAMES after frame PRED_AT, K diverse
  completions; saves each copy's evaluated positions (``completed.npy``, ``predicted.npy``,
  ``samples.npy``), the completed copy's shape-key data (``completed_keys.npy``), and the reports
  of the failures (a bad model folder, a mesh of another connectivity, one marker, a missing
  meshseq command) in ``ops.json``.
* ``screenshot`` (windowed Blender, e.g. under Xvfb, opening a saved .blend so that no splash
  screen shows): the picture docs/img/blender_addon.png.
"""

import json
import sys
import time
from pathlib import Path

import bpy
import numpy as np

FRAMES = 24
KEYS = (1, 9, 17)
PRED_AT, PRED_FRAMES, PRED_GIVEN = 10, 6, 3
SAMPLES, SEED = 3, 0


def install(zip_path: str, meshseq: str) -> None:
    bpy.ops.preferences.addon_install(filepath=zip_path, overwrite=True)
    bpy.ops.preferences.addon_enable(module="meshseq_blender")
    bpy.context.preferences.addons["meshseq_blender"].preferences.meshseq_path = meshseq


def evaluated(obj, frames) -> np.ndarray:
    """Local positions ``(len(frames), V, 3)`` of ``obj``'s evaluated mesh (float32 as Blender has them)."""
    out = []
    for f in frames:
        bpy.context.scene.frame_set(f)
        dg = bpy.context.evaluated_depsgraph_get()
        mesh = obj.evaluated_get(dg).to_mesh()
        co = np.empty(len(mesh.vertices) * 3, np.float32)
        mesh.vertices.foreach_get("co", co)
        out.append(co.reshape(-1, 3))
        obj.evaluated_get(dg).to_mesh_clear()
    return np.stack(out)


def select_only(obj) -> None:
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj


def make_blob(name: str, subdivisions: int, location=(0.0, 0.0, 0.0), phase: float = 0.0):
    """An icosphere with three shape keys keyed every 3 frames (Bezier in between), made active."""
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=subdivisions, radius=1.0, location=location)
    obj = bpy.context.active_object
    obj.name = name
    co = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    obj.shape_key_add(name="Basis")
    shapes = [co * np.array([1.0, 1.0, 1.5], np.float32), co + 0.3 * co * (co[:, :1] > 0),
              np.stack([co[:, 0] * np.cos(co[:, 2]) - co[:, 1] * np.sin(co[:, 2]),
                        co[:, 0] * np.sin(co[:, 2]) + co[:, 1] * np.cos(co[:, 2]), co[:, 2]], 1)]
    for k, pos in enumerate(shapes):
        key = obj.shape_key_add(name=f"shape{k}")
        key.data.foreach_set("co", np.ascontiguousarray(pos, np.float32).ravel())
        for f in range(1, FRAMES + 1, 3):
            key.value = float(0.5 + 0.5 * np.sin(0.4 * f + 2.0 * k + phase))
            key.keyframe_insert("value", frame=f)
    select_only(obj)
    return obj


def setup(out: Path, zip_path: str, meshseq: str):
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj, do_unlink=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, FRAMES
    install(zip_path, meshseq)
    blob = make_blob("Blob", 4)
    np.save(out / "source.npy", evaluated(blob, range(1, FRAMES + 1)))
    poly = np.empty(len(blob.data.polygons) * 3, np.int64)
    blob.data.polygons.foreach_get("vertices", poly)
    np.save(out / "faces.npy", poly.reshape(-1, 3))
    scene.frame_set(1)
    return blob


def report_of(op, **kwargs) -> str:
    """The error report of an operator that must fail (bpy.ops raises it as a RuntimeError)."""
    try:
        op(**kwargs)
    except RuntimeError as err:
        return str(err)
    raise AssertionError(f"{op} did not fail")


def train(out: Path, zip_path: str, meshseq: str, run: str) -> None:
    blob = setup(out, zip_path, meshseq)
    make_blob("Blob2", 4, location=(3.0, 0.0, 0.0), phase=1.0)  # a second animation of the same mesh
    blob.select_set(True)
    bpy.context.view_layer.objects.active = blob  # both selected, Blob active
    s = bpy.context.scene.meshseq
    s.run_dir, s.iterations, s.window, s.batch, s.train_args = run, 3, 8, 2, "--threads 1"
    started = time.monotonic()
    assert bpy.ops.meshseq.train() == {"FINISHED"}
    result = {"train_seconds": time.monotonic() - started,
              "not_empty_report": report_of(bpy.ops.meshseq.train)}
    # a long training, cancelled while it runs
    addon = sys.modules["meshseq_blender"]
    s.run_dir, s.iterations, s.replace = run + "-cancel", 100000, True
    job = addon.start_training(bpy.context)
    started = time.monotonic()
    while job.poll() == "running" and job.iteration < 1 and time.monotonic() - started < 240:
        time.sleep(0.2)
    result.update(iteration_before_cancel=job.iteration, progress_message=job.message)
    assert bpy.ops.meshseq.cancel() == {"FINISHED"}
    result.update(cancel_state=job.state, cancel_message=job.message, returncode=job.proc.returncode,
                  workdir_left=Path(job.workdir).exists(), cancel_poll=bpy.ops.meshseq.cancel.poll())
    (out / "train.json").write_text(json.dumps(result))


def ops(out: Path, zip_path: str, meshseq: str, run: str) -> None:
    blob = setup(out, zip_path, meshseq)
    scene = bpy.context.scene
    s = scene.meshseq
    s.run_dir = run
    scene.timeline_markers.new("key", frame=KEYS[0])
    reports = {"one_marker": report_of(bpy.ops.meshseq.complete)}
    for k in KEYS[1:]:
        scene.timeline_markers.new("key", frame=k)
    span = range(KEYS[0], KEYS[-1] + 1)

    assert bpy.ops.meshseq.complete() == {"FINISHED"}
    done = bpy.context.active_object
    assert done.name != blob.name and done.data.shape_keys is not None
    np.save(out / "completed.npy", evaluated(done, span))
    keys = done.data.shape_keys.key_blocks
    stored = []
    for k in KEYS:
        co = np.empty(len(done.data.vertices) * 3, np.float32)
        keys[f"frame_{k:04d}"].data.foreach_get("co", co)
        stored.append(co.reshape(-1, 3))
    np.save(out / "completed_keys.npy", np.stack(stored))
    info = {"completed_name": done.name, "completed_keys": len(keys),
            "completed_world": [list(r) for r in done.matrix_world]}

    select_only(blob)
    scene.frame_set(PRED_AT)
    assert s.given == PRED_GIVEN  # the panel's default
    s.frames = PRED_FRAMES
    assert bpy.ops.meshseq.predict() == {"FINISHED"}
    pred = bpy.context.active_object
    np.save(out / "predicted.npy", evaluated(pred, range(PRED_AT - PRED_GIVEN + 1, PRED_AT + PRED_FRAMES + 1)))
    info["predicted_name"] = pred.name
    select_only(blob)
    scene.frame_set(2)  # one frame after the scene's first: the frames from there are given
    assert bpy.ops.meshseq.predict() == {"FINISHED"}
    np.save(out / "predicted_early.npy", evaluated(bpy.context.active_object, range(1, 2 + PRED_FRAMES + 1)))

    select_only(blob)
    scene.frame_set(1)
    s.samples, s.seed = SAMPLES, SEED
    assert bpy.ops.meshseq.samples() == {"FINISHED"}
    samples = sorted(bpy.context.selected_objects, key=lambda o: o.name)
    np.save(out / "samples.npy", np.stack([evaluated(o, span) for o in samples]))
    info["sample_names"] = [o.name for o in samples]
    info["sample_x"] = [o.matrix_world.translation.x for o in samples]

    select_only(blob)
    s.run_dir = str(Path(run).parent / "no-such-model")
    reports["bad_model"] = report_of(bpy.ops.meshseq.complete)
    s.run_dir = run
    make_blob("Small", 3, location=(4.0, 0.0, 0.0))  # 162 vertices: another connectivity
    reports["other_mesh"] = report_of(bpy.ops.meshseq.complete)
    n_objects = len(bpy.data.objects)
    bpy.context.preferences.addons["meshseq_blender"].preferences.meshseq_path = "/no/such/meshseq"
    reports["no_meshseq"] = report_of(bpy.ops.meshseq.predict)
    info["objects_added_by_failures"] = len(bpy.data.objects) - n_objects
    (out / "ops.json").write_text(json.dumps({**info, "reports": reports}))


def screenshot(out: Path, zip_path: str, meshseq: str, run: str) -> None:
    """Windowed Blender only (under Xvfb, with --enable-event-simulate): the source and SAMPLES
    completions side by side, the sidebar open on the meshseq tab (clicked with a simulated
    event: Blender 3.4 cannot pick a tab from Python); the 3D view saved as
    ``out/blender_addon.png``, then quit."""
    blob = setup(out, zip_path, meshseq)
    scene = bpy.context.scene
    scene.meshseq.run_dir, scene.meshseq.samples = bpy.path.relpath(run), SAMPLES
    for k in KEYS:
        scene.timeline_markers.new(f"F_{k:02d}", frame=k)
    area = next(a for a in bpy.context.screen.areas if a.type == "VIEW_3D")
    area.spaces.active.show_region_ui = True
    window = bpy.context.window

    def override():
        region = next(r for r in area.regions if r.type == "WINDOW")
        return bpy.context.temp_override(window=window, screen=window.screen, area=area, region=region)

    def shoot():
        with override():
            bpy.ops.meshseq.samples()
            select_only(blob)
            scene.frame_set(12)
            bpy.ops.view3d.view_all()
        bpy.app.timers.register(click_tab, first_interval=1.0)

    def click_tab():  # Blender 3.4 cannot pick a sidebar tab from Python: click it (the fourth tab)
        x, y = area.x + area.width - 12, area.y + area.height - 225
        for value in ("PRESS", "RELEASE"):
            window.event_simulate(type="LEFTMOUSE", value=value, x=x, y=y)
        bpy.app.timers.register(save, first_interval=1.5)

    def save():
        with override():
            bpy.ops.screen.screenshot_area(filepath=str(out / "blender_addon.png"))
        print("BLENDER_CLIENT_OK", flush=True)
        bpy.ops.wm.quit_blender()

    bpy.app.timers.register(shoot, first_interval=2.0)


def main() -> None:
    argv = sys.argv[sys.argv.index("--") + 1:]
    command, out, zip_path, meshseq, run = argv[0], Path(argv[1]), argv[2], argv[3], argv[4]
    {"train": train, "ops": ops, "screenshot": screenshot}[command](out, zip_path, meshseq, run)
    if command != "screenshot":
        print("BLENDER_CLIENT_OK")


main()
