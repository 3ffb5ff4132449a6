"""Character loading: OBJ blendshape folders, glTF morph targets (round trip through our writer, foreign layouts),
identity mix, landmark ids, the embedded ICT FaceKit GLB and its builder."""

import gzip
import json
from pathlib import Path

import numpy as np
import pytest

from msflow import UserError
from msflow.testing import run_stage
from stages.formats.gltf import MaterialGroup, MorphMesh, read_morph_mesh, validate_glb, write_morph_glb
from stages.retarget.character import GltfCharacter, ObjBlendshapes, mix_identity
from stages.retarget.ict_facekit import build_ict_character
from stages.retarget.obj_blendshapes import parse_obj_faces, parse_obj_vertices

ROOT = Path(__file__).resolve().parents[1]
ICT_GLB = ROOT / "data" / "characters" / "ict-facekit.glb"


# ------------------------------------------------------------------------------------------------ synthetic data


def grid(nx=12, ny=10):
    """A wavy quad grid (x right, y up, facing +z): vertices (V, 3) and quads (Q, 4), counter-clockwise."""
    xs, ys = np.meshgrid(np.linspace(-1, 1, nx), np.linspace(-1, 1, ny))
    v = np.c_[xs.ravel(), ys.ravel(), 0.1 * np.sin(3 * xs.ravel()) * np.cos(2 * ys.ravel())]
    idx = np.arange(nx * ny).reshape(ny, nx)
    quads = np.c_[idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()]
    return v, quads


