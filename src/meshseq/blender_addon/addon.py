"""meshseq inside Blender: train, complete, predict and sample mesh animations from the 3D view.

This is the source of the Blender add-on that ``meshseq blender-addon -o meshseq_addon.zip``
packs as ``meshseq_blender/__init__.py`` (beside ``cachefiles.py``); meshseq itself never
imports it (it needs ``bpy``).

Everything heavy runs in the ``meshseq`` command, in a subprocess (its path is an add-on
preference), so Blender's Python needs nothing beyond Blender: no torch, no numpy. Data goes
through files meshseq reads and writes: the object's evaluated animation as a PC2 point cache
(float32 local positions, one sample a frame) with an OBJ base mesh beside it (the polygons
fan-triangulated, so every frame and every object gets the same triangles), and meshseq's
results as PC2 (one result) or folders of binary PLY frames (K samples), read here with
``struct``/``array``. Results go onto a COPY of the object (its evaluated mesh at the first
frame, transform and materials) as a shape-key animation: one shape key a frame, its value keyed
1 on its frame and 0 on the neighbouring ones (linear in between).

Sidebar of the 3D view (N), tab "meshseq". A failure of meshseq shows as an operator report
with meshseq's one-line error.
"""

bl_info = {
    "name": "meshseq",
    "author": "meshseq",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "3D View > Sidebar > meshseq",
    "description": "Learn a mesh animation (ACAP features + bidirectional LSTM) and complete, "
                   "continue or vary it with the meshseq command",
    "category": "Animation",
}

import array
import atexit
import os
import shlex
import shutil
import subprocess
import tempfile
import time

import bpy
from bpy.props import BoolProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from .cachefiles import AddonError, read_pc2, read_ply_folder, write_obj, write_pc2

#: the meshseq command the add-on runs unless its preferences say otherwise
#: (``meshseq blender-addon`` writes the path of the meshseq that made the zip here)
DEFAULT_MESHSEQ = "meshseq"


# --------------------------------------------------------------------------------------------
# the object's animation


def evaluated_coords(obj, depsgraph) -> array.array:
    """Local positions (3 V float32) of ``obj``'s evaluated mesh in ``depsgraph``."""
    ob_eval = obj.evaluated_get(depsgraph)
    mesh = ob_eval.to_mesh()
    try:
        co = array.array("f", bytes(12 * len(mesh.vertices)))
        mesh.vertices.foreach_get("co", co)
    finally:
        ob_eval.to_mesh_clear()
    return co


def sample_animation(context, obj, frames) -> list:
    """The evaluated positions of ``obj`` at each of ``frames`` (shape keys, Mesh Cache, armatures,
    any modifiers), the scene's current frame restored after; AddonError if the count changes."""
    scene = context.scene
    current = scene.frame_current
    out = []
    try:
        for f in frames:
            scene.frame_set(f)
            co = evaluated_coords(obj, context.evaluated_depsgraph_get())
            if out and len(co) != len(out[0]):
                raise AddonError(f"{obj.name}: its evaluated mesh has {len(out[0]) // 3} vertices at frame "
                                 f"{frames[0]} but {len(co) // 3} at frame {f}; meshseq needs a fixed mesh")
            out.append(co)
    finally:
        scene.frame_set(current)
    return out


def triangles_of(obj, depsgraph) -> tuple:
    """``(triangles, n_vertices)`` of the evaluated mesh: every polygon fanned from its first
    corner (the same triangles whatever the pose); AddonError if a vertex is in no face."""
    ob_eval = obj.evaluated_get(depsgraph)
    mesh = ob_eval.to_mesh()
    try:
        n = len(mesh.vertices)
        tris, used = [], bytearray(n)
        for poly in mesh.polygons:
            v = poly.vertices
            for i in range(1, len(v) - 1):
                tris.append((v[0], v[i], v[i + 1]))
            for i in v:
                used[i] = 1
    finally:
        ob_eval.to_mesh_clear()
    loose = n - sum(used)
    if not tris:
        raise AddonError(f"{obj.name}: the mesh has no faces")
    if loose:
        raise AddonError(f"{obj.name}: {loose} of its {n} vertices are in no face; meshseq needs every vertex "
                         "in a face (delete loose vertices)")
    return tris, n


