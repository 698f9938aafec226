"""A headless Blender session with the torchfit extension installed from its built zip (the
subprocess of test_ui.py: ``python extension_session.py job.json``, ``bpy`` as a module).

It installs and enables the zip, builds the ``limb`` rig of tests/helpers/blender_rigs.py,
checks that each error of issue 51 item 6 leaves the scene as it was, fits (``wait=True``),
cancels and resumes a second fit, simulates a second action, fits from a painted attribute,
and writes what it saw to ``<job>.result.json`` (the test asserts on it).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

TESTS = Path(__file__).resolve().parents[2]


def scene_state(bpy) -> list:
    """The scene as names, modifiers, attributes and materials (for 'unchanged' checks)."""
    return sorted([o.name, o.type, [m.type for m in getattr(o, "modifiers", [])],
                   sorted(o.data.attributes.keys()) if o.type == "MESH" else [],
                   [m.name for m in o.data.materials] if o.type == "MESH" else []]
                  for o in bpy.data.objects)


def evaluated_points(bpy, obj, frames):
    import numpy as np

    out = []
    for frame in frames:
        bpy.context.scene.frame_set(frame)
        evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
        mesh = evaluated.to_mesh()
        points = np.empty(len(mesh.vertices) * 3)
        mesh.vertices.foreach_get("co", points)
        matrix = np.array(evaluated.matrix_world)
        points = points.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3]
        out.append(points.tolist())
        evaluated.to_mesh_clear()
    return out


def attribute(obj, name):
    values = [0.0] * len(obj.data.vertices)
    obj.data.attributes[name].data.foreach_get("value", values)
    return values


def layer_values(path: str, name: str = "youngsModulus") -> list:
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(path)
    for prim in stage.Traverse():
        primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar(name)
        if prim.GetTypeName() == "Mesh" and primvar and primvar.HasAuthoredValue():
            return [float(v) for v in primvar.Get()]
    raise AssertionError(f"no {name} in {path}")


def main(job_file: str) -> None:
    sys.path.insert(0, str(TESTS))
    import bpy
    from helpers import blender_rigs

    job = json.loads(Path(job_file).read_text())
    folder = Path(job_file).parent
    out: dict = {}
    bpy.ops.wm.read_factory_settings(use_empty=True)
    # the extension from its built zip, as Install from Disk does
    bpy.ops.extensions.package_install_files(filepath=job["zip"], repo="user_default",
                                             enable_on_install=True)
    package = next(name for name in bpy.context.preferences.addons.keys() if name.endswith(".torchfit"))
    out["package"] = package
    out["classes"] = [name for name in ("TORCHFIT_OT_fit", "TORCHFIT_OT_cancel",
                                        "TORCHFIT_OT_simulate", "TORCHFIT_OT_import_result",
                                        "TORCHFIT_OT_watch", "TORCHFIT_OT_modulus_to_mesh",
                                        "VIEW3D_PT_torchfit")
                      if hasattr(bpy.types, name)]
    ui = sys.modules[package + ".ui"]
    prefs = bpy.context.preferences.addons[package].preferences

    body, arm = blender_rigs._limb(bpy, {"frames": 3, "bend": 45.0})
    first_action = arm.animation_data.action
    settings = bpy.context.scene.torchfit
    settings.frame_start, settings.frame_end, settings.held_out = 1, 3, "3"
    settings.iterations, settings.tet_edge_length, settings.threads = 2, 0.08, 1
    bpy.ops.object.select_all(action="DESELECT")
    body.select_set(True)
    bpy.context.view_layer.objects.active = body

    def refused(label, **options):
        before = scene_state(bpy)
        settings.error = ""
        try:                          # an operator's ERROR report raises when called from Python
            status = sorted(bpy.ops.torchfit.fit(wait=True, **options))
        except RuntimeError as error:
            status = ["raised", str(error)]
        out.setdefault("errors", {})[label] = {"status": status, "line": settings.error,
                                               "unchanged": scene_state(bpy) == before}

    # item 6: each error is one line, the scene unchanged
    prefs.repository, prefs.interpreter = job["repo"], str(folder / "no_python")
    refused("interpreter")
    prefs.interpreter = sys.executable
    refused("unsaved")
    bpy.ops.wm.save_as_mainfile(filepath=str(folder / "limb.blend"))
    bare = blender_rigs._mesh_object(bpy, "Bare", *blender_rigs._tube(0, 0.2, 0.05, 8, 5))
    bpy.context.view_layer.objects.active = bare
    refused("no_armature")
    bare.modifiers.new("Armature", "ARMATURE").object = arm
    refused("no_weights")
    bpy.data.objects.remove(bare)
    bpy.context.view_layer.objects.active = body
    settings.held_out = "1,2,3"                          # torchfit refuses: nothing to fit
    refused("run_fails")
    settings.held_out = "3"

    # fit to the end, then the scene holds the cache object, the attribute, the material
    start = time.perf_counter()
    out["fit_status"] = sorted(bpy.ops.torchfit.fit(wait=True))
    out["fit_seconds"] = time.perf_counter() - start
    out["fit_error"], out["summary"] = settings.error, settings.summary
    run = Path(settings.last_run)
    out["run"] = str(run)
    simulated = bpy.data.objects["Limb simulated"]
    modulus = bpy.data.objects["Limb modulus"]
    out["cache_modifiers"] = [m.type for m in simulated.modifiers]
    out["simulated_points"] = evaluated_points(bpy, simulated, [1, 2, 3])
    out["attribute"] = attribute(modulus, "youngsModulus")
    out["layer"] = layer_values(str(run / "usd" / "material.usda"))
    out["materials"] = [m.name for m in modulus.data.materials]
    nodes = modulus.data.materials[0].node_tree.nodes
    out["attribute_node"] = [n.attribute_name for n in nodes if n.type == "ATTRIBUTE"]
    out["panel_iteration"], out["panel_misfit"] = settings.iteration, settings.misfit
    out["panel_surface_mm"] = settings.surface_error_mm
    out["modulus_range"] = [settings.modulus_min, settings.modulus_max, settings.modulus_unit]

    # cancel, then Fit again resumes the run
    settings.job_folder = str(folder / "second")
    settings.iterations = 4
    bpy.ops.torchfit.fit(wait=False)
    running, _, _ = ui._RUNNING[bpy.context.scene.name]
    deadline = time.monotonic() + 300
    while running.running and time.monotonic() < deadline:
        rows = (running.run / "history.jsonl")
        if rows.is_file() and len(rows.read_text().splitlines()) >= 2:
            break
        time.sleep(0.2)
    bpy.ops.torchfit.cancel()
    out["cancel_status"] = running.poll()
    out["cancel_state"] = settings.state
    # the resumed run as the watch operator follows it (its timer step, called here)
    out["resume_status"] = sorted(bpy.ops.torchfit.fit(wait=False))
    seen = []
    while ui.poll_running(None, bpy.context):
        shown = settings.iteration
        rows = [json.loads(x) for x in (running.run / "history.jsonl").read_text().splitlines()
                if x.endswith("}")]
        seen.append([shown, settings.misfit, rows[shown]["misfit"] if shown >= 0 else None,
                     rows[-1]["iteration"]])
        time.sleep(0.2)
    out["resume_seen"] = seen
    out["resume_state"], out["resume_panel_iteration"] = settings.state, settings.iteration
    out["resume_imported"] = "Limb simulated.001" in bpy.data.objects
    out["resume_console"] = (running.console.read_text())[-2000:]
    out["resumed_iterations"] = json.loads((running.run / "result.json").read_text())["iterations"]
    out["resumed_log_says_resume"] = "resum" in (running.run / "fit.log").read_text().lower()

    # simulate a second action with the first fit's material
    settings.job_folder = ""
    settings.last_run = str(run)
    second = first_action.copy()
    second.name = "Wave"
    for curve in second.fcurves:
        for point in curve.keyframe_points:
            point.co.y *= 0.5 if curve.array_index in (0, 3) else 1.0
    settings.simulate_action = "Wave"
    before = set(bpy.data.objects)
    out["simulate_status"] = sorted(bpy.ops.torchfit.simulate(wait=True))
    out["simulate_error"] = settings.error
    new = [o for o in bpy.data.objects if o not in before]
    out["simulate_new"] = [[o.name, [m.type for m in o.modifiers]] for o in new]
    out["action_kept"] = arm.animation_data.action == first_action

    # fit again from a painted attribute: the imported modulus onto the user's mesh, then
    # "painted" (doubled)
    bpy.context.view_layer.objects.active = body
    out["to_mesh_status"] = sorted(bpy.ops.torchfit.modulus_to_mesh())
    out["on_mesh"] = attribute(body, "youngsModulus")
    painted = [2.0 * v for v in out["on_mesh"]]
    body.data.attributes["youngsModulus"].data.foreach_set("value", painted)
    settings.iterations = 1
    out["paint_status"] = sorted(bpy.ops.torchfit.fit(wait=True, from_paint=True))
    out["paint_error"] = settings.error
    paint_run = Path(settings.last_run)
    out["paint_layer"] = layer_values(str(paint_run.parent / "painted.usda"))
    out["painted"] = painted
    out["paint_log_names_layer"] = "painted.usda" in (paint_run / "fit.log").read_text()

    # the hand: a palm bone branching into two fingers of two bones each (end bones)
    for o in list(bpy.data.objects):
        bpy.data.objects.remove(o)
    hand, _ = blender_rigs._hand(bpy, {"frames": 3, "bend": 50.0})
    bpy.ops.object.select_all(action="DESELECT")
    hand.select_set(True)
    bpy.context.view_layer.objects.active = hand
    settings.job_folder, settings.iterations, settings.held_out = "", 2, "3"
    bpy.ops.wm.save_as_mainfile(filepath=str(folder / "hand.blend"))
    start = time.perf_counter()
    out["hand_status"] = sorted(bpy.ops.torchfit.fit(wait=True))
    out["hand_seconds"] = time.perf_counter() - start
    out["hand_summary"] = settings.summary
    out["hand_run"] = settings.last_run
    out["hand_points"] = evaluated_points(bpy, bpy.data.objects["Hand simulated"], [1, 2])
    out["hand_attribute"] = attribute(bpy.data.objects["Hand modulus"], "youngsModulus")
    out["hand_layer"] = layer_values(str(Path(settings.last_run) / "usd" / "material.usda"))
    Path(job_file).with_suffix(".result.json").write_text(json.dumps(out))


if __name__ == "__main__":
    main(sys.argv[1])
