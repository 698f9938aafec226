"""The Blender side of the extension: preferences, the sidebar panel, its operators (``bpy``).

Fit (``torchfit.fit``) checks the selection (a mesh with vertex groups, deformed by an
armature; a saved file; the interpreter), exports the mesh and its armature with Blender's USD
exporter into the job folder (``//torchfit/<mesh>/rig.usda``, the chosen action over the frame
range), starts torchfit in the background (:mod:`.job`) and a modal timer operator
(``torchfit.watch``) that polls it twice a second on Blender's main thread without waiting on
it (the work runs in another process), so the UI stays responsive. When the run ends the
result is imported (``torchfit.import_result``): the simulated frames on a copy of the mesh
(``/Simulated`` of ``usd/frames.usda``, a Mesh Sequence Cache), the fitted modulus as the
point attribute ``youngsModulus`` on a rest copy from ``usd/material.usda``, with a material
that shows it through a colour ramp. A failure is one line in the status bar and the panel,
the scene unchanged. ``wait=True`` runs a fit or simulation to its end inside the operator
(headless Blender has no event loop for the modal operator; tests use it).
"""
from __future__ import annotations

from pathlib import Path

import bpy

from . import job as jobs
from .command import (CommandError, FitSettings, JobFolder, find_interpreter, fit_command,
                      simulate_command)
from .results import read_progress, read_summary

ADDON = __package__
ATTRIBUTE = "youngsModulus"
MODELS = [("corotated", "Corotated", ""), ("linear", "Linear", ""),
          ("stable_neo_hookean", "Stable Neo-Hookean", "")]
_DEFAULTS = FitSettings()
#: the running process of each scene (one at a time), by scene name
_RUNNING: dict[str, tuple[jobs.Job, str, str]] = {}


class TorchfitError(Exception):
    """A check that failed: one line for the status bar and the panel."""


# -- preferences and settings -------------------------------------------------------------------
class TorchfitPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON

    repository: bpy.props.StringProperty(name="torchfit repository", subtype="DIR_PATH",
                                         description="The torchfit checkout (holds experiments/fit.py)")
    interpreter: bpy.props.StringProperty(
        name="Python interpreter", subtype="FILE_PATH",
        description="torchfit's Python; empty: <repository>/.venv/bin/python")

    def draw(self, context):
        self.layout.prop(self, "repository")
        self.layout.prop(self, "interpreter")


class TorchfitSettings(bpy.types.PropertyGroup):
    action: bpy.props.StringProperty(name="Action", description="The armature's action to fit ("
                                     "empty: the one it has)")
    frame_start: bpy.props.IntProperty(name="Start", default=_DEFAULTS.frame_start)
    frame_end: bpy.props.IntProperty(name="End", default=_DEFAULTS.frame_end)
    held_out: bpy.props.StringProperty(name="Held out", description="Frames held out of the "
                                       "fit for validation, e.g. 12,24")
    model: bpy.props.EnumProperty(name="Model", items=MODELS, default=_DEFAULTS.model)
    grid_nodes: bpy.props.IntProperty(name="Grid nodes", default=_DEFAULTS.grid_nodes, min=8)
    iterations: bpy.props.IntProperty(name="Iterations", default=_DEFAULTS.iterations, min=1)
    dynamic: bpy.props.BoolProperty(name="In time", default=_DEFAULTS.dynamic,
                                    description="Inertia and damping; off: quasistatic")
    tet_edge_length: bpy.props.FloatProperty(name="Tet edge", default=_DEFAULTS.tet_edge_length,
                                             min=0.005, max=0.5)
    threads: bpy.props.IntProperty(name="Threads", default=_DEFAULTS.threads, min=0)
    job_folder: bpy.props.StringProperty(name="Job folder", subtype="DIR_PATH",
                                         description="Empty: //torchfit/<mesh> beside the file")
    simulate_action: bpy.props.StringProperty(name="Shot", description="Another action of the "
                                              "rig to simulate with the fitted material")
    # what the panel shows (written by the operators)
    state: bpy.props.StringProperty(name="State", default="")
    error: bpy.props.StringProperty(name="Error", default="")
    iteration: bpy.props.IntProperty(default=-1)
    misfit: bpy.props.FloatProperty(default=0.0)
    surface_error_mm: bpy.props.FloatProperty(default=0.0)
    progress: bpy.props.FloatProperty(default=0.0, min=0.0, max=1.0, subtype="FACTOR")
    log: bpy.props.StringProperty(default="")
    summary: bpy.props.StringProperty(default="")
    modulus_min: bpy.props.FloatProperty(default=0.0)
    modulus_max: bpy.props.FloatProperty(default=0.0)
    modulus_unit: bpy.props.StringProperty(default="")
    last_run: bpy.props.StringProperty(default="")


