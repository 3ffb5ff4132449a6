"""The landmark vertices of a character that has none, found by the tracker on its front render
(stages.retarget.auto_landmarks). Known answer: the ICT head's hand-placed ids."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from msflow import UserError
from msflow.testing import run_stage
from stages.formats.gltf import read_morph_mesh, write_morph_glb
from stages.retarget.auto_landmarks import ibug_mirror, jaw_open_target, track_character_landmarks
from stages.retarget.character import GltfCharacter

ROOT = Path(__file__).resolve().parents[1]
ICT_GLB = ROOT / "data" / "characters" / "ict-facekit.glb"


@pytest.fixture(scope="module")
def ict_mesh():
    return read_morph_mesh(ICT_GLB)


@pytest.fixture(scope="module")
def placed(ict_mesh):
    return track_character_landmarks(ict_mesh)


def eye_distance(points):
    return float(np.linalg.norm(points[36:42].mean(axis=0) - points[42:48].mean(axis=0)))


def without_landmarks(mesh):
    extras = {k: v for k, v in mesh.extras.items() if k != "landmarkVertexIds"}
    return dataclasses.replace(mesh, extras=extras)


def test_placed_landmarks_lie_where_the_hand_placed_ones_do(ict_mesh, placed):
    ids, meta, warnings = placed
    stored = np.asarray(ict_mesh.extras["landmarkVertexIds"])
    v = ict_mesh.positions.astype(np.float64)
    iod = eye_distance(v[stored])
    off = np.linalg.norm(v[ids] - v[stored], axis=1) / iod
    assert off[27:68].mean() < 0.05 and np.median(off[48:68]) < 0.03, off.round(3)
    assert meta["from"] == "tracked" and meta["presence"] > 0.9 and warnings == []
    # on the face's skin: no eyeball, iris or tooth, though the lids and the lips' line border them
    face = ict_mesh.triangles[ict_mesh.triangle_groups == 0]
    assert np.isin(ids, face).all()
    # the closed lips told apart: the jaw lowers the inner lower lip's points, not the inner upper lip's
    drop = -ict_mesh.deltas[ict_mesh.target_names.index("jawOpen"), :, 1] / iod
    assert drop[ids[[65, 66, 67]]].min() > 0.3 > 0.1 > drop[ids[[61, 62, 63]]].max()  # ICT: 0.49-0.56 / 0.04-0.06


def test_the_symmetric_head_gets_symmetric_points(ict_mesh, placed):
    """The landmark model leans 0.015-0.03 eye distances to one side on a symmetric render; averaged with its
    reading of the mirror image, the ICT head (symmetric about x = 0) gets its points in mirror pairs."""
    ids, _, _ = placed
    p = ict_mesh.positions.astype(np.float64)[ids]
    iod = eye_distance(p)
    mirror = ibug_mirror()
    inner = np.arange(27, 68)  # nose, eyes, lips (the brows' upper edge and the jaw line snap to coarser vertices)
    assert np.abs(p[inner, 0] + p[mirror[inner], 0]).max() / iod < 0.01
    assert np.abs(p[[27, 28, 29, 30, 33, 51, 57, 62, 66], 0]).max() / iod < 0.005  # the midline on it


def test_a_character_without_landmarks_gets_them_with_a_warning(tmp_path, ict_mesh, placed):
    path = tmp_path / "no_landmarks.glb"
    path.write_bytes(write_morph_glb(without_landmarks(ict_mesh)))
    with pytest.warns(UserWarning, match="no landmark vertices given"):
        out = run_stage(GltfCharacter, {}, {"mesh": path})
    assert out.arrays["landmark_ids"].tolist() == placed[0].tolist()
    assert out.meta["source"]["landmarks"]["from"] == "tracked"
    assert any("no landmark vertices given" in w and "landmarks" in w for w in out.warnings), out.warnings
    stock = run_stage(GltfCharacter, {}, {"mesh": ICT_GLB})
    assert stock.meta["source"]["landmarks"] == {"from": "mesh extras"} and not stock.warnings
    asked = run_stage(GltfCharacter, {"landmarks": "tracked"}, {"mesh": ICT_GLB})
    assert asked.arrays["landmark_ids"].tolist() == placed[0].tolist() and not asked.warnings


def test_a_character_facing_away_is_a_user_error(tmp_path, ict_mesh):
    turned = without_landmarks(ict_mesh)
    flip = np.array([-1.0, 1.0, -1.0], dtype=np.float32)  # half a turn about +y: the face looks along -z
    turned = dataclasses.replace(turned, positions=turned.positions * flip, deltas=turned.deltas * flip)
    path = tmp_path / "away.glb"
    path.write_bytes(write_morph_glb(turned))
    with pytest.raises(UserError, match=r"no face found.*look along \+z") as err:
        run_stage(GltfCharacter, {}, {"mesh": path})
    assert err.value.field == "inputs.landmarks"


def test_without_a_jaw_opening_morph_the_lips_take_the_nearest_vertices(ict_mesh):
    names = ["jawLowered" if n == "jawOpen" else n for n in ict_mesh.target_names]
    ids, meta, warnings = track_character_landmarks(dataclasses.replace(ict_mesh, target_names=names))
    assert meta["jaw_open_target"] is None and len(ids) == 68
    assert any("no jaw-opening morph" in w for w in warnings)


def test_the_jaw_opening_morph_is_found_by_its_usual_names():
    assert jaw_open_target(["mouthSmile_L", "jawOpen"]) == 1
    assert jaw_open_target(["Jaw_Drop", "mouthOpen"]) == 0  # the first of jawOpen, jawDrop, mouthOpen present
    assert jaw_open_target(["JawOpen"]) == 0 and jaw_open_target(["jaw_open"]) == 0
    assert jaw_open_target(["jawLeft", "mouthClose"]) is None


def test_the_closed_lips_line_takes_the_upper_or_the_lower_lip_by_the_jaw():
    from stages.retarget.auto_landmarks import lip_line_vertex

    # four vertices on the lip line: 0 and 1 on the upper lip (the jaw barely lowers them), 2 and 3 on the lower
    xy = np.array([[10.0, 10.4], [12.0, 10.0], [10.0, 10.1], [11.0, 10.6]])
    drop = np.array([0.01, 0.0, 0.5, 0.6])
    candidates = np.arange(4)
    point = np.array([10.0, 10.2])  # nearest to vertex 2, a lower-lip vertex
    assert lip_line_vertex(candidates, point, xy, drop, upper=True) == 0
    assert lip_line_vertex(candidates, point, xy, drop, upper=False) == 2
    assert lip_line_vertex(np.array([2, 3]), point, xy, drop, upper=True) == 2  # no upper vertex near: the nearest


def test_an_obj_character_without_landmarks_gets_the_same_ones(tmp_path, ict_mesh, placed):
    """The OBJ reader takes the same path: the ICT head written as OBJ files (neutral with its materials, and the
    jaw-opening shape), no landmark JSON, gets the GLB's placement."""
    from stages.retarget.character import ObjBlendshapes

    def obj(vertices):
        lines = ["mtllib head.mtl", *(f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in vertices)]
        current = None
        for group, tri in zip(ict_mesh.triangle_groups, ict_mesh.triangles):
            if group != current:
                current = group
                lines.append(f"usemtl {ict_mesh.groups[group].name}")
            lines.append("f " + " ".join(str(k + 1) for k in tri))
        return "\n".join(lines) + "\n"

    jaw = ict_mesh.target_names.index("jawOpen")
    (tmp_path / "neutral.obj").write_text(obj(ict_mesh.positions))
    (tmp_path / "jawOpen.obj").write_text(obj(ict_mesh.positions + ict_mesh.deltas[jaw]))
    (tmp_path / "head.mtl").write_text(
        "".join(f"newmtl {g.name}\nKd {g.color[0]} {g.color[1]} {g.color[2]}\n" for g in ict_mesh.groups)
    )
    shapes = {p.name: p for p in tmp_path.iterdir()}
    with pytest.warns(UserWarning, match="no landmark vertices given"):
        out = run_stage(ObjBlendshapes, {"neutral": "neutral"}, {"shapes": shapes})
    ids = out.arrays["landmark_ids"]
    v = ict_mesh.positions.astype(np.float64)
    off = np.linalg.norm(v[ids] - v[placed[0]], axis=1) / eye_distance(v[placed[0]])
    assert (ids == placed[0]).sum() >= 64 and off.max() < 0.03  # the MTL's colours shade a little differently
    assert out.meta["source"]["landmarks"]["from"] == "tracked" and out.warnings