def obj_text(vertices, faces, groups=None, group_names=None) -> str:
    lines = ["# synthetic", "mtllib test.mtl"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    current = None
    for i, face in enumerate(faces):
        if groups is not None and groups[i] != current:
            current = groups[i]
            lines.append(f"usemtl {group_names[current]}")
        lines.append("f " + " ".join(f"{k + 1}/{k + 1}" for k in face))
    return "\n".join(lines) + "\n"


def write(path: Path, text: str) -> Path:
    if path.name.endswith(".gz"):
        with gzip.open(path, "wt") as fh:
            fh.write(text)
    else:
        path.write_text(text)
    return path


@pytest.fixture()
def obj_folder(tmp_path):
    """neutral + 3 blendshapes (.obj and .obj.gz) + 2 identities + landmark JSON + MTL, known deltas."""
    v, quads = grid()
    groups = (np.arange(len(quads)) >= len(quads) // 2).astype(int)
    names = ["M_Skin", "M_Lips"]
    rng = np.random.default_rng(0)
    write(tmp_path / "neutral.obj", obj_text(v, quads, groups, names))
    deltas = {}
    for name, suffix in [("jawOpen", ".obj"), ("mouthSmile_L", ".obj.gz"), ("mouthSmile_R", ".obj.gz")]:
        d = np.zeros_like(v)
        sel = rng.choice(len(v), 15, replace=False)
        d[sel] = rng.normal(0, 0.05, (15, 3))
        deltas[name] = d
        write(tmp_path / f"{name}{suffix}", obj_text(v + d, quads))
    identities = {}
    for i in range(2):
        d = rng.normal(0, 0.02, v.shape)
        identities[f"identity{i:03d}"] = d
        write(tmp_path / f"identity{i:03d}.obj.gz", obj_text(v + d, quads))
    ids = rng.choice(len(v), 68, replace=False)
    (tmp_path / "landmarks.json").write_text(json.dumps({"idx_to_landmark_verts": ids.tolist()}))
    (tmp_path / "test.mtl").write_text("newmtl M_Skin\nKd 0.9 0.7 0.6\nnewmtl M_Lips\nKd 0.7 0.2 0.2\nd 1.0\n")
    return {
        "dir": tmp_path,
        "v": v,
        "quads": quads,
        "deltas": deltas,
        "identities": identities,
        "ids": ids,
        "groups": groups,
    }


def shape_files(folder: Path, *, exclude=()):
    return {
        p.name: p
        for p in sorted(folder.iterdir())
        if (p.name.endswith((".obj", ".obj.gz", ".mtl"))) and p.name not in exclude
    }


# ------------------------------------------------------------------------------------------------ OBJ parsing


def test_obj_faces_are_fan_triangulated_keeping_winding_and_groups():
    text = (
        "\n".join(
            [
                "v 0 0 0",
                "v 1 0 0",
                "v 1 1 0",
                "v 0 1 0",
                "v 2 0 0",
                "usemtl A",
                "f 1 2 3 4",
                "usemtl B",
                "f 2/5/1 5/6/2 3/7/3",
                "f -4 -3 -1",
            ]
        )
        + "\n"
    )
    v = parse_obj_vertices(text, Path("x.obj"))
    tris, groups, names = parse_obj_faces(text, len(v), Path("x.obj"))
    assert names == ["A", "B"]
    assert tris.tolist() == [[0, 1, 2], [0, 2, 3], [1, 4, 2], [1, 2, 4]]
    assert groups.tolist() == [0, 0, 1, 1]
    normals = np.cross(v[tris[:, 1]] - v[tris[:, 0]], v[tris[:, 2]] - v[tris[:, 0]])
    assert (normals[:3, 2] > 0).all()  # counter-clockwise polygons stay counter-clockwise


def test_obj_face_index_out_of_range_is_a_user_error():
    text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 4\n"
    with pytest.raises(UserError, match="vertex 4"):
        parse_obj_faces(text, 3, Path("bad.obj"))


# ------------------------------------------------------------------------------------------------ ObjBlendshapes


def test_obj_blendshapes_reads_names_deltas_groups_and_landmarks(obj_folder):
    f = obj_folder
    out = run_stage(
        ObjBlendshapes,
        {"neutral": "neutral"},
        {"shapes": shape_files(f["dir"]), "landmarks": f["dir"] / "landmarks.json"},
        store=f["dir"] / "s",
    )
    names = out.meta["target_names"]
    assert sorted(names) == ["jawOpen", "mouthSmile_L", "mouthSmile_R"]
    assert out.arrays["neutral"].shape == f["v"].shape
    assert len(out.arrays["triangles"]) == 2 * len(f["quads"])
    for i, name in enumerate(names):
        assert np.allclose(out.arrays["deltas"][i], f["deltas"][name], atol=2e-6)
    assert out.arrays["landmark_ids"].tolist() == f["ids"].tolist()
    assert [g["name"] for g in out.meta["groups"]] == ["M_Skin", "M_Lips"]
    assert np.allclose(out.meta["groups"][1]["color"][:3], [0.7, 0.2, 0.2])
    assert np.array_equal(out.arrays["triangle_groups"], np.repeat(f["groups"], 2))
    assert out.meta["source"]["identity_targets"] == ["identity000", "identity001"]


def test_identity_mix_moves_the_neutral_and_keeps_expression_deltas(obj_folder):
    f = obj_folder
    inputs = {"shapes": shape_files(f["dir"]), "landmarks": f["dir"] / "landmarks.json"}
    base = run_stage(ObjBlendshapes, {"neutral": "neutral"}, inputs)
    mixed = run_stage(
        ObjBlendshapes, {"neutral": "neutral", "identity": {"identity000": 0.7, "identity001": -1.5}}, inputs
    )
    expected = f["v"] + 0.7 * f["identities"]["identity000"] - 1.5 * f["identities"]["identity001"]
    assert np.allclose(mixed.arrays["neutral"], expected, atol=1e-5)
    assert np.array_equal(mixed.arrays["deltas"], base.arrays["deltas"])
    assert np.allclose(
        mix_identity(f["v"], np.stack([f["identities"]["identity000"]]), [2.0]),
        f["v"] + 2 * f["identities"]["identity000"],
        atol=1e-6,
    )
    with pytest.raises(UserError, match="identity999"):
        run_stage(ObjBlendshapes, {"neutral": "neutral", "identity": {"identity999": 1.0}}, inputs)


def test_obj_blendshapes_params_are_checked_up_front():
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="greater than 0"):
        ObjBlendshapes.Params(scale=0)


def test_obj_blendshapes_scale_and_dropped_groups_remap_landmarks(obj_folder):
    f = obj_folder
    inputs = {"shapes": shape_files(f["dir"]), "landmarks": f["dir"] / "landmarks.json"}
    base = run_stage(ObjBlendshapes, {"neutral": "neutral"}, inputs)
    ids = base.arrays["landmark_ids"]
    lips_vertices = np.unique(base.arrays["triangles"][base.arrays["triangle_groups"] == 1])
    skin_vertices = np.unique(base.arrays["triangles"][base.arrays["triangle_groups"] == 0])
    only_lips = np.setdiff1d(lips_vertices, skin_vertices)
    if np.isin(ids, only_lips).any():
        with pytest.raises(UserError, match="landmark"):
            run_stage(ObjBlendshapes, {"neutral": "neutral", "drop_groups": ["M_Lips"]}, inputs)
        # landmarks elsewhere: a JSON restricted to skin vertices
        (f["dir"] / "landmarks.json").write_text(json.dumps(np.resize(skin_vertices, 68).tolist()))
        base = run_stage(ObjBlendshapes, {"neutral": "neutral"}, inputs)
        ids = base.arrays["landmark_ids"]
    dropped = run_stage(ObjBlendshapes, {"neutral": "neutral", "drop_groups": ["M_Lips"], "scale": 0.01}, inputs)
    assert len(dropped.arrays["neutral"]) == len(skin_vertices)
    assert np.allclose(
        dropped.arrays["neutral"][dropped.arrays["landmark_ids"]], 0.01 * base.arrays["neutral"][ids], atol=1e-7
    )
    kept_deltas = base.arrays["deltas"][:, skin_vertices]
    assert np.allclose(np.abs(dropped.arrays["deltas"]).max(), 0.01 * np.abs(kept_deltas).max(), rtol=1e-5)
    assert [g["name"] for g in dropped.meta["groups"]] == ["M_Skin"]
    with pytest.raises(UserError, match="M_Nope"):
        run_stage(ObjBlendshapes, {"neutral": "neutral", "drop_groups": ["M_Nope"]}, inputs)


def test_blendshape_with_another_vertex_count_is_a_user_error(obj_folder):
    f = obj_folder
    v, quads = grid(11, 10)
    write(f["dir"] / "browDown_L.obj", obj_text(v, quads))
    with pytest.raises(UserError, match="browDown_L.*vertices"):
        run_stage(
            ObjBlendshapes,
            {"neutral": "neutral"},
            {"shapes": shape_files(f["dir"]), "landmarks": f["dir"] / "landmarks.json"},
        )


def test_no_blendshapes_is_a_user_error(obj_folder):
    f = obj_folder
    only = {"neutral.obj": f["dir"] / "neutral.obj"}
    with pytest.raises(UserError, match="no morph targets"):
        run_stage(ObjBlendshapes, {}, {"shapes": only, "landmarks": f["dir"] / "landmarks.json"})


@pytest.mark.parametrize(
    "ids, message",
    [
        (list(range(67)), "expected 68"),
        (list(range(67)) + [10_000], "out of range"),
        (list(range(67)) + [-1], "out of range"),
        ([0.5] * 68, "integers"),
    ],
)
def test_bad_landmark_ids_are_user_errors(obj_folder, ids, message):
    f = obj_folder
    (f["dir"] / "landmarks.json").write_text(json.dumps(ids))
    with pytest.raises(UserError, match=message):
        run_stage(
            ObjBlendshapes,
            {"neutral": "neutral"},
            {"shapes": shape_files(f["dir"]), "landmarks": f["dir"] / "landmarks.json"},
        )


def test_neutral_is_found_by_name_or_must_be_named(obj_folder):
    f = obj_folder
    inputs = {"shapes": shape_files(f["dir"]), "landmarks": f["dir"] / "landmarks.json"}
    auto = run_stage(ObjBlendshapes, {}, inputs)  # the one file with "neutral" in its name
    assert np.allclose(auto.arrays["neutral"], f["v"], atol=1e-6)
    with pytest.raises(UserError, match="no file named 'face'"):
        run_stage(ObjBlendshapes, {"neutral": "face"}, inputs)


# ------------------------------------------------------------------------------------------------ glTF


def synthetic_mesh(n_targets=3, seed=1) -> MorphMesh:
    v, quads = grid(9, 9)
    tris = np.r_[quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]].astype(np.int32)
    rng = np.random.default_rng(seed)
    deltas = np.zeros((n_targets, len(v), 3), np.float32)
    for t in range(n_targets):
        sel = rng.choice(len(v), 12, replace=False)
        deltas[t, sel] = rng.normal(0, 0.05, (12, 3))
    groups = (np.arange(len(tris)) % 2).astype(np.int32)
    return MorphMesh(
        v.astype(np.float32),
        tris,
        [f"shape{t}" for t in range(n_targets)],
        deltas,
        groups,
        [MaterialGroup("A", (0.8, 0.6, 0.5, 1.0)), MaterialGroup("B", (0.3, 0.3, 0.3, 1.0))],
        extras={"landmarkVertexIds": list(range(68))},
    )