def _settings(context) -> TorchfitSettings:
    return context.scene.torchfit


def _preferences(context):
    addon = context.preferences.addons.get(ADDON)
    return addon.preferences if addon else None


def _tool(context) -> tuple[Path, Path]:
    prefs = _preferences(context)
    repository = bpy.path.abspath(prefs.repository) if prefs and prefs.repository else ""
    if not repository:
        raise TorchfitError("set the extension's preference 'torchfit repository' "
                            "(Edit > Preferences > Add-ons > torchfit)")
    try:
        interpreter = find_interpreter(repository, bpy.path.abspath(prefs.interpreter)
                                       if prefs.interpreter else "")
    except CommandError as error:
        raise TorchfitError(str(error)) from None
    return Path(repository), interpreter


# -- the selection and the export -----------------------------------------------------------------
def _rig(context):
    """The selected skinned mesh and its armature (checked: one line for each problem)."""
    mesh = context.active_object
    if mesh is None or mesh.type != "MESH":
        raise TorchfitError("select the skinned mesh (a mesh object) to fit")
    armature = next((m.object for m in mesh.modifiers if m.type == "ARMATURE" and m.object), None)
    if armature is None and mesh.parent is not None and mesh.parent.type == "ARMATURE":
        armature = mesh.parent
    if armature is None:
        raise TorchfitError(f"mesh {mesh.name} has no armature: parent it to one "
                            "(Parent > With Automatic Weights)")
    if not mesh.vertex_groups:
        raise TorchfitError(f"mesh {mesh.name} has no skin weights (vertex groups): "
                            "parent it With Automatic Weights or paint them")
    return mesh, armature


def _job_folder(context, mesh, suffix: str = "") -> JobFolder:
    settings = _settings(context)
    if not bpy.data.is_saved and not settings.job_folder:
        raise TorchfitError("save the .blend file first (the run folder goes beside it), "
                            "or set the panel's job folder")
    root = bpy.path.abspath(settings.job_folder or f"//torchfit/{bpy.path.clean_name(mesh.name)}")
    return JobFolder(Path(root + suffix))


def _held_out(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(x) for x in text.replace(";", ",").split(",") if x.strip())
    except ValueError:
        raise TorchfitError(f"held-out frames '{text}': write frame numbers separated by "
                            "commas") from None


def _export(context, mesh, armature, path: Path, frames: tuple[int, int], action_name: str,
            animation: bool = True) -> None:
    """The mesh and its armature with Blender's USD exporter (only they; the scene's frame
    range and the armature's action restored after)."""
    scene = context.scene
    action = bpy.data.actions.get(action_name) if action_name else None
    if action_name and action is None:
        raise TorchfitError(f"no action named {action_name}: pick one of the rig's actions")
    kept_range, kept_frame = (scene.frame_start, scene.frame_end), scene.frame_current
    kept_action = armature.animation_data.action if armature.animation_data else None
    selected = [o for o in context.view_layer.objects if o.select_get()]
    active = context.view_layer.objects.active
    try:
        if action is not None:
            armature.animation_data_create().action = action
        scene.frame_start, scene.frame_end = frames
        for o in selected:
            o.select_set(False)
        mesh.select_set(True)
        armature.select_set(True)
        context.view_layer.objects.active = mesh
        path.parent.mkdir(parents=True, exist_ok=True)
        bpy.ops.wm.usd_export(filepath=str(path), selected_objects_only=True,
                              export_animation=animation, export_armatures=True,
                              only_deform_bones=True, export_materials=False,
                              export_shapekeys=False, convert_scene_units="METERS")
    finally:
        if armature.animation_data:
            armature.animation_data.action = kept_action
        scene.frame_start, scene.frame_end = kept_range
        scene.frame_set(kept_frame)
        for o in context.view_layer.objects:
            o.select_set(o in selected)
        context.view_layer.objects.active = active


# -- importing a result -----------------------------------------------------------------------------
def _import_new(context, path: Path, **options) -> list:
    before = set(bpy.data.objects)
    bpy.ops.wm.usd_import(filepath=str(path), import_skeletons=False, import_materials=False,
                          create_collection=False, set_frame_range=False, **options)
    return [o for o in bpy.data.objects if o not in before]