def export_animation(context, obj, frames, folder: str, name: str) -> str:
    """Write ``obj``'s animation over ``frames`` as ``folder/name.pc2`` with ``name.obj`` beside it."""
    if obj is None or obj.type != "MESH":
        raise AddonError("select a mesh object (the active object is not a mesh)")
    tris, n = triangles_of(obj, context.evaluated_depsgraph_get())
    coords = sample_animation(context, obj, frames)
    if len(coords[0]) != 3 * n:
        raise AddonError(f"{obj.name}: its evaluated mesh changes its vertex count between frames")
    cache = os.path.join(folder, name + ".pc2")
    write_pc2(cache, coords, n)
    write_obj(os.path.join(folder, name + ".obj"), coords[0], tris)
    return cache


def safe_name(text: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in text) or "mesh"


# --------------------------------------------------------------------------------------------
# running meshseq


def meshseq_command(context) -> str:
    prefs = context.preferences.addons[__name__].preferences
    return bpy.path.abspath(prefs.meshseq_path.strip()) if prefs.meshseq_path.strip() else DEFAULT_MESHSEQ


def child_env() -> dict:
    """The environment for meshseq: Blender's own Python settings left out."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONHOME", "PYTHONPATH", "PYTHONSTARTUP")}


def error_line(stderr: str, returncode: int) -> str:
    """meshseq's one-line error (the last ``meshseq: error:`` line, else the last line)."""
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("meshseq: error:")]
    if errors:
        return errors[-1]
    return lines[-1] if lines else f"meshseq exited with status {returncode}"


def not_found(exe: str) -> AddonError:
    return AddonError(f"cannot run the meshseq command {exe!r}: set its path in Edit > Preferences > "
                      "Add-ons > meshseq")


def run_meshseq(context, args: list, workdir: str) -> str:
    """Run ``meshseq ARGS`` to the end; its stdout, or AddonError with its one-line error (the
    temporary ``workdir`` left out of the paths it names)."""
    exe = meshseq_command(context)
    try:
        proc = subprocess.run([exe, *args], capture_output=True, text=True, env=child_env())
    except OSError:
        raise not_found(exe) from None
    if proc.returncode != 0:
        raise AddonError(error_line(proc.stderr, proc.returncode).replace(workdir + os.sep, ""))
    return proc.stdout


def model_folder(context) -> str:
    """The model (run folder) of the scene's settings, as an absolute path."""
    path = context.scene.meshseq.run_dir.strip()
    if not path:
        raise AddonError("set the model folder first (meshseq panel > Model)")
    if path.startswith("//") and not bpy.data.filepath:
        return os.path.join(tempfile.gettempdir(), path[2:] or "meshseq_run")
    return os.path.normpath(bpy.path.abspath(path))


class TrainJob:
    """One ``meshseq train`` in the background: start, ``poll()``, ``cancel()``."""

    def __init__(self, args: list, run_dir: str, iterations: int, workdir: str, exe: str):
        self.run_dir, self.iterations, self.workdir = run_dir, iterations, workdir
        self.iteration, self.state, self.message = 0, "running", "starting meshseq train"
        self.started = time.monotonic()
        self.out = open(os.path.join(workdir, "stdout.txt"), "w")
        self.err = open(os.path.join(workdir, "stderr.txt"), "w")
        try:
            self.proc = subprocess.Popen([exe, *args], stdout=self.out, stderr=self.err, env=child_env())
        except OSError:
            self._close()
            raise not_found(exe) from None
        atexit.register(self.cancel)  # Blender quitting stops the training

    @property
    def progress(self) -> float:
        """Percent of the iterations done."""
        return 100.0 * min(self.iteration, self.iterations) / max(self.iterations, 1)

    def _read_iteration(self) -> None:
        """The iteration of metrics.csv's last complete row (its first column)."""
        try:
            with open(os.path.join(self.run_dir, "metrics.csv"), "rb") as fh:
                fh.seek(max(0, fh.seek(0, os.SEEK_END) - 4096))
                lines = fh.read().split(b"\n")[:-1]  # the part after the last newline may be torn
        except OSError:
            return
        if lines and not lines[-1].startswith(b"iteration,"):
            try:
                self.iteration = max(self.iteration, int(lines[-1].split(b",", 1)[0]))
            except ValueError:
                pass  # the tail's first line cut in the middle

    def poll(self) -> str:
        """Update ``iteration``, ``state`` (running, done, failed, cancelled) and ``message``."""
        if self.state != "running":
            return self.state
        self._read_iteration()
        code = self.proc.poll()
        seconds = time.monotonic() - self.started
        if code is None:
            self.message = (f"training {self.progress:.0f}% (iteration {self.iteration}/{self.iterations}, "
                            f"{seconds:.0f} s)" if self.iteration else
                            f"training: starting ({seconds:.0f} s; the first run compiles meshseq's kernels)")
            return self.state
        self._close()
        if code == 0:
            self.state, self.iteration = "done", self.iterations
            self.message = f"trained {self.iterations} iterations in {seconds:.0f} s: {self.run_dir}"
        else:
            with open(os.path.join(self.workdir, "stderr.txt")) as fh:
                self.state, self.message = "failed", error_line(fh.read(), code)
        shutil.rmtree(self.workdir, ignore_errors=True)
        return self.state

    def cancel(self) -> None:
        """Stop meshseq (SIGTERM: it removes its temporary outputs) and mark the job cancelled."""
        if self.state != "running":
            return
        self.proc.terminate()
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._read_iteration()
        self._close()
        self.state = "cancelled"
        self.message = f"training cancelled at iteration {self.iteration}"
        shutil.rmtree(self.workdir, ignore_errors=True)

    def _close(self) -> None:
        self.out.close()
        self.err.close()