def test_glb_round_trip_keeps_geometry_targets_and_landmarks(tmp_path, node_modules):
    mesh = synthetic_mesh()
    data = write_morph_glb(mesh)
    report = validate_glb(data)
    assert report["numErrors"] == 0 and report["numWarnings"] == 0, report["messages"]
    (tmp_path / "c.glb").write_bytes(data)
    out = run_stage(GltfCharacter, {}, {"mesh": tmp_path / "c.glb"})
    assert out.meta["target_names"] == mesh.target_names
    assert np.array_equal(out.arrays["neutral"], mesh.positions)
    assert np.allclose(out.arrays["deltas"], mesh.deltas, atol=1e-7)

    # triangles come back grouped by material; compare as sets of (sorted-rotation) triangles
    def canon(t):
        t = np.asarray(t)
        k = np.argmin(t, axis=1)
        return sorted(map(tuple, np.stack([t[np.arange(len(t)), (k + j) % 3] for j in range(3)], 1)))

    assert canon(out.arrays["triangles"]) == canon(mesh.triangles)
    assert out.arrays["landmark_ids"].tolist() == list(range(68))
    assert [g["name"] for g in out.meta["groups"]] == ["A", "B"]


def test_sparse_tolerance_drops_only_tiny_deltas(tmp_path):
    mesh = synthetic_mesh(1)
    mesh.deltas[0, 0] = [3e-6, 0, 0]  # below 1e-5: not stored
    mesh.deltas[0, 1] = [0, 2e-5, 0]  # above: stored
    back = read_back(tmp_path, write_morph_glb(mesh))
    assert back.deltas[0, 0].tolist() == [0, 0, 0]
    assert np.allclose(back.deltas[0, 1], [0, 2e-5, 0])
    big = np.abs(mesh.deltas[0]).max(axis=1) > 1e-5
    assert np.allclose(back.deltas[0][big], mesh.deltas[0][big])


