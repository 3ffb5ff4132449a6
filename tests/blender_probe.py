"""Run inside Blender, not by pytest: import a GLB and a BVH as an animator would and write down what Blender shows.

    blender -b --factory-startup --python tests/blender_probe.py -- GLB BVH OUT_DIR SECONDS [SECONDS ...]

Writes to OUT_DIR:
- ``report.json``: the objects (name, type, parent, modifiers), the armatures' bones, the mesh's shape keys, the
  scene's frame rate, the actions' frame ranges, the BVH's bones, its action's frame count and the frame rate it set;
- ``vertices.npy`` (len(SECONDS), vertices, 3): the GLB mesh's evaluated vertices (shape keys, armature) in world
  coordinates at each time, Blender's axes (Z up);
- ``bvh_rotations.npy`` (frames * joints, 3, 3): each BVH joint's rotation per frame in the armature's space, its
  rest orientation taken out.

Only Blender's own importers run here (``bpy.ops.import_scene.gltf``, ``bpy.ops.import_anim.bvh``) with their
defaults, but the BVH importer is asked to set the scene's frame rate from the file, as a user would.
"""

import builtins
import json
import sys
from pathlib import Path

import numpy

if not hasattr(numpy, "bool"):
    # Debian's Blender 3.4 glTF importer calls numpy.bool, which Debian's numpy 1.24 no longer has
    numpy.bool = numpy.bool_


def _open_without_universal_newlines(file, mode="r", *args, **kwargs):
    # Debian's Blender 3.4 runs on Python 3.11, whose open() no longer takes mode "rU" (its BVH importer's)
    return _builtin_open(file, mode.replace("U", ""), *args, **kwargs)


_builtin_open, builtins.open = builtins.open, _open_without_universal_newlines

import bpy  # noqa: E402


def scene_frame(seconds: float) -> float:
    """The (fractional) frame the glTF importer put a key at ``seconds`` on: seconds times the scene's rate."""
    render = bpy.context.scene.render
    return seconds * render.fps / render.fps_base


def evaluated_vertices(obj, frame: float) -> numpy.ndarray:
    scene = bpy.context.scene
    scene.frame_set(int(numpy.floor(frame)), subframe=float(frame - numpy.floor(frame)))
    evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    mesh = evaluated.to_mesh()
    local = numpy.empty(len(mesh.vertices) * 3)
    mesh.vertices.foreach_get("co", local)
    evaluated.to_mesh_clear()
    local = local.reshape(-1, 3)
    matrix = numpy.array(evaluated.matrix_world)
    return local @ matrix[:3, :3].T + matrix[:3, 3]


def describe_objects() -> list[dict]:
    return [
        {
            "name": obj.name,
            "type": obj.type,
            "parent": obj.parent.name if obj.parent else None,
            "modifiers": [m.type for m in obj.modifiers],
            "bones": [b.name for b in obj.data.bones] if obj.type == "ARMATURE" else [],
            "shape_keys": [k.name for k in obj.data.shape_keys.key_blocks]
            if obj.type == "MESH" and obj.data.shape_keys
            else [],
            "vertex_groups": [g.name for g in obj.vertex_groups],
        }
        for obj in bpy.data.objects
    ]


def import_glb(path: str, seconds: list[float], out: Path) -> dict:
    bpy.ops.import_scene.gltf(filepath=path)
    report = {
        "objects": describe_objects(),
        "scene_fps": bpy.context.scene.render.fps / bpy.context.scene.render.fps_base,
        "actions": {a.name: list(a.frame_range) for a in bpy.data.actions},
    }
    meshes = [obj for obj in bpy.data.objects if obj.type == "MESH"]
    if len(meshes) == 1:
        numpy.save(out / "vertices.npy", numpy.stack([evaluated_vertices(meshes[0], scene_frame(t)) for t in seconds]))
    return report


def import_bvh(path: str, out: Path) -> dict:
    before = set(bpy.data.objects)
    bpy.ops.import_anim.bvh(filepath=path, update_scene_fps=True)
    (armature,) = [obj for obj in bpy.data.objects if obj not in before]
    first, last = (round(f) for f in armature.animation_data.action.frame_range)
    scene = bpy.context.scene
    rotations = []
    for frame in range(first, last + 1):
        scene.frame_set(frame)
        for bone in armature.pose.bones:
            rest = numpy.array(bone.bone.matrix_local)[:3, :3]
            rotations.append(numpy.array(bone.matrix)[:3, :3] @ rest.T)
    numpy.save(out / "bvh_rotations.npy", numpy.array(rotations))
    return {
        "bvh_bones": [b.name for b in armature.data.bones],
        "bvh_frames": last - first + 1,
        "bvh_fps": scene.render.fps / scene.render.fps_base,
    }


def main(argv: list[str]) -> None:
    glb, bvh, out = argv[0], argv[1], Path(argv[2])
    seconds = [float(s) for s in argv[3:]]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    report = import_glb(glb, seconds, out)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    report.update(import_bvh(bvh, out))
    (out / "report.json").write_text(json.dumps(report, indent=1))


main(sys.argv[sys.argv.index("--") + 1 :])