#: the training job of this Blender session (one at a time)
JOB = None


def training_objects(context) -> list:
    """The active mesh object first, then the other selected mesh objects."""
    active = context.active_object
    if active is None or active.type != "MESH":
        raise AddonError("select a mesh object (the active object is not a mesh)")
    others = [o for o in context.selected_objects if o.type == "MESH" and o != active]
    return [active, *others]


def start_training(context) -> TrainJob:
    """Export the selected objects' animations and start ``meshseq train`` on them."""
    global JOB
    if JOB is not None and JOB.poll() == "running":
        raise AddonError("meshseq is already training (cancel it first)")
    s = context.scene.meshseq
    run_dir = model_folder(context)
    if os.path.isdir(run_dir) and os.listdir(run_dir) and not s.replace:
        raise AddonError(f"the model folder {run_dir} is not empty: tick 'Replace model' to train a new model "
                         "there")
    scene = context.scene
    frames = list(range(scene.frame_start, scene.frame_end + 1))
    if len(frames) < 4:
        raise AddonError(f"the scene has {len(frames)} frames; training needs an animation of at least 4")
    workdir = tempfile.mkdtemp(prefix="meshseq_train_")
    try:
        caches = [export_animation(context, obj, frames, workdir, f"{i:02d}_{safe_name(obj.name)}")
                  for i, obj in enumerate(training_objects(context))]
        config = os.path.join(workdir, "train.toml")  # all frames train; a progress row every <= 10 iterations
        with open(config, "w") as fh:
            fh.write(f"holdout = 0.0\nlog_every = {max(1, min(10, s.iterations // 100))}\n")
        args = ["train", *caches, "--out", run_dir, "--iterations", str(s.iterations), "--window", str(s.window),
                "--batch", str(s.batch), "--config", config, "--no-progress", *(["--force"] if s.replace else []),
                *shlex.split(s.train_args)]
        JOB = TrainJob(args, run_dir, s.iterations, workdir, meshseq_command(context))
    except BaseException:
        shutil.rmtree(workdir, ignore_errors=True)
        raise
    return JOB


# --------------------------------------------------------------------------------------------
# results: copies of the object with one shape key a frame


def add_frame_keys(obj, coords: list, first_frame: int) -> None:
    """Shape keys ``frame_NNNN`` on ``obj`` holding ``coords[i]`` at frame ``first_frame + i``:
    each keyed 1 on its frame and 0 on the frames before and after (linear in between)."""
    obj.shape_key_add(name="Basis", from_mix=False)
    blocks = []
    for i, co in enumerate(coords):
        kb = obj.shape_key_add(name=f"frame_{first_frame + i:04d}", from_mix=False)
        kb.data.foreach_set("co", co)
        kb.value = 0.0
        blocks.append(kb)
    keys = obj.data.shape_keys
    action = bpy.data.actions.new(f"{obj.name}_meshseq")
    keys.animation_data_create().action = action
    last = first_frame + len(coords) - 1
    for f, kb in enumerate(blocks, first_frame):
        points = [(p, 1.0 if p == f else 0.0) for p in (f - 1, f, f + 1) if first_frame <= p <= last]
        fc = action.fcurves.new(f'key_blocks["{kb.name}"].value', action_group="meshseq")
        fc.keyframe_points.add(len(points))
        fc.keyframe_points.foreach_set("co", [c for p in points for c in p])
        for kp in fc.keyframe_points:
            kp.interpolation = "LINEAR"
        fc.update()