def read_back(tmp_path, data: bytes, name="x.glb"):
    path = tmp_path / name
    path.write_bytes(data)
    return read_morph_mesh(path)


def gltf_without_targets(tmp_path) -> Path:
    import pygltflib

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    gltf = pygltflib.GLTF2()
    blob = v.tobytes()
    gltf.buffers = [pygltflib.Buffer(byteLength=len(blob))]
    gltf.bufferViews = [pygltflib.BufferView(buffer=0, byteOffset=0, byteLength=len(blob), target=34962)]
    gltf.accessors = [
        pygltflib.Accessor(
            bufferView=0, componentType=5126, count=3, type="VEC3", min=[0.0, 0.0, 0.0], max=[1.0, 1.0, 0.0]
        )
    ]
    gltf.meshes = [pygltflib.Mesh(primitives=[pygltflib.Primitive(attributes=pygltflib.Attributes(POSITION=0))])]
    gltf.nodes = [pygltflib.Node(mesh=0)]
    gltf.scenes = [pygltflib.Scene(nodes=[0])]
    gltf.set_binary_blob(blob)
    path = tmp_path / "static.glb"
    path.write_bytes(b"".join(gltf.save_to_bytes()))
    return path


def test_character_without_morph_targets_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="no morph targets"):
        run_stage(GltfCharacter, {}, {"mesh": gltf_without_targets(tmp_path)})


def test_compressed_gltf_is_refused_clearly(tmp_path):
    import pygltflib

    path = gltf_without_targets(tmp_path)
    gltf = pygltflib.GLTF2().load(str(path))
    gltf.extensionsUsed = gltf.extensionsRequired = ["KHR_draco_mesh_compression"]
    path.write_bytes(b"".join(gltf.save_to_bytes()))
    with pytest.raises(UserError, match="KHR_draco_mesh_compression"):
        run_stage(GltfCharacter, {}, {"mesh": path})


def test_broken_and_wrong_files_are_user_errors(tmp_path):
    (tmp_path / "broken.glb").write_bytes(b"glTF\x02\x00\x00\x00garbage")
    with pytest.raises(UserError):
        run_stage(GltfCharacter, {}, {"mesh": tmp_path / "broken.glb"})
    (tmp_path / "mesh.obj").write_text("v 0 0 0\n")
    with pytest.raises(UserError, match="glb"):
        run_stage(GltfCharacter, {}, {"mesh": tmp_path / "mesh.obj"})