def _remove(objects) -> None:
    for o in objects:
        data = o.data
        bpy.data.objects.remove(o)
        if data is not None and data.users == 0 and isinstance(data, bpy.types.Mesh):
            bpy.data.meshes.remove(data)


def modulus_material(low: float, high: float) -> bpy.types.Material:
    """A material colouring the point attribute ``youngsModulus`` from ``low`` (blue) to
    ``high`` (red) through a colour ramp (shown in Material Preview and rendered)."""
    material = bpy.data.materials.get("torchfit modulus") or bpy.data.materials.new("torchfit modulus")
    material.use_nodes = True
    nodes, links = material.node_tree.nodes, material.node_tree.links
    nodes.clear()
    attribute = nodes.new("ShaderNodeAttribute")
    attribute.attribute_type, attribute.attribute_name = "GEOMETRY", ATTRIBUTE
    scale = nodes.new("ShaderNodeMapRange")
    scale.inputs["From Min"].default_value = low
    scale.inputs["From Max"].default_value = high if high > low else low + 1.0
    ramp = nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = (0.05, 0.15, 0.8, 1.0)
    ramp.color_ramp.elements[1].color = (0.85, 0.1, 0.05, 1.0)
    middle = ramp.color_ramp.elements.new(0.5)
    middle.color = (0.95, 0.95, 0.9, 1.0)
    shader = nodes.new("ShaderNodeBsdfPrincipled")
    out = nodes.new("ShaderNodeOutputMaterial")
    links.new(attribute.outputs["Fac"], scale.inputs["Value"])
    links.new(scale.outputs["Result"], ramp.inputs["Fac"])
    links.new(ramp.outputs["Color"], shader.inputs["Base Color"])
    links.new(shader.outputs["BSDF"], out.inputs["Surface"])
    for x, node in enumerate((attribute, scale, ramp, shader, out)):
        node.location = (300 * x, 0)
    return material


def import_result(context, run: Path, mesh_name: str, with_material: bool = True) -> list:
    """``/Simulated`` of the run's ``usd/frames.usda`` as ``<mesh> simulated`` (a Mesh Sequence
    Cache), and with ``with_material`` the rest mesh of ``usd/material.usda`` as
    ``<mesh> modulus`` with its ``youngsModulus`` attribute and the colour material (also
    on the simulated copy). Nothing is left in the scene if any step fails."""
    frames = run / "usd" / "frames.usda"
    if not frames.is_file():
        raise TorchfitError(f"{frames} is missing: the run did not finish (see its fit.log)")
    made = []
    selected = [o for o in context.view_layer.objects if o.select_get()]
    active = context.view_layer.objects.active
    try:
        made += _import_new(context, frames, prim_path_mask="/Simulated")
        simulated = next((o for o in made if o.type == "MESH"), None)
        if simulated is None:
            raise TorchfitError(f"{frames} holds no /Simulated mesh")
        _remove([o for o in made if o is not simulated])
        made = [simulated]
        simulated.name = f"{mesh_name} simulated"
        if with_material:
            material_file = run / "usd" / "material.usda"
            new = _import_new(context, material_file, read_mesh_attributes=True)
            made += new
            carrier = next((o for o in new if o.type == "MESH" and ATTRIBUTE in o.data.attributes),
                           None)
            if carrier is None:
                raise TorchfitError(f"{material_file} holds no mesh with {ATTRIBUTE}")
            _remove([o for o in new if o is not carrier])
            made = [simulated, carrier]
            carrier.name = f"{mesh_name} modulus"
            for modifier in list(carrier.modifiers):
                carrier.modifiers.remove(modifier)
            values = [v.value for v in carrier.data.attributes[ATTRIBUTE].data]
            settings = _settings(context)
            settings.modulus_min, settings.modulus_max = min(values), max(values)
            summary = read_summary(run)
            settings.modulus_unit = summary.units if summary else ""
            material = modulus_material(min(values), max(values))
            for obj in (carrier, simulated):
                obj.data.materials.clear()
                obj.data.materials.append(material)
            if len(simulated.data.vertices) == len(values):
                simulated.data.attributes.new(ATTRIBUTE, "FLOAT", "POINT").data.foreach_set(
                    "value", values)
        return made
    except Exception:
        _remove(made)
        raise
    finally:                                # the user's selection, as before the import
        for o in context.view_layer.objects:
            o.select_set(o in selected)
        context.view_layer.objects.active = active