def make_copy(context, source, coords: list, first_frame: int, suffix: str, offset: float = 0.0):
    """A new object: ``source``'s evaluated mesh at ``first_frame`` (materials kept), its
    transform moved ``offset`` along world X, animated with ``coords`` from ``first_frame``."""
    scene = context.scene
    current = scene.frame_current
    scene.frame_set(first_frame)
    try:
        ob_eval = source.evaluated_get(context.evaluated_depsgraph_get())
        mesh = bpy.data.meshes.new_from_object(ob_eval)
    finally:
        scene.frame_set(current)
    if 3 * len(mesh.vertices) != len(coords[0]):
        bpy.data.meshes.remove(mesh)
        raise AddonError(f"{source.name}: meshseq returned {len(coords[0]) // 3} vertices a frame for its "
                         "mesh of a different size")
    mesh.name = f"{source.name}_{suffix}"
    obj = bpy.data.objects.new(mesh.name, mesh)
    obj.matrix_world = source.matrix_world.copy()
    obj.matrix_world.translation.x += offset
    collection = source.users_collection[0] if source.users_collection else context.collection
    collection.objects.link(obj)
    add_frame_keys(obj, coords, first_frame)
    return obj


def select_only(context, objects: list) -> None:
    for o in context.selected_objects:
        o.select_set(False)
    for o in objects:
        o.select_set(True)
    context.view_layer.objects.active = objects[0]


def marker_frames(context) -> list:
    """The frames of the scene's timeline markers, sorted, at least two."""
    frames = sorted({m.frame for m in context.scene.timeline_markers})
    if len(frames) < 2:
        raise AddonError(f"mark at least two keyframes with timeline markers (M in the timeline); "
                         f"the scene has {len(frames)}")
    return frames


def complete(context, samples: int, seed: int) -> list:
    """Complete the active object between the marked keyframes; ``samples`` copies (side by side
    when several). Returns the new objects."""
    obj = context.active_object
    keys = marker_frames(context)
    run_dir = model_folder(context)
    workdir = tempfile.mkdtemp(prefix="meshseq_complete_")
    try:
        data = export_animation(context, obj, list(range(keys[0], keys[-1] + 1)), workdir, safe_name(obj.name))
        args = ["complete", run_dir, data, "--keyframes", ",".join(str(k - keys[0]) for k in keys)]
        if samples == 1:
            out = os.path.join(workdir, "completed.pc2")
            run_meshseq(context, [*args, "-o", out], workdir)
            results = [read_pc2(out)]
        else:
            out = os.path.join(workdir, "samples")
            run_meshseq(context, [*args, "--samples", str(samples), "--seed", str(seed), "--format", "ply", "-o", out],
                        workdir)
            results = [read_ply_folder(os.path.join(out, d)) for d in sorted(os.listdir(out))
                       if os.path.isdir(os.path.join(out, d))]
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    if samples == 1:
        return [make_copy(context, obj, results[0], keys[0], "completed")]
    spacing = 1.25 * max(obj.dimensions.x, 1e-3)
    return [make_copy(context, obj, r, keys[0], f"sample_{i:02d}", spacing * (i + 1)) for i, r in enumerate(results)]


def predict(context, frames: int, given: int) -> list:
    """Continue the active object ``frames`` frames after the current one, given the ``given``
    frames up to the current one (those from the scene's first frame on, where it starts later).
    Returns the new object (in a list)."""
    obj = context.active_object
    current = context.scene.frame_current
    first = min(current, max(current - given + 1, context.scene.frame_start))
    given = current - first + 1
    run_dir = model_folder(context)
    workdir = tempfile.mkdtemp(prefix="meshseq_predict_")
    try:
        data = export_animation(context, obj, list(range(first, current + 1)), workdir, safe_name(obj.name))
        out = os.path.join(workdir, "predicted.pc2")
        run_meshseq(context, ["predict", run_dir, data, "--given", str(given), "--frames", str(frames), "-o", out],
                    workdir)
        coords = read_pc2(out)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    return [make_copy(context, obj, coords, first, "predicted")]