def test_gltf_with_data_uri_strided_positions_and_node_transform(tmp_path):
    """A foreign layout: .gltf JSON with a base64 buffer, interleaved POSITION/NORMAL (byteStride 24), dense morph
    target, no targetNames, and a node that scales by 2 and translates."""
    import base64

    import pygltflib

    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    n = np.tile(np.array([[0, 0, 1]], np.float32), (4, 1))
    interleaved = np.concatenate([v, n], axis=1).astype(np.float32).tobytes()
    idx = np.array([0, 1, 2, 0, 2, 3], np.uint16).tobytes()
    delta = np.array([[0, 0, 0], [0, 0, 0], [0.1, 0.2, 0.3], [0, 0, 0]], np.float32).tobytes()
    blob = interleaved + idx + b"\0\0\0\0" + delta
    gltf = pygltflib.GLTF2()
    gltf.buffers = [
        pygltflib.Buffer(
            byteLength=len(blob), uri="data:application/octet-stream;base64," + base64.b64encode(blob).decode()
        )
    ]
    gltf.bufferViews = [
        pygltflib.BufferView(buffer=0, byteOffset=0, byteLength=len(interleaved), byteStride=24, target=34962),
        pygltflib.BufferView(buffer=0, byteOffset=len(interleaved), byteLength=len(idx), target=34963),
        pygltflib.BufferView(buffer=0, byteOffset=len(interleaved) + len(idx) + 4, byteLength=len(delta)),
    ]
    gltf.accessors = [
        pygltflib.Accessor(
            bufferView=0,
            byteOffset=0,
            componentType=5126,
            count=4,
            type="VEC3",
            min=[0.0, 0.0, 0.0],
            max=[1.0, 1.0, 0.0],
        ),
        pygltflib.Accessor(bufferView=0, byteOffset=12, componentType=5126, count=4, type="VEC3"),
        pygltflib.Accessor(bufferView=1, componentType=5123, count=6, type="SCALAR"),
        pygltflib.Accessor(
            bufferView=2, componentType=5126, count=4, type="VEC3", min=[0.0, 0.0, 0.0], max=[0.1, 0.2, 0.3]
        ),
    ]
    gltf.meshes = [
        pygltflib.Mesh(
            primitives=[
                pygltflib.Primitive(
                    attributes=pygltflib.Attributes(POSITION=0, NORMAL=1),
                    indices=2,
                    targets=[pygltflib.Attributes(POSITION=3)],
                )
            ]
        )
    ]
    gltf.nodes = [pygltflib.Node(mesh=0, scale=[2.0, 2.0, 2.0], translation=[0.0, 5.0, 0.0])]
    gltf.scenes = [pygltflib.Scene(nodes=[0])]
    path = tmp_path / "foreign.gltf"
    path.write_text(gltf.to_json())
    mesh = read_morph_mesh(path)
    assert np.allclose(mesh.positions, v * 2 + [0, 5, 0])
    assert mesh.target_names == ["target_000"]
    assert np.allclose(mesh.deltas[0, 2], [0.2, 0.4, 0.6])
    assert mesh.triangles.tolist() == [[0, 1, 2], [0, 2, 3]]
    with pytest.raises(UserError, match="no face found.*JSON file input 'landmarks'"):  # a quad has no face
        run_stage(GltfCharacter, {}, {"mesh": path})
    (tmp_path / "lm.json").write_text(json.dumps([0, 1, 2, 3] * 17))
    out = run_stage(GltfCharacter, {}, {"mesh": path, "landmarks": tmp_path / "lm.json"})
    assert out.arrays["landmark_ids"].tolist() == [0, 1, 2, 3] * 17


# ------------------------------------------------------------------------------------------------ embedded ICT


@pytest.fixture(scope="module")
def ict():
    return run_stage(GltfCharacter, {}, {"mesh": ICT_GLB})


