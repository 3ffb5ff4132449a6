"""The default run's GLB and BVH imported by Blender's own importers (headless, ``tests/blender_probe.py``): the face
Blender shows at each time is the face the file describes, by the glTF specification, computed here from the file.

The file's meaning is computed independently of Blender: the morph targets' deltas weighted by the animation's
weights at a key, then linear-blend skinning with the animated joints' global matrices and the inverse bind matrices,
then glTF's Y-up axes turned to Blender's Z-up, the turn Blender's importer makes. Blender duplicates the vertices
that the file's primitives share, so each of its vertices is matched to the file's vertex it coincides with over all
the times at once.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import blender_env

from stages.formats.bvh import joint_rotation, parse_bvh
from stages.formats.gltf import read_accessor, read_morph_mesh
from stages.geometry.rotations import quat_to_matrix

GLB = "out/sad_as_happy_to_disgust.glb"
BVH = "out/sad_head_motion.bvh"
#: glTF (and BVH) Y up, -Z forward to Blender's Z up, -Y forward: (x, y, z) -> (x, -z, y)
Y_UP_TO_Z_UP = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])


def accessor(gltf, index: int) -> np.ndarray:
    """Accessor ``index`` of a GLB as (count, components), read by the project's glTF reader."""
    return read_accessor(gltf, [gltf.binary_blob()], index, Path("default run GLB"))


def trs(translation, rotation_xyzw) -> np.ndarray:
    """A node's local matrix from glTF's translation and (x, y, z, w) rotation (no scale in these files)."""
    matrix = np.eye(4)
    matrix[:3, :3] = quat_to_matrix(np.asarray(rotation_xyzw, np.float64)[[3, 0, 1, 2]])
    matrix[:3, 3] = translation
    return matrix


def posed_vertices(path, keys: list[int]) -> np.ndarray:
    """(len(keys), vertices, 3): the GLB's mesh at the given animation keys, by the glTF specification, Z up."""
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(path))
    mesh = read_morph_mesh(path)
    (animation,) = gltf.animations
    channels = {(c.target.node, c.target.path): animation.samplers[c.sampler].output for c in animation.channels}
    primitive = gltf.meshes[0].primitives[0]
    joints = accessor(gltf, primitive.attributes.JOINTS_0).astype(int)
    weights = accessor(gltf, primitive.attributes.WEIGHTS_0)
    (skin,) = gltf.skins
    inverse_bind = accessor(gltf, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    parents = {child: i for i, node in enumerate(gltf.nodes) for child in node.children or []}
    mesh_node = next(i for i, node in enumerate(gltf.nodes) if node.mesh is not None)
    morph_weights = accessor(gltf, channels[mesh_node, "weights"]).reshape(-1, len(mesh.target_names))
    posed = []
    for key in keys:
        local = {}
        for i, node in enumerate(gltf.nodes):
            translation = channels.get((i, "translation"))
            rotation = channels.get((i, "rotation"))
            local[i] = trs(
                node.translation or [0, 0, 0] if translation is None else accessor(gltf, translation)[key],
                node.rotation or [0, 0, 0, 1] if rotation is None else accessor(gltf, rotation)[key],
            )

        def world(i):
            return local[i] if i not in parents else world(parents[i]) @ local[i]

        skinning = np.stack([world(j) @ inverse_bind[k] for k, j in enumerate(skin.joints)])
        morphed = mesh.positions + np.einsum("t,tvc->vc", morph_weights[key], mesh.deltas)
        homogeneous = np.concatenate([morphed, np.ones((len(morphed), 1))], axis=1)
        blended = np.einsum("vi,vixy,vy->vx", weights, skinning[joints], homogeneous)[:, :3]
        posed.append(blended @ Y_UP_TO_Z_UP.T)
    return np.stack(posed)


def key_times(path, count: int = 4) -> tuple[list[int], list[float]]:
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(path))
    times = accessor(gltf, gltf.animations[0].samplers[0].input)[:, 0]
    keys = [int(k) for k in np.linspace(0, len(times) - 1, count).round()]
    return keys, [float(times[k]) for k in keys]


@pytest.fixture(scope="module")
def imported(default_run, blender, tmp_path_factory):
    """What Blender made of the default run's GLB and BVH (report, vertices at the chosen keys, BVH rotations)."""
    root, _ = default_run
    out = tmp_path_factory.mktemp("blender")
    keys, seconds = key_times(root / GLB)
    probe = [blender, "-b", "--factory-startup", "--python-exit-code", "1", "--python"]
    command = [*probe, str(Path(__file__).with_name("blender_probe.py")), "--"]
    proc = subprocess.run(
        [*command, str(root / GLB), str(root / BVH), str(out), *map(repr, seconds)],
        capture_output=True,
        text=True,
        timeout=300,
        env=blender_env(),
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    return root, keys, report, np.load(out / "vertices.npy"), np.load(out / "bvh_rotations.npy")


def test_blender_imports_the_glb_as_a_skinned_mesh_with_its_shape_keys(imported):
    root, _, report, _, _ = imported
    objects = {o["name"]: o for o in report["objects"]}
    (armature,) = [o for o in objects.values() if o["type"] == "ARMATURE"]
    (mesh,) = [o for o in objects.values() if o["type"] == "MESH"]
    assert armature["bones"] == ["Root", "Head", "LeftEye", "RightEye"]
    assert mesh["parent"] == armature["name"] and mesh["modifiers"] == ["ARMATURE"]
    assert set(mesh["vertex_groups"]) == {"Root", "Head", "LeftEye", "RightEye"}
    assert mesh["shape_keys"][1:] == read_morph_mesh(root / GLB).target_names  # after Blender's "Basis"
    assert len(report["actions"]) == 2  # the shape keys' and the skeleton's


def test_the_face_blender_shows_is_the_face_the_glb_describes(imported):
    """Morph weights, head motion and gaze together: every vertex Blender evaluates (shape keys, then the
    armature) at four keys is where the glTF specification puts it, to float32 precision."""
    from scipy.spatial import cKDTree

    root, keys, _, shown, _ = imported
    expected = posed_vertices(root / GLB, keys)
    # match each of Blender's vertices to the file's vertex it coincides with at every key at once
    distance, match = cKDTree(expected.transpose(1, 0, 2).reshape(len(expected[0]), -1)).query(
        shown.transpose(1, 0, 2).reshape(len(shown[0]), -1)
    )
    assert len(np.unique(match)) == len(expected[0])  # every vertex of the file is shown
    assert distance.max() < 1e-5  # metres, over all keys
    # and the face does move between the keys, so the match above tests the animation
    moved = np.linalg.norm(expected[1:] - expected[0], axis=-1).max(axis=1)
    assert np.all(moved > 1e-3)


def test_blender_plays_the_bvh_at_its_rate_with_its_rotations(imported):
    root, _, report, _, rotations = imported
    bvh = parse_bvh((root / BVH).read_text())
    assert report["bvh_bones"] == ["Head"]
    assert report["bvh_frames"] == bvh.frames
    assert report["bvh_fps"] == pytest.approx(bvh.fps, rel=1e-5)
    ours = Y_UP_TO_Z_UP @ quat_to_matrix(joint_rotation(bvh, "Head")) @ Y_UP_TO_Z_UP.T
    assert np.abs(rotations - ours).max() < 1e-4
    assert np.degrees(np.arccos(np.clip((np.trace(ours, axis1=1, axis2=2) - 1) / 2, -1, 1))).max() > 1.0