# --------------------------------------------------------------------------------------------
# Blender classes


class MeshseqPreferences(bpy.types.AddonPreferences):
    bl_idname = __name__

    meshseq_path: StringProperty(
        name="meshseq command", subtype="FILE_PATH", default=DEFAULT_MESHSEQ,
        description="The meshseq command the add-on runs (a path, or a name on PATH)")

    def draw(self, context):
        self.layout.prop(self, "meshseq_path")


class MeshseqSettings(bpy.types.PropertyGroup):
    run_dir: StringProperty(name="Model", subtype="DIR_PATH", default="//meshseq_run",
                            description="The training run folder meshseq trains into and synthesizes from")
    iterations: IntProperty(name="Iterations", default=2000, min=1, description="training iterations")
    window: IntProperty(name="Window", default=32, min=2, description="frames per training window")
    batch: IntProperty(name="Batch", default=8, min=1, description="windows per iteration")
    replace: BoolProperty(name="Replace model", default=False,
                          description="train a new model in a model folder that already holds one")
    train_args: StringProperty(name="Options", default="",
                               description="further options of `meshseq train`, e.g. --latent 64 --threads 2")
    frames: IntProperty(name="Frames", default=24, min=1, description="frames to predict after the current one")
    given: IntProperty(name="Given", default=3, min=1,
                       description="frames up to the current one given to the model (from 2 on it follows their "
                       "direction and pace)")
    samples: IntProperty(name="Samples", default=4, min=2, max=32, description="diverse completions to make")
    seed: IntProperty(name="Seed", default=0, min=0, description="seed of the samples' random initial states")


class _MeshseqOperator:
    """Reports AddonError (and any other failure) as one line, never a traceback."""

    @classmethod
    def poll(cls, context):
        return context.active_object is not None and context.active_object.type == "MESH"

    def execute(self, context):
        try:
            return self.run(context)
        except AddonError as err:
            self.report({"ERROR"}, str(err))
        except Exception as err:  # noqa: BLE001 - shown as a report, not a traceback
            self.report({"ERROR"}, f"meshseq add-on: {type(err).__name__}: {err}".splitlines()[0])
        return {"CANCELLED"}


class MESHSEQ_OT_train(_MeshseqOperator, bpy.types.Operator):
    """Train a meshseq model on the animation of the selected mesh objects (in the background)"""

    bl_idname = "meshseq.train"
    bl_label = "Train"
    _timer = None

    def run(self, context):  # execute: trains to the end (scripts, background mode)
        job = start_training(context)
        while job.poll() == "running":
            time.sleep(0.2)
        return self.finish(context, job)

    def invoke(self, context, event):
        if bpy.app.background:
            return self.execute(context)
        try:
            start_training(context)
        except AddonError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.5, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        state = JOB.poll()
        context.window_manager.meshseq_progress = JOB.progress
        context.workspace.status_text_set(f"meshseq: {JOB.message}" if state == "running" else None)
        for area in context.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()
        if state == "running":
            return {"PASS_THROUGH"}
        context.window_manager.event_timer_remove(self._timer)
        return self.finish(context, JOB)

    def finish(self, context, job):
        context.window_manager.meshseq_progress = job.progress
        if job.state == "done":
            self.report({"INFO"}, f"meshseq: {job.message}")
            return {"FINISHED"}
        self.report({"ERROR"} if job.state == "failed" else {"WARNING"}, job.message)
        return {"CANCELLED"}


class MESHSEQ_OT_cancel(bpy.types.Operator):
    """Stop the training in progress"""

    bl_idname = "meshseq.cancel"
    bl_label = "Cancel"

    @classmethod
    def poll(cls, context):
        return JOB is not None and JOB.state == "running"

    def execute(self, context):
        JOB.cancel()
        self.report({"WARNING"}, f"meshseq: {JOB.message}")
        return {"FINISHED"}