ICT_EXPRESSIONS = {
    "browDown_L",
    "browDown_R",
    "browInnerUp_L",
    "browInnerUp_R",
    "browOuterUp_L",
    "browOuterUp_R",
    "cheekPuff_L",
    "cheekPuff_R",
    "cheekSquint_L",
    "cheekSquint_R",
    "eyeBlink_L",
    "eyeBlink_R",
    "eyeLookDown_L",
    "eyeLookDown_R",
    "eyeLookIn_L",
    "eyeLookIn_R",
    "eyeLookOut_L",
    "eyeLookOut_R",
    "eyeLookUp_L",
    "eyeLookUp_R",
    "eyeSquint_L",
    "eyeSquint_R",
    "eyeWide_L",
    "eyeWide_R",
    "jawForward",
    "jawLeft",
    "jawOpen",
    "jawRight",
    "mouthClose",
    "mouthDimple_L",
    "mouthDimple_R",
    "mouthFrown_L",
    "mouthFrown_R",
    "mouthFunnel",
    "mouthLeft",
    "mouthLowerDown_L",
    "mouthLowerDown_R",
    "mouthPress_L",
    "mouthPress_R",
    "mouthPucker",
    "mouthRight",
    "mouthRollLower",
    "mouthRollUpper",
    "mouthShrugLower",
    "mouthShrugUpper",
    "mouthSmile_L",
    "mouthSmile_R",
    "mouthStretch_L",
    "mouthStretch_R",
    "mouthUpperUp_L",
    "mouthUpperUp_R",
    "noseSneer_L",
    "noseSneer_R",
    "cheekRaiser_L",
    "cheekRaiser_R",
    "PupilDilate_L",
    "PupilDilate_R",
}


def test_embedded_character_files_size_and_validity(node_modules):
    folder = ICT_GLB.parent
    assert ICT_GLB.stat().st_size <= 10 * 1024 * 1024
    assert "MIT License" in (folder / "LICENSE").read_text()
    assert "Bladin" in (folder / "CREDITS.md").read_text()
    readme = (folder / "README.md").read_text()
    assert "python -m stages.retarget.ict_facekit build" in readme
    report = validate_glb(ICT_GLB.read_bytes())
    assert report["numErrors"] == 0 and report["numWarnings"] == 0, report["messages"]


def test_embedded_character_has_all_57_targets_and_sane_landmarks(ict):
    names = ict.meta["target_names"]
    assert len(names) == 57 and set(names) == ICT_EXPRESSIONS
    assert ict.meta["source"]["identity_targets"] == [f"identity{i:03d}" for i in range(10)]
    v = ict.arrays["neutral"]
    ids = ict.arrays["landmark_ids"]
    assert ids.shape == (68,) and ids.min() >= 0 and ids.max() < len(v)
    lm = v[ids]
    width = np.ptp(v[:, 0])
    assert 0.12 < width < 0.4  # metres: a human head
    assert lm[36, 0] < 0 < lm[45, 0]  # iBUG 36 (right eye outer corner) on the character's right (-x)
    assert lm[30, 2] == lm[:, 2].max()  # nose tip nearest the viewer
    assert lm[8, 1] == lm[:, 1].min()  # chin lowest
    assert lm[19, 1] > lm[37, 1] > lm[30, 1] > lm[51, 1] > lm[57, 1]  # brow, eye, nose, lips top to bottom
    d = ict.arrays["deltas"]
    blink_l = np.abs(d[names.index("eyeBlink_L")]).max(axis=1) > 1e-3
    assert v[blink_l, 0].mean() > 0.01  # _L is the character's left (+x)
    jaw = d[names.index("jawOpen")]
    assert jaw[ids[8], 1] < -0.005  # the chin goes down


def test_embedded_character_is_the_default(ict):
    from stages.retarget.character import DEFAULT_CHARACTER

    assert DEFAULT_CHARACTER == ICT_GLB.resolve()
    assert GltfCharacter.resources["character"] == DEFAULT_CHARACTER
    assert all(path.is_file() for path in GltfCharacter.resources.values())  # the tracker's too (auto_landmarks)
    default = run_stage(GltfCharacter, {}, {})
    assert np.array_equal(default.arrays["neutral"], ict.arrays["neutral"])
    assert default.meta["target_names"] == ict.meta["target_names"]


def test_embedded_character_identity_mix(ict):
    mixed = run_stage(GltfCharacter, {"identity": {"identity000": 1.0, "identity003": -0.5}}, {"mesh": ICT_GLB})
    raw = read_morph_mesh(ICT_GLB)
    names = raw.target_names
    expected = raw.positions + raw.deltas[names.index("identity000")] - 0.5 * raw.deltas[names.index("identity003")]
    assert np.allclose(mixed.arrays["neutral"], expected, atol=1e-6)
    assert np.abs(mixed.arrays["neutral"] - ict.arrays["neutral"]).max() > 1e-3
    assert np.array_equal(mixed.arrays["deltas"], ict.arrays["deltas"])
    assert mixed.meta["identity"] == {"identity000": 1.0, "identity003": -0.5}