# -- running -----------------------------------------------------------------------------------------
def _show_progress(settings, run: Path, max_iter: int) -> None:
    progress = read_progress(run, max_iter)
    settings.iteration = progress.iteration
    settings.misfit = progress.misfit or 0.0
    settings.surface_error_mm = 1000 * (progress.surface_error or 0.0)
    settings.progress = progress.fraction
    settings.log = "\n".join(progress.log[-4:])


def _show_summary(settings, run: Path) -> None:
    summary = read_summary(run)
    if summary is None:
        return
    held = (f", held out {1000 * summary.held_out_error:.3g} mm"
            if summary.held_out_error is not None else "")
    reduction = f"{summary.reduction:.3g}x" if summary.reduction is not None else "-"
    determined = {True: "determined", False: "not determined", None: "determination unknown"}
    lines = [f"surface error {1000 * summary.surface_error:.3g} mm{held}",
             f"{reduction} below the homogeneous material, {determined[summary.determined]}",
             f"modulus {summary.units}; {summary.iterations} iterations ({summary.stop_reason})"]
    lines += [f"warning: {w}" for w in summary.warnings]
    settings.summary = "\n".join(lines)


def finish(context, job: jobs.Job, kind: str, mesh_name: str) -> str | None:
    """After the process ended: the summary and the import (a fit, a simulation), or the
    error line; returns the error line or ``None``."""
    settings = _settings(context)
    status = job.poll()
    settings.last_run = str(job.run)
    if kind == "fit":
        _show_progress(settings, job.run, settings.iterations)
    if status == 143:
        settings.state, settings.error = "cancelled (Fit resumes it)", ""
        return None
    if status != 0:
        settings.state, settings.error = "failed", job.error_line() or f"exit status {status}"
        return settings.error
    try:
        if kind == "fit":
            _show_summary(settings, job.run)
        import_result(context, job.run, mesh_name, with_material=(kind == "fit"))
    except TorchfitError as error:
        settings.state, settings.error = "failed", str(error)
        return settings.error
    settings.state, settings.error = "done", ""
    return None


def _launch(operator, context, job: jobs.Job, kind: str, mesh_name: str, wait: bool):
    settings = _settings(context)
    settings.state, settings.error, settings.summary = f"{kind} running", "", ""
    if wait:
        job.wait()
        error = finish(context, job, kind, mesh_name)
        if error:
            operator.report({"ERROR"}, error)
            return {"CANCELLED"}
        return {"FINISHED"}
    _RUNNING[context.scene.name] = (job, kind, mesh_name)
    if not bpy.app.background and context.window is not None:   # headless: no event loop
        bpy.ops.torchfit.watch("INVOKE_DEFAULT")
    return {"FINISHED"}


class TORCHFIT_OT_fit(bpy.types.Operator):
    """Export the selected skinned mesh and its armature and fit its material with torchfit
    (a cancelled run resumes)"""

    bl_idname = "torchfit.fit"
    bl_label = "Fit"
    bl_options = {"REGISTER"}

    wait: bpy.props.BoolProperty(default=False, options={"HIDDEN", "SKIP_SAVE"})
    from_paint: bpy.props.BoolProperty(name="From the painted modulus", default=False,
                                       options={"SKIP_SAVE"})

    def execute(self, context):
        settings = _settings(context)
        if context.scene.name in _RUNNING:
            self.report({"ERROR"}, "a torchfit run is going on: wait or cancel it")
            return {"CANCELLED"}
        try:
            repository, interpreter = _tool(context)
            mesh, armature = _rig(context)
            folder = _job_folder(context, mesh, "_painted" if self.from_paint else "")
            fit = FitSettings(frame_start=settings.frame_start, frame_end=settings.frame_end,
                              held_out=_held_out(settings.held_out), model=settings.model,
                              grid_nodes=settings.grid_nodes, iterations=settings.iterations,
                              dynamic=settings.dynamic, tet_edge_length=settings.tet_edge_length,
                              threads=settings.threads)
            resume = (folder.run / "checkpoint.pt").is_file() and \
                not (folder.run / "result.json").is_file()
            if self.from_paint:
                if ATTRIBUTE not in mesh.data.attributes:
                    raise TorchfitError(f"mesh {mesh.name} has no {ATTRIBUTE} point attribute "
                                        "to start from: import a result or add and paint one")
                fit.init_field = str(folder.painted)
            if (folder.run / "result.json").is_file():
                raise TorchfitError(f"{folder.run} holds a finished fit: set another job "
                                    "folder (or delete it) to fit again")
            command = fit_command(fit, folder, repository, interpreter, resume=resume)
            if not resume:
                _export(context, mesh, armature, folder.rig,
                        (settings.frame_start, settings.frame_end), settings.action)
                if self.from_paint:
                    _export(context, mesh, armature, folder.painted,
                            (settings.frame_start, settings.frame_start), "", animation=False)
        except (TorchfitError, CommandError) as error:
            settings.error = str(error)
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        job = jobs.start(command, repository, folder.run, folder.console)
        return _launch(self, context, job, "fit", mesh.name, self.wait)