class MESHSEQ_OT_complete(_MeshseqOperator, bpy.types.Operator):
    """Fill in the frames between the keyframes marked with timeline markers (on a copy)"""

    bl_idname = "meshseq.complete"
    bl_label = "Complete"
    bl_options = {"REGISTER", "UNDO"}

    def run(self, context):
        objs = complete(context, 1, 0)
        select_only(context, objs)
        self.report({"INFO"}, f"meshseq: completed into {objs[0].name}")
        return {"FINISHED"}


class MESHSEQ_OT_samples(_MeshseqOperator, bpy.types.Operator):
    """Make several different completions between the marked keyframes, side by side"""

    bl_idname = "meshseq.samples"
    bl_label = "Diverse completions"
    bl_options = {"REGISTER", "UNDO"}

    def run(self, context):
        s = context.scene.meshseq
        objs = complete(context, s.samples, s.seed)
        select_only(context, objs)
        self.report({"INFO"}, f"meshseq: {len(objs)} completions, {objs[0].name} ...")
        return {"FINISHED"}


class MESHSEQ_OT_predict(_MeshseqOperator, bpy.types.Operator):
    """Continue the animation after the current frame (on a copy)"""

    bl_idname = "meshseq.predict"
    bl_label = "Predict"
    bl_options = {"REGISTER", "UNDO"}

    def run(self, context):
        s = context.scene.meshseq
        objs = predict(context, s.frames, s.given)
        select_only(context, objs)
        self.report({"INFO"}, f"meshseq: predicted {s.frames} frames into {objs[0].name}")
        return {"FINISHED"}


class MESHSEQ_PT_panel(bpy.types.Panel):
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "meshseq"
    bl_label = "meshseq"

    def draw(self, context):
        layout, s = self.layout, context.scene.meshseq
        obj = context.active_object
        layout.label(text=obj.name if obj and obj.type == "MESH" else "Select a mesh object", icon="MESH_DATA")
        layout.prop(s, "run_dir", text="")
        self.draw_train(context, layout.box(), s)
        box = layout.box()
        keys = sorted({m.frame for m in context.scene.timeline_markers})
        box.label(text="Keys " + (", ".join(map(str, keys)) if keys else "(add markers)"), icon="MARKER_HLT")
        box.operator("meshseq.complete", icon="IPO_BEZIER")
        col = box.column(align=True)
        col.prop(s, "samples")
        col.prop(s, "seed")
        box.operator("meshseq.samples", icon="MOD_ARRAY")
        box = layout.box()
        box.label(text=f"After frame {context.scene.frame_current}", icon="TRACKING_FORWARDS")
        col = box.column(align=True)
        col.prop(s, "frames")
        col.prop(s, "given")
        box.operator("meshseq.predict", icon="PLAY")

    @staticmethod
    def draw_train(context, box, s):
        scene = context.scene
        box.label(text=f"Train on frames {scene.frame_start}-{scene.frame_end}", icon="MOD_ARRAY")
        if JOB is not None and JOB.state == "running":
            row = box.row()
            row.enabled = False
            row.prop(context.window_manager, "meshseq_progress", text="Training", slider=True)
            box.label(text=f"iteration {JOB.iteration}/{JOB.iterations}")
            box.operator("meshseq.cancel", icon="CANCEL")
            return
        col = box.column(align=True)
        col.prop(s, "iterations")
        col.prop(s, "window")
        col.prop(s, "batch")
        box.prop(s, "train_args", text="", icon="OPTIONS")
        box.prop(s, "replace")
        n = len([o for o in context.selected_objects if o.type == "MESH"]) or 1
        box.operator("meshseq.train", text=f"Train on {n} object{'s' * (n > 1)}", icon="PLAY")
        if JOB is not None:
            box.label(text=JOB.message)


CLASSES = (MeshseqPreferences, MeshseqSettings, MESHSEQ_OT_train, MESHSEQ_OT_cancel, MESHSEQ_OT_complete,
           MESHSEQ_OT_samples, MESHSEQ_OT_predict, MESHSEQ_PT_panel)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.meshseq = PointerProperty(type=MeshseqSettings)
    bpy.types.WindowManager.meshseq_progress = FloatProperty(name="Progress", subtype="PERCENTAGE",
                                                             min=0.0, max=100.0)


def unregister():
    if JOB is not None:
        JOB.cancel()
    del bpy.types.WindowManager.meshseq_progress
    del bpy.types.Scene.meshseq
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