def test_builder_on_an_ict_like_folder(tmp_path, node_modules):
    """The builder on a small folder in ICT FaceKit's layout: overlay groups dropped, eye shells removed, the
    eyeball painted, identity targets flagged, landmark ids remapped; the GLB validates."""
    src = tmp_path / "ict"
    src.mkdir()
    face_v, face_q = grid(10, 10)
    ball_v, ball_q = sphere_quads(6, 8, centre=(0.5, 0.2, 0.3), radius=0.15)
    shell_v, shell_q = sphere_quads(6, 8, centre=(0.5, 0.2, 0.3), radius=0.17)
    lash_v, lash_q = grid(3, 2)
    parts = [
        (face_v, face_q, "M_Face"),
        (shell_v, shell_q, "M_ScleraLeft"),
        (ball_v, ball_q, "M_IrisLeft"),
        (lash_v * 0.1 + [0.5, 0.4, 0.4], lash_q, "M_EyeLashes"),
    ]
    vertices, faces, groups, offset = [], [], [], 0
    for g, (v, q, name) in enumerate(parts):
        vertices.append(v)
        faces.append(q + offset)
        groups += [g] * len(q)
        offset += len(v)
    v = np.concatenate(vertices) * 10  # centimetres, like ICT
    q = np.concatenate(faces)
    names = [p[2] for p in parts]
    write(src / "generic_neutral_mesh.obj.gz", obj_text(v, q, groups, names))
    rng = np.random.default_rng(5)
    d_jaw = np.zeros_like(v)
    d_jaw[:50, 1] = -0.5
    write(src / "jawOpen.obj.gz", obj_text(v + d_jaw, q))
    write(src / "eyeBlink_L.obj.gz", obj_text(v + np.where(np.arange(len(v))[:, None] >= len(face_v), 0.02, 0), q))
    d_id = rng.normal(0, 0.1, v.shape)
    write(src / "identity000.obj.gz", obj_text(v + d_id, q))
    ids = rng.choice(len(face_v), 68, replace=False)
    (src / "vertex_indices.json").write_text(
        json.dumps({"expressions": ["jawOpen", "eyeBlink_L"], "idx_to_landmark_verts": ids.tolist()})
    )
    (src / "ICTFaceModelMaterial.mtl").write_text("newmtl M_Face\nKd 0.6 0.6 0.6\nnewmtl M_IrisLeft\nKd 0.2 0.2 0.2\n")
    (src / "LICENSE").write_text("MIT License\n")
    (src / "CREDITS.md").write_text("credits\n")
    dst = tmp_path / "out" / "char.glb"
    summary = build_ict_character(src, dst)
    assert summary["dropped_groups"] == ["M_EyeLashes"]
    assert summary["eye_shell_triangles_removed"] == 2 * len(shell_q)
    assert (dst.parent / "LICENSE").is_file() and (dst.parent / "README.md").is_file()
    report = validate_glb(dst.read_bytes())
    assert report["numErrors"] == 0 and report["numWarnings"] == 0, report["messages"]
    out = run_stage(GltfCharacter, {}, {"mesh": dst})
    assert out.meta["target_names"] == ["jawOpen", "eyeBlink_L"]
    assert out.meta["source"]["identity_targets"] == ["identity000"]
    kept = len(face_v) + len(ball_v)
    assert len(out.arrays["neutral"]) == kept
    assert np.allclose(out.arrays["neutral"][out.arrays["landmark_ids"]], 0.01 * v[ids], atol=1e-6)
    assert np.allclose(out.arrays["deltas"][0][:50, 1], -0.005, atol=1e-6)
    group_names = [g["name"] for g in out.meta["groups"]]
    assert {"M_EyeScleraLeft", "M_EyeIrisLeft", "M_EyePupilLeft"} <= set(group_names)
    # the pupil is at the front of the eyeball (towards +z), the sclera part behind
    tg = out.arrays["triangle_groups"]
    centroid = out.arrays["neutral"][out.arrays["triangles"]].mean(axis=1)
    assert (
        centroid[tg == group_names.index("M_EyePupilLeft"), 2].mean()
        > centroid[tg == group_names.index("M_EyeScleraLeft"), 2].mean()
    )