class TORCHFIT_OT_simulate(bpy.types.Operator):
    """Simulate another action of the rig with the fitted material and import it"""

    bl_idname = "torchfit.simulate"
    bl_label = "Simulate shot"

    wait: bpy.props.BoolProperty(default=False, options={"HIDDEN", "SKIP_SAVE"})

    def execute(self, context):
        settings = _settings(context)
        try:
            repository, interpreter = _tool(context)
            mesh, armature = _rig(context)
            fit_run = Path(settings.last_run) if settings.last_run else _job_folder(context, mesh).run
            if not (fit_run / "params.pt").is_file():
                raise TorchfitError("no finished fit to simulate with: Fit first")
            action = bpy.data.actions.get(settings.simulate_action)
            if action is None:
                raise TorchfitError(f"no action named '{settings.simulate_action}': pick the "
                                    "shot to simulate")
            shot = JobFolder(fit_run.parent / f"shot_{bpy.path.clean_name(action.name)}")
            if shot.root.exists():
                n = 2
                while Path(f"{shot.root}_{n}").exists():
                    n += 1
                shot = JobFolder(Path(f"{shot.root}_{n}"))
            start, end = (int(round(f)) for f in action.frame_range)
            _export(context, mesh, armature, shot.rig, (start, end), action.name)
            command = simulate_command(fit_run, shot.rig, shot.run, repository, interpreter)
        except (TorchfitError, CommandError) as error:
            settings.error = str(error)
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        job = jobs.start(command, repository, shot.run, shot.console)
        return _launch(self, context, job, "simulate", mesh.name, self.wait)


def poll_running(operator, context) -> bool:
    """One look at the scene's running process (the watch operator's timer step): the
    panel's progress from its files; when it has ended, :func:`finish` (errors reported
    through ``operator``). Whether it still runs."""
    entry = _RUNNING.get(context.scene.name)
    if entry is None:
        return False
    job, kind, mesh_name = entry
    if kind == "fit":
        _show_progress(_settings(context), job.run, _settings(context).iterations)
    if job.running:
        return True
    del _RUNNING[context.scene.name]
    error = finish(context, job, kind, mesh_name)
    if error and operator is not None:
        operator.report({"ERROR"}, error)
    return False


class TORCHFIT_OT_watch(bpy.types.Operator):
    """Poll the running torchfit process (a modal timer: the UI stays responsive)"""

    bl_idname = "torchfit.watch"
    bl_label = "Watch torchfit"
    bl_options = {"INTERNAL"}

    _timer = None

    def invoke(self, context, event):
        self._timer = context.window_manager.event_timer_add(0.5, window=context.window)
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        running = poll_running(self, context)
        for area in context.screen.areas if context.screen else []:
            area.tag_redraw()
        return {"PASS_THROUGH"} if running else self._stop(context)

    def _stop(self, context):
        context.window_manager.event_timer_remove(self._timer)
        for area in context.screen.areas if context.screen else []:
            area.tag_redraw()
        return {"FINISHED"}


class TORCHFIT_OT_cancel(bpy.types.Operator):
    """Stop the running fit (SIGTERM; Fit resumes it from its last iteration)"""

    bl_idname = "torchfit.cancel"
    bl_label = "Cancel"

    def execute(self, context):
        entry = _RUNNING.pop(context.scene.name, None)
        if entry is None:
            self.report({"WARNING"}, "no torchfit run is going on")
            return {"CANCELLED"}
        entry[0].cancel()
        _settings(context).state = "cancelled (Fit resumes it)"
        return {"FINISHED"}