@pytest.mark.parametrize("scale", [1.0, 100.0])
def test_other_faces_and_units_keep_the_points_where_the_hand_made_list_puts_them(ict_mesh, scale):
    """ICT's identity shapes make other faces with the same vertex order, so the hand-made list is still the known
    answer; centimetres and an offset origin (a character exported from another tool) change nothing."""
    names = ict_mesh.target_names
    identity = [i for i, n in enumerate(names) if n.startswith("identity")]
    coefficients = np.random.default_rng(7).normal(0.0, 1.0, len(identity))
    face = ict_mesh.positions + np.tensordot(coefficients, ict_mesh.deltas[identity], 1)
    other = dataclasses.replace(
        ict_mesh,
        positions=(face * scale + [0.0, 0.5 * scale, 0.03 * scale]).astype(np.float32),
        deltas=(ict_mesh.deltas * scale).astype(np.float32),
    )
    ids, meta, _ = track_character_landmarks(other)
    stored = np.asarray(ict_mesh.extras["landmarkVertexIds"])
    v = face.astype(np.float64)
    off = np.linalg.norm(v[ids] - v[stored], axis=1) / eye_distance(v[stored])
    assert off[27:68].mean() < 0.05 and off[60:68].mean() < 0.04 and meta["presence"] > 0.9, off.round(3)


def test_the_character_stages_key_covers_the_models_the_placement_reads():
    from stages.retarget.character import TRACKER_RESOURCES, ObjBlendshapes
    from stages.tracking.stages import DETECTOR_MODEL, LANDMARK_MODEL, FaceMeshParams, model_paths

    detector, landmarks, _ = model_paths(None, FaceMeshParams().model, False)  # what track_character_landmarks uses
    assert {detector, landmarks} == {DETECTOR_MODEL, LANDMARK_MODEL} == set(TRACKER_RESOURCES.values())
    assert set(TRACKER_RESOURCES.values()) <= set(GltfCharacter.resources.values())
    assert set(TRACKER_RESOURCES.values()) <= set(ObjBlendshapes.resources.values())