def sphere_quads(n_lat, n_lon, centre, radius):
    """A closed quad sphere (poles as degenerate quads) facing outward, densest nowhere in particular; the +z pole
    gets an extra ring so the vertex mean leans forward like ICT's eyeball."""
    lat = np.r_[np.linspace(0, np.pi, n_lat)]
    lat = np.sort(np.r_[lat, 0.05, 0.1, 0.15])
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    t, p = np.meshgrid(lat, lon, indexing="ij")
    # +z pole at lat = 0
    v = np.c_[(np.sin(t) * np.cos(p)).ravel(), (np.sin(t) * np.sin(p)).ravel(), np.cos(t).ravel()]
    v = v * radius + np.asarray(centre)
    idx = np.arange(len(v)).reshape(len(lat), n_lon)
    nxt = np.roll(idx, -1, axis=1)
    q = np.c_[idx[:-1].ravel(), idx[1:].ravel(), nxt[1:].ravel(), nxt[:-1].ravel()]
    c = v[q].mean(axis=1) - np.asarray(centre)
    nrm = np.cross(v[q[:, 1]] - v[q[:, 0]], v[q[:, 2]] - v[q[:, 0]])
    flip = (nrm * c).sum(axis=1) < 0
    q[flip] = q[flip][:, ::-1]
    return v, q


def test_figures_render_pngs(obj_folder):
    import cv2

    from stages.retarget.character import figure_landmarks, figure_targets

    f = obj_folder
    out = run_stage(
        ObjBlendshapes,
        {"neutral": "neutral"},
        {"shapes": shape_files(f["dir"]), "landmarks": f["dir"] / "landmarks.json"},
    )
    assert set(ObjBlendshapes.figures) == {"landmarks", "targets"}
    image = cv2.imdecode(np.frombuffer(figure_landmarks(out.view()), np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (512, 512, 3)
    assert (np.abs(image.astype(int) - [0, 200, 255]).sum(axis=2) < 60).sum() > 68  # the landmark dots
    sheet = cv2.imdecode(np.frombuffer(figure_targets(out.view(), tile=64, columns=2), np.uint8), cv2.IMREAD_COLOR)
    assert sheet.shape == (128, 128, 3)  # 3 targets in 2 columns: 2 rows


# ------------------------------------------------------------------------------------------------ identity fit


def facemesh_tracks(points: np.ndarray, frames: int = 4):
    """A tracking artifact whose FaceMesh's iBUG points are ``points`` (68, 3, head axes) seen from the front
    (image axes, pixels), every frame the same (a closed mouth: the character's neutral)."""
    from msflow.testing import artifact
    from stages.tracking.landmarks68 import MAPPING_MATRIX

    image = points * np.array([1.0, -1.0, -1.0]) * 2000.0 + np.array([320.0, 240.0, 0.0])
    mesh = np.linalg.pinv(MAPPING_MATRIX) @ image  # whose iBUG means are exactly ``image``
    return artifact({"mesh": np.repeat(mesh[None], frames, axis=0).astype(np.float32)}, meta={"fields": {}})


def test_fit_identity_recovers_known_coefficients(ict):
    """Known answer: a performer who is the character with a known identity mix gets that mix back."""
    truth = {"identity000": 1.0, "identity003": -0.5, "identity007": 0.8}
    performer = run_stage(GltfCharacter, {"identity": truth}, {"mesh": ICT_GLB})
    tracks = facemesh_tracks(performer.arrays["neutral"][performer.arrays["landmark_ids"]])
    fitted = run_stage(GltfCharacter, {"fit_identity": True, "identity_ridge": 1e-6}, {"tracks": tracks})
    for name, value in fitted.meta["identity"].items():
        assert value == pytest.approx(truth.get(name, 0.0), abs=0.05), name
    assert np.array_equal(fitted.arrays["deltas"], ict.arrays["deltas"])
    # the default ridge goes part of the way: the landmarks (up to a similarity) move towards the performer's
    from stages.retarget.identity import IDENTITY_POINTS
    from stages.retarget.shapes3d import similarity_align

    default = run_stage(GltfCharacter, {"fit_identity": True}, {"tracks": tracks})
    target, points = performer.arrays["neutral"][performer.arrays["landmark_ids"]], list(IDENTITY_POINTS)

    def distance(character):
        face = character.arrays["neutral"][character.arrays["landmark_ids"]]
        return np.abs(similarity_align(face[None], target, points)[0][points] - target[points]).max()

    assert distance(default) < 0.6 * distance(ict)


def test_fit_identity_needs_a_facemesh_and_excludes_given_coefficients():
    with pytest.raises(UserError, match="needs the performer's FaceMesh tracking"):
        run_stage(GltfCharacter, {"fit_identity": True}, {})
    with pytest.raises(ValueError, match="not both"):
        GltfCharacter.Params(fit_identity=True, identity={"identity000": 1.0})