class TORCHFIT_OT_import_result(bpy.types.Operator):
    """Import the last run's simulated frames and fitted modulus"""

    bl_idname = "torchfit.import_result"
    bl_label = "Import result"

    def execute(self, context):
        settings = _settings(context)
        try:
            mesh, _ = _rig(context)
            run = Path(settings.last_run) if settings.last_run else _job_folder(context, mesh).run
            import_result(context, run, mesh.name)
        except TorchfitError as error:
            settings.error = str(error)
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        return {"FINISHED"}


class TORCHFIT_OT_modulus_to_mesh(bpy.types.Operator):
    """Copy the imported modulus (<mesh> modulus) onto the selected mesh's youngsModulus point
    attribute, to paint it and fit again from it"""

    bl_idname = "torchfit.modulus_to_mesh"
    bl_label = "Modulus to mesh"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        try:
            mesh, _ = _rig(context)
            source = bpy.data.objects.get(f"{mesh.name} modulus")
            if source is None or ATTRIBUTE not in source.data.attributes:
                raise TorchfitError(f"no imported '{mesh.name} modulus': fit or Import result first")
            if len(source.data.vertices) != len(mesh.data.vertices):
                raise TorchfitError(f"'{source.name}' has {len(source.data.vertices)} points, "
                                    f"{mesh.name} {len(mesh.data.vertices)}: not this mesh's result")
        except TorchfitError as error:
            _settings(context).error = str(error)
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        values = [0.0] * len(source.data.vertices)
        source.data.attributes[ATTRIBUTE].data.foreach_get("value", values)
        target = mesh.data.attributes.get(ATTRIBUTE) or \
            mesh.data.attributes.new(ATTRIBUTE, "FLOAT", "POINT")
        target.data.foreach_set("value", values)
        mesh.data.update()
        return {"FINISHED"}


class VIEW3D_PT_torchfit(bpy.types.Panel):
    bl_label = "torchfit"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "torchfit"

    def draw(self, context):
        settings, layout = _settings(context), self.layout
        obj = context.active_object
        layout.label(text=f"Mesh: {obj.name}" if obj else "Select the skinned mesh",
                     icon="MESH_DATA")
        column = layout.column(align=True)
        column.prop(settings, "action")
        row = column.row(align=True)
        row.prop(settings, "frame_start")
        row.prop(settings, "frame_end")
        column.prop(settings, "held_out")
        column.prop(settings, "model")
        column.prop(settings, "grid_nodes")
        column.prop(settings, "iterations")
        column.prop(settings, "dynamic")
        column.prop(settings, "tet_edge_length")
        column.prop(settings, "job_folder")
        row = layout.row(align=True)
        row.operator("torchfit.fit", icon="PLAY")
        row.operator("torchfit.cancel", icon="CANCEL")
        if settings.state:
            layout.label(text=settings.state)
        if settings.iteration >= 0:
            layout.progress(factor=settings.progress,
                            text=f"iteration {settings.iteration}/{settings.iterations}")
            layout.label(text=f"misfit {settings.misfit:.4g}, "
                              f"surface error {settings.surface_error_mm:.3g} mm")
        for line in settings.log.splitlines():
            layout.label(text=line)
        if settings.error:
            layout.label(text=settings.error, icon="ERROR")
        for line in settings.summary.splitlines():
            layout.label(text=line)
        if settings.modulus_max > 0:
            layout.label(text=f"modulus {settings.modulus_min:.3g} .. {settings.modulus_max:.3g} "
                              f"({settings.modulus_unit})", icon="COLOR")
        layout.operator("torchfit.import_result", icon="IMPORT")
        layout.operator("torchfit.modulus_to_mesh", icon="BRUSH_DATA")
        layout.operator("torchfit.fit", text="Fit from painted modulus",
                        icon="BRUSH_DATA").from_paint = True
        layout.prop(settings, "simulate_action")
        layout.operator("torchfit.simulate", icon="RENDER_ANIMATION")


CLASSES = (TorchfitPreferences, TorchfitSettings, TORCHFIT_OT_fit, TORCHFIT_OT_simulate,
           TORCHFIT_OT_watch, TORCHFIT_OT_cancel, TORCHFIT_OT_import_result,
           TORCHFIT_OT_modulus_to_mesh, VIEW3D_PT_torchfit)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.torchfit = bpy.props.PointerProperty(type=TorchfitSettings)


def unregister() -> None:
    for entry in list(_RUNNING.values()):
        entry[0].cancel()
    _RUNNING.clear()
    del bpy.types.Scene.torchfit
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
