"""Export: GLB animation (validated by the Khronos glTF Validator), Live Link Face CSV, preview MP4 with audio, BVH;
stream alignment (frame rates, lengths, audio offset) and the user errors around them."""

import csv
import io
import os
import signal
from pathlib import Path

import av
import numpy as np
import pytest
from conftest import run_cli

from msflow import UserError
from msflow.testing import artifact, prepare_inputs, run_stage
from stages.export.animation import Export
from stages.export.timeline import align_head_motion, nominal_rate
from stages.formats.audio import decode_audio
from stages.formats.gltf import read_morph_mesh, validate_glb
from stages.formats.live_link import (
    ANGLE_COLUMNS,
    ARKIT_NAMES,
    ARKIT_TABLE,
    arkit_key,
    arkit_mapping,
    arkit_weights,
    fit_destination,
    format_timecode,
    live_link_csv,
    timecode_seconds,
)
from stages.geometry.rotations import euler_to_quat, quat_to_euler, quat_to_matrix
from stages.retarget.character import GltfCharacter

ROOT = Path(__file__).resolve().parents[1]
ICT_GLB = ROOT / "data" / "characters" / "ict-facekit.glb"
CLIP = ROOT / "data" / "crema-d" / "1001_DFA_HAP_XX.flv"
FPS = 30.0
FRAMES = 45
DRIVEN = ["jawOpen", "mouthSmile_L", "mouthSmile_R", "browInnerUp_L", "browInnerUp_R", "eyeBlink_L"]


ORIGIN = "http://msflow.test"
THREEJS_PAGE = """<!doctype html><html><body><canvas id=c width=128 height=128></canvas>
<script type="importmap">{"imports": {"three": "/three/build/three.module.js", "three/addons/": "/three/examples/jsm/"}}
</script>
<script type="module">
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
window.probe = async (times) => {
  const gltf = await new GLTFLoader().parseAsync(await (await fetch('/take.glb')).arrayBuffer(), '/');
  const scene = gltf.scene, meshes = [], bones = {};
  scene.traverse(o => { if (o.isMesh) meshes.push(o); if (o.isBone) bones[o.name] = o; });
  const mixer = new THREE.AnimationMixer(scene);
  mixer.clipAction(gltf.animations[0]).play();
  const canvas = document.getElementById('c');
  const renderer = new THREE.WebGLRenderer({canvas, preserveDrawingBuffer: true});
  const camera = new THREE.PerspectiveCamera(20, 1, 0.01, 10);
  camera.position.set(0, 0.03, 0.8);
  scene.add(new THREE.AmbientLight(0xffffff, 1.0));
  const frames = [];
  for (const t of times) {
    mixer.setTime(t);
    scene.updateMatrixWorld(true);
    renderer.render(scene, camera);
    const gl = renderer.getContext(), pixels = new Uint8Array(128 * 128 * 4);
    gl.readPixels(0, 0, 128, 128, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
    let image = 0;
    for (let i = 0; i < pixels.length; i += 4) image += pixels[i] + 3 * pixels[i + 1] + 7 * pixels[i + 2];
    frames.push({t, image, influences: Array.from(meshes[0].morphTargetInfluences),
      skinned: meshes.every(m => m.isSkinnedMesh), head: bones.Head.quaternion.toArray(),
      left: bones.LeftEye.quaternion.toArray()});
  }
  return {bones: Object.keys(bones), webgl: renderer.getContext() !== null,
          morphs: meshes[0].morphTargetDictionary, frames};
};
window.ready = true;
</script></body></html>"""


def probe_in_threejs(glb: bytes, node_modules: Path, chromium: str, times: list[float]) -> dict:
    """Load the GLB with three.js in headless Chromium (software WebGL), play it at ``times``, report the state.

    Files are served from a made-up origin through Playwright's routing (ES modules do not load from file:)."""
    from playwright.sync_api import sync_playwright

    def serve(route):
        path = route.request.url[len(ORIGIN) :]
        if path == "/":
            return route.fulfill(body=THREEJS_PAGE, content_type="text/html")
        if path == "/take.glb":
            return route.fulfill(body=glb, content_type="model/gltf-binary")
        file = node_modules / path.lstrip("/")
        if path.startswith("/three/") and file.is_file():
            return route.fulfill(body=file.read_bytes(), content_type="text/javascript")
        return route.fulfill(status=404, body="")

    args = ["--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=args)
        page = browser.new_page()
        errors: list[str] = []
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.route(ORIGIN + "/**", serve)
        page.goto(ORIGIN + "/")
        page.wait_for_function("window.ready === true")
        report = page.evaluate("(t) => window.probe(t)", times)
        browser.close()
    return report | {"errors": errors}


# ------------------------------------------------------------------------------------------------ Live Link Face


def test_arkit_names_and_keys():
    assert len(ARKIT_NAMES) == 52 and len(set(ARKIT_NAMES)) == 52
    assert ARKIT_NAMES[0] == "EyeBlinkLeft" and ARKIT_NAMES[-1] == "TongueOut"
    assert len(ANGLE_COLUMNS) == 9 and ANGLE_COLUMNS[:3] == ["HeadYaw", "HeadPitch", "HeadRoll"]
    assert arkit_key("eyeBlink_L") == "EyeBlinkLeft"
    assert arkit_key("mouthSmile_R") == "MouthSmileRight"
    assert arkit_key("jawOpen") == "JawOpen"
    assert arkit_key("eyeBlinkLeft") == "EyeBlinkLeft"  # ARKit camelCase passes through


def test_arkit_weights_map_split_and_missing_targets():
    names = [
        "eyeBlink_L",
        "jawOpen",
        "browInnerUp_L",
        "browInnerUp_R",
        "cheekPuff_L",
        "cheekPuff_R",
        "cheekRaiser_L",
        "tongueOut",
        "PupilDilate_L",
        "mouthSmile",
    ]
    w = np.array([[0.2, 0.5, 0.8, 0.4, 1.0, 0.0, 0.5, 0.3, 0.7, 0.25]])
    out, mapping = arkit_weights(w, names)
    col = {n: out[0, i] for i, n in enumerate(ARKIT_NAMES)}
    assert col["EyeBlinkLeft"] == pytest.approx(0.2)
    assert col["JawOpen"] == pytest.approx(0.5)
    assert col["BrowInnerUp"] == pytest.approx(0.6)  # mean of the halves
    assert col["CheekPuff"] == pytest.approx(0.5)
    assert col["TongueOut"] == pytest.approx(0.3)
    assert col["MouthSmileLeft"] == col["MouthSmileRight"] == pytest.approx(0.25)  # a whole shape feeds both sides
    # the raised cheek goes to the cheek and eye squint columns of its side
    assert col["CheekSquintLeft"] == pytest.approx(0.5 * ARKIT_TABLE["cheekRaiser_L"]["CheekSquintLeft"])
    assert col["EyeSquintLeft"] == pytest.approx(0.5 * ARKIT_TABLE["cheekRaiser_L"]["EyeSquintLeft"])
    assert col["EyeBlinkRight"] == 0.0 and col["CheekSquintRight"] == 0.0
    assert mapping.sources["BrowInnerUp"] == ["browInnerUp_L", "browInnerUp_R"]
    assert mapping.rule["cheekRaiser_L"] == "table" and mapping.rule["jawOpen"] == "namesake"
    assert mapping.unmapped == ["PupilDilate_L"] and mapping.dropped(w) == ["PupilDilate_L"]
    assert mapping.dropped(w * 0) == []
    assert "EyeBlinkRight" in mapping.missing_columns and "JawOpen" not in mapping.missing_columns


def test_arkit_sums_are_clipped_and_aliases_take_precedence():
    names = ["cheekSquint_L", "cheekRaiser_L", "smile_left"]
    out, mapping = arkit_weights(np.array([[1.0, 1.0, 0.4]]), names, aliases={"smile_left": {"MouthSmileLeft": 2.0}})
    col = dict(zip(ARKIT_NAMES, out[0]))
    assert col["CheekSquintLeft"] == 1.0  # 1 + 0.92, clipped to ARKit's [0, 1]
    assert col["MouthSmileLeft"] == pytest.approx(0.8) and mapping.rule["smile_left"] == "alias"
    with pytest.raises(ValueError, match="did you mean 'MouthSmileLeft'"):
        arkit_mapping(names, aliases={"smile_left": {"mouthSmile_L": 1.0}})


def test_fitted_destination_recovers_a_known_mix():
    """A morph built as 0.7 jawOpen + 0.4 mouthFunnel (plus noise far below) is placed in those columns."""
    rng = np.random.default_rng(1)
    basis = rng.normal(size=(4, 50, 3))
    names = ["jawOpen", "mouthFunnel", "browDown_L", "browInnerUp_L", "ahVowel"]
    mix = 0.7 * basis[0] + 0.4 * basis[1] + 0.01 * rng.normal(size=(50, 3))
    mapping = arkit_mapping(names, deltas=np.r_[basis, mix[None]])
    assert mapping.rule["ahVowel"] == "fitted"
    assert mapping.destinations["ahVowel"] == pytest.approx({"JawOpen": 0.7, "MouthFunnel": 0.4}, abs=0.011)
    assert mapping.explained["ahVowel"] > 0.95
    # a half-shape (BrowInnerUp x 0.5) is used at its unit: a copy of browInnerUp_L maps to 0.5 of the column
    half = arkit_mapping(names[:4] + ["browCopy"], deltas=np.r_[basis, basis[3:4]])
    assert half.destinations["browCopy"] == pytest.approx({"BrowInnerUp": 0.5})
    # unrelated displacement: no destination rather than a poor one
    lone = arkit_mapping(names, deltas=np.r_[basis, rng.normal(size=(1, 50, 3))])
    assert lone.rule["ahVowel"] == "none"


def test_ict_table_is_the_fit_of_the_ict_displacements():
    """ARKIT_TABLE's factors are fit_destination of each morph on the ICT head (documented derivation)."""
    mesh = read_morph_mesh(ICT_GLB)
    names = [n for n in mesh.target_names if not n.startswith("identity")]
    mapping = arkit_mapping(names)
    basis_names = [n for n in names if mapping.rule[n] == "namesake" and len(mapping.destinations[n]) == 1]
    columns = [next(iter(mapping.destinations[n])) for n in basis_names]
    basis = np.stack(
        [mesh.deltas[mesh.target_names.index(n)] / mapping.destinations[n][c] for n, c in zip(basis_names, columns)]
    )
    for morph, table in ARKIT_TABLE.items():
        fitted, explained = fit_destination(mesh.deltas[mesh.target_names.index(morph)], basis, columns)
        assert fitted == pytest.approx(table, abs=0.011), morph
        assert explained > 0.55


def test_every_moving_ict_morph_has_a_destination():
    mesh = read_morph_mesh(ICT_GLB)
    names = [n for n in mesh.target_names if not n.startswith("identity")]
    mapping = arkit_mapping(names, deltas=mesh.deltas[: len(names)])
    assert mapping.unmapped == ["PupilDilate_L", "PupilDilate_R"]  # ARKit has no pupil
    assert mapping.missing_columns == ["TongueOut"]  # ICT has no tongue shape
    assert set(mapping.rule.values()) == {"namesake", "table", "none"}


def test_timecodes():
    assert format_timecode(np.array([0, 1, 29, 30, 61, 30 * 3600 + 45]), 30.0) == [
        "00:00:00:00.000",
        "00:00:00:01.000",
        "00:00:00:29.000",
        "00:00:01:00.000",
        "00:00:02:01.000",
        "01:00:01:15.000",
    ]
    # 29.97 fps (30000/1001): frames labelled at the nominal 30 with the exact sub-frame remainder
    codes = format_timecode(np.arange(40000), 30000 / 1001)
    assert codes[1] == "00:00:00:01.001" and codes[30] == "00:00:01:00.030"
    assert codes == format_timecode(np.arange(40000), 29.97)
    seconds = np.array([timecode_seconds(c, 29.97) for c in codes])
    assert np.abs(seconds - np.arange(40000) * 1001 / 30000).max() < 0.5e-3 / 30 + 1e-9
    assert len(set(codes)) == 40000
    assert format_timecode(np.array([3]), 60.0) == ["00:00:00:03.000"]
    assert format_timecode(np.array([24]), 24000 / 1001) == ["00:00:01:00.024"]


def test_live_link_csv_layout():
    rng = np.random.default_rng(0)
    arkit = rng.uniform(0, 1, (5, 52))
    head = rng.uniform(-0.3, 0.3, (5, 3))
    text = live_link_csv(arkit, 60.0, head).decode()
    rows = list(csv.reader(io.StringIO(text)))
    assert rows[0] == ["Timecode", "BlendShapeCount"] + ARKIT_NAMES + ANGLE_COLUMNS
    assert len(rows) == 6
    for i, row in enumerate(rows[1:]):
        assert len(row) == 63 and row[1] == "61"
        assert row[0] == f"00:00:00:{i:02d}.000"
        assert np.allclose([float(x) for x in row[2:54]], arkit[i], atol=1e-6)
        assert np.allclose([float(x) for x in row[54:57]], head[i], atol=1e-6)
        assert [float(x) for x in row[57:]] == [0.0] * 6


# ------------------------------------------------------------------------------------------------ alignment


def test_head_motion_alignment_resamples_holds_and_refuses():
    yaw = np.linspace(0, 0.5, 26)  # 25 fps, constant angular velocity
    rot = euler_to_quat(yaw, 0 * yaw, 0 * yaw)
    trans = np.c_[np.linspace(0, 1, 26), 0 * yaw, 0 * yaw]
    with pytest.raises(UserError, match="frame-rate mismatch"):
        align_head_motion(rot, trans, 25.0, 30.0, 31, resample=False, max_mismatch=0.25)
    r, t, info = align_head_motion(rot, trans, 25.0, 30.0, 31, resample=True, max_mismatch=0.25)
    times = np.arange(31) / 30.0
    assert np.allclose(quat_to_euler(r)[:, 0], np.minimum(times, 1.0) * 0.5, atol=1e-9)
    assert np.allclose(t[:, 0], np.minimum(times, 1.0), atol=1e-9)
    assert info["resampled"]
    # same rate, slightly short: the last pose holds
    r, t, info = align_head_motion(rot, trans, 25.0, 25.0, 30, resample=False, max_mismatch=0.25)
    assert info["held_frames"] == 4 and np.allclose(r[-4:], rot[-1])
    with pytest.raises(UserError, match="lasts"):
        align_head_motion(rot, trans, 25.0, 25.0, 60, resample=False, max_mismatch=0.25)
    with pytest.raises(UserError, match="lasts"):
        align_head_motion(rot, trans, 25.0, 25.0, 10, resample=False, max_mismatch=0.25)


# ------------------------------------------------------------------------------------------------ the stage


@pytest.fixture(scope="module")
def character():
    return run_stage(GltfCharacter, {}, {"mesh": ICT_GLB})


def make_gaze(frames=FRAMES, fps=FPS):
    """(frames, 2, 2) degrees: yaw 20 sin(2 pi t) (right eye 0.8 of it), pitch 10 cos(2 pi t) up."""
    t = np.arange(frames) / fps
    gaze = np.zeros((frames, 2, 2), np.float32)
    gaze[:, 0, 0], gaze[:, 1, 0] = 20 * np.sin(2 * np.pi * t), 16 * np.sin(2 * np.pi * t)
    gaze[:, :, 1] = 10 * np.cos(2 * np.pi * t)[:, None]
    return gaze


def make_blend(frames=FRAMES, fps=FPS, gaze=False):
    t = np.arange(frames) / fps
    w = np.zeros((frames, len(DRIVEN)), np.float32)
    w[:, 0] = np.where((t > 0.5) & (t < 1.0), 1.0, 0.0)  # jaw open between 0.5 s and 1 s
    w[:, 1] = w[:, 2] = np.linspace(0, 1, frames)
    w[:, 3], w[:, 4] = 0.8, 0.4
    w[:, 5] = 0.3
    arrays = {"weights": w, "gaze": make_gaze(frames, fps)} if gaze else {"weights": w}
    return artifact(arrays, {"target_names": DRIVEN, "fps": fps})


def make_head(frames=FRAMES, fps=FPS, units="cm"):
    t = np.arange(frames) / fps
    rot = euler_to_quat(0.3 * np.sin(2 * np.pi * t), 0.1 * np.cos(2 * np.pi * t), 0.05 * t)
    trans = np.c_[2.0 * np.sin(2 * np.pi * t), np.zeros(frames), 50.0 + np.zeros(frames)]
    return artifact({"rotation": rot, "translation": trans}, {"fps": fps, "translation_units": units})


def make_audio(offset: float, rate=16000, beep_at=0.6, beep_len=0.2):
    """A tracking-like audio artifact: two takes; the second is silence with a 1 kHz beep ``beep_at`` seconds
    into its audio track, whose first sample is ``offset`` seconds after the first video frame."""
    real = decode_audio(CLIP, rate)
    beep = np.zeros(int(2.0 * rate), np.float32)
    k = np.arange(int(beep_len * rate))
    beep[int(beep_at * rate) : int(beep_at * rate) + len(k)] = 0.5 * np.sin(2 * np.pi * 1000 * k / rate)
    audio = np.concatenate([real.samples, beep])
    bounds = np.array([[0, len(real.samples)], [len(real.samples), len(audio)]])
    return artifact(
        {"audio": audio, "audio_bounds": bounds},
        {
            "labels": ["happy", "beep"],
            "audio_rate": rate,
            "fps": [FPS, FPS],
            "audio_offset": [real.offset_to_video, offset],
        },
    )


@pytest.fixture(scope="module")
def exported(character):
    out = run_stage(
        Export,
        {"sequence": "beep", "video_size": 256, "head_rotation": "absolute"},
        {
            "character": character.view(),
            "blend": make_blend(gaze=True),
            "head": make_head(),
            "audio": make_audio(offset=0.1),
        },
    )
    return out


def test_glb_passes_the_khronos_validator(exported, node_modules):
    report = validate_glb(exported.arrays["animation"].tobytes(), node_modules=node_modules)
    assert report["numErrors"] == 0, report["messages"]
    assert report["numWarnings"] == 0, report["messages"]


def test_glb_animation_holds_the_weights_and_head_motion(exported, character, tmp_path):
    import pygltflib

    path = tmp_path / "anim.glb"
    path.write_bytes(exported.arrays["animation"].tobytes())
    gltf = pygltflib.GLTF2().load(str(path))
    blob = gltf.binary_blob()

    def accessor(i):
        acc = gltf.accessors[i]
        view = gltf.bufferViews[acc.bufferView]
        n = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc.type]
        return np.frombuffer(blob, np.float32, acc.count * n, view.byteOffset + acc.byteOffset).reshape(acc.count, n)

    anim = gltf.animations[0]
    paths = {ch.target.path: ch for ch in anim.channels}
    assert set(paths) == {"weights", "rotation", "translation"}
    names = character.meta["target_names"]
    sampler = anim.samplers[paths["weights"].sampler]
    times = accessor(sampler.input)[:, 0]
    assert np.allclose(times, np.arange(FRAMES) / FPS)
    weights = accessor(sampler.output).reshape(FRAMES, len(names))
    blend = make_blend()
    for k, name in enumerate(DRIVEN):
        assert np.allclose(weights[:, names.index(name)], blend["weights"][:, k])
    others = [i for i, n in enumerate(names) if n not in DRIVEN]
    assert np.all(weights[:, others] == 0)
    xyzw = accessor(anim.samplers[paths["rotation"].sampler].output)
    q = xyzw[:, [3, 0, 1, 2]]
    expected = make_head()["rotation"]
    assert np.allclose(np.abs((q * expected).sum(axis=1)), 1.0, atol=1e-6)
    head_node = gltf.nodes[paths["rotation"].target.node]
    pivot = np.array(head_node.translation)
    trans = accessor(anim.samplers[paths["translation"].sampler].output) - pivot
    cm = make_head()["translation"] * 0.01
    assert np.allclose(trans, cm - cm.mean(axis=0), atol=1e-6)  # relative, in metres
    assert gltf.nodes[paths["weights"].target.node].mesh == 0
    # the GLB is itself a character again: same neutral and (up to the sparse tolerance) the same deltas
    mesh = read_morph_mesh(path)
    assert np.allclose(mesh.positions, character.arrays["neutral"], atol=1e-6)
    assert np.abs(mesh.deltas - character.arrays["deltas"]).max() <= 1e-5


def csv_by_name(data: bytes) -> dict[str, np.ndarray]:
    """Reader 1: Python's csv module, columns looked up by header name."""
    rows = list(csv.DictReader(io.StringIO(bytes(data).decode())))
    return {name: np.array([float(r[name]) for r in rows]) for name in ARKIT_NAMES + ANGLE_COLUMNS} | {
        "Timecode": [r["Timecode"] for r in rows]
    }


def csv_by_position(data: bytes) -> np.ndarray:
    """Reader 2: numpy's text parser, the 61 values by position (columns 2..62), header skipped unread."""
    return np.loadtxt(io.StringIO(bytes(data).decode()), delimiter=",", skiprows=1, usecols=range(2, 63), ndmin=2)


def test_live_link_csv_read_by_name_and_by_position(exported):
    data = exported.arrays["live_link"].tobytes()
    named, values = csv_by_name(data), csv_by_position(data)
    assert values.shape == (FRAMES, 61)
    assert np.allclose(values[:, :52], exported.arrays["arkit"], atol=1e-6)
    for k, name in enumerate(ARKIT_NAMES + ANGLE_COLUMNS):  # both readers see the same numbers
        assert np.array_equal(named[name], values[:, k]), name
    t = np.arange(FRAMES) / FPS
    assert np.allclose(named["JawOpen"], make_blend()["weights"][:, 0], atol=1e-6)
    assert np.allclose(named["BrowInnerUp"], 0.6, atol=1e-6)
    assert np.all(named["EyeBlinkRight"] == 0.0)
    assert np.allclose(named["HeadYaw"], 0.3 * np.sin(2 * np.pi * t), atol=1e-5)  # radians
    # eye angles from the gaze: yaw as is, pitch in the head's convention (> 0 looks down), radians
    gaze = np.radians(make_gaze())
    assert np.allclose(named["LeftEyeYaw"], gaze[:, 0, 0], atol=1e-6)
    assert np.allclose(named["RightEyeYaw"], gaze[:, 1, 0], atol=1e-6)
    assert np.allclose(named["LeftEyePitch"], -gaze[:, 0, 1], atol=1e-6)
    assert np.all(named["LeftEyeRoll"] == 0.0)
    assert [timecode_seconds(c, FPS) for c in named["Timecode"]] == pytest.approx(t, abs=1e-9)
    assert exported.metrics["live_link_columns_filled"] == 51  # ICT has all ARKit shapes but TongueOut


def glb_accessor(gltf, index: int) -> np.ndarray:
    """A dense accessor of a pygltflib GLTF2 loaded from a GLB."""
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    dtype = {5126: np.float32, 5121: np.uint8, 5123: np.uint16}[acc.componentType]
    n = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    offset = (view.byteOffset or 0) + (acc.byteOffset or 0)
    return np.frombuffer(gltf.binary_blob(), dtype, acc.count * n, offset).reshape(acc.count, n)


def load_glb(data: bytes, tmp_path):
    import pygltflib

    path = tmp_path / "take.glb"
    path.write_bytes(data)
    return pygltflib.GLTF2().load(str(path))


def test_glb_is_skinned_to_root_head_and_eye_joints(exported, character, tmp_path):
    """Root and Head joints, an eye joint at each eyeball's centre; every vertex follows the head with weight 1,
    but the eyeballs', which follow their eye; head motion on the Head joint, gaze on the eye joints."""
    from stages.export.rig import gaze_rotations

    gltf = load_glb(exported.arrays["animation"].tobytes(), tmp_path)
    skin = gltf.skins[0]
    names = [gltf.nodes[j].name for j in skin.joints]
    assert names == ["Root", "Head", "LeftEye", "RightEye"]
    mesh_node = next(n for n in gltf.nodes if n.mesh is not None)
    assert mesh_node.skin == 0 and gltf.nodes.index(mesh_node) in gltf.scenes[0].nodes  # a root node
    attributes = gltf.meshes[0].primitives[0].attributes
    joints, weights = glb_accessor(gltf, attributes.JOINTS_0), glb_accessor(gltf, attributes.WEIGHTS_0)
    assert np.all(weights == [1, 0, 0, 0])
    eyes = [e for e in exported.meta["eyes"]]
    groups = [g["name"] for g in character.meta["groups"]]
    tri_groups = character.arrays["triangle_groups"]
    for side, joint in ((0, 2), (1, 3)):
        eye_groups = [i for i, g in enumerate(groups) if "Eye" in g and ("Left" if side == 0 else "Right") in g]
        ids = np.unique(character.arrays["triangles"][np.isin(tri_groups, eye_groups)])
        assert np.all(joints[ids, 0] == joint)
        assert np.allclose(eyes[side]["radius"], 0.0144, atol=5e-4)  # the ICT eyeball, 14.4 mm
    assert (joints[:, 0] == 1).sum() == len(joints) - sum(np.sum(joints[:, 0] == j) for j in (2, 3))
    assert np.all(joints[:, 1:] == 0)
    # inverse bind matrices translate by minus each joint's position
    ibm = glb_accessor(gltf, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    assert np.allclose(ibm[2, :3, 3], -np.array(eyes[0]["center"]), atol=1e-6)
    assert np.allclose(ibm[1, :3, 3], -np.array(character.meta["pivot"]), atol=1e-6)
    # the animation: weights on the mesh node, head on Head, gaze on the eyes
    anim = gltf.animations[0]
    target = {(gltf.nodes[c.target.node].name, c.target.path): anim.samplers[c.sampler].output for c in anim.channels}
    assert set(target) == {
        ("Character", "weights"),
        ("Head", "rotation"),
        ("Head", "translation"),
        ("LeftEye", "rotation"),
        ("RightEye", "rotation"),
    }
    head = glb_accessor(gltf, target["Head", "rotation"])[:, [3, 0, 1, 2]]
    assert np.allclose(np.abs((head * make_head()["rotation"]).sum(axis=1)), 1.0, atol=1e-6)
    left = glb_accessor(gltf, target["LeftEye", "rotation"])[:, [3, 0, 1, 2]]
    assert np.allclose(np.abs((left * gaze_rotations(make_gaze())[:, 0]).sum(axis=1)), 1.0, atol=1e-6)


def test_gaze_without_eyes_goes_to_the_csv_with_a_warning(character, tmp_path):
    inputs = {"character": character.view(), "blend": make_blend(gaze=True)}
    result = run_with_warnings({"preview": False, "skin": False}, inputs)
    assert any("gaze goes to the Live Link CSV only" in w for w in result.warnings)
    named = csv_by_name(result.arrays["live_link"])
    assert np.allclose(named["LeftEyeYaw"], np.radians(make_gaze()[:, 0, 0]), atol=1e-6)
    plain = load_glb(result.arrays["animation"], tmp_path)
    assert not plain.skins and [n.name for n in plain.nodes] == ["Head", "Character"]


def test_output_frame_rate(character):
    """fps: 60 from a 30 fps take: twice the frames, same duration, integer timecodes, streams interpolated."""
    inputs = {"character": character.view(), "blend": make_blend(gaze=True), "head": make_head()}
    out = run_stage(Export, {"preview": False, "fps": 60, "head_rotation": "absolute"}, inputs)
    frames = 2 * FRAMES
    assert len(out.arrays["weights"]) == frames and out.meta["fps"] == 60.0
    assert np.allclose(out.arrays["time"], np.arange(frames) / 60)
    names = out.meta["target_names"]
    smile = out.arrays["weights"][:, names.index("mouthSmile_L")]
    ramp = np.linspace(0, 1, FRAMES)  # the blend's ramp, sampled at half frames and held past its end
    assert np.allclose(smile, np.interp(np.arange(frames) / 2, np.arange(FRAMES), ramp), atol=1e-6)
    yaw = quat_to_euler(out.arrays["head_rotation"])[:, 0]
    t = np.minimum(np.arange(frames) / 60, (FRAMES - 1) / FPS)
    assert np.allclose(yaw[::2], 0.3 * np.sin(2 * np.pi * t[::2]), atol=1e-6)
    codes = csv_by_name(out.arrays["live_link"])["Timecode"]
    assert codes[61] == "00:00:01:01.000" and all(c.endswith(".000") for c in codes)
    assert np.allclose(out.arrays["gaze"][::2], make_gaze(), atol=1e-5)
    for bad in (0, -30, 241):
        with pytest.raises(ValueError, match="fps"):
            Export.Params(fps=bad)


def test_threejs_plays_the_glb_in_headless_chromium(exported, node_modules, chromium):
    """three.js (GLTFLoader + AnimationMixer) in Debian's Chromium: a skinned mesh whose morph influences,
    head rotation and eye rotations follow the animation, and rendered frames that change over time."""
    times = [k / FPS for k in (0, 8, 15, 22, 30, 42)]  # key frames: the jaw is open at 22 only
    report = probe_in_threejs(exported.arrays["animation"].tobytes(), node_modules, chromium, times)
    assert report["errors"] == []
    assert report["bones"] == ["Root", "Head", "LeftEye", "RightEye"] and report["webgl"]
    index = report["morphs"]["jawOpen"]
    head, gaze = make_head(), make_gaze()
    from stages.export.rig import gaze_rotations

    for frame in report["frames"]:
        k = int(round(frame["t"] * FPS))
        assert frame["skinned"]
        expected_jaw = make_blend()["weights"][k, 0]
        assert frame["influences"][index] == pytest.approx(expected_jaw, abs=1e-6)
        q = np.array(frame["head"])[[3, 0, 1, 2]]
        assert abs(q @ head["rotation"][k]) == pytest.approx(1.0, abs=1e-5)
        q = np.array(frame["left"])[[3, 0, 1, 2]]
        assert abs(q @ gaze_rotations(gaze)[k, 0]) == pytest.approx(1.0, abs=1e-5)
    images = [f["image"] for f in report["frames"]]
    assert len(set(images)) == len(images) and min(images) > 0  # something is drawn, and it moves


def av_container(data: bytes):
    import av

    return av.open(io.BytesIO(bytes(data)))


def decode_mp4(data: bytes):
    import av

    with av.open(io.BytesIO(data)) as container:
        vs = container.streams.video[0]
        rate = float(vs.average_rate)
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    with av.open(io.BytesIO(data)) as container:
        a = container.streams.audio[0]
        audio_rate = a.rate
        duration = float(a.duration * a.time_base)
        chunks = [f.to_ndarray().reshape(-1) for f in container.decode(audio=0)]
    return rate, frames, np.concatenate(chunks), audio_rate, duration


def test_the_preview_shows_the_performer_beside_the_character(character):
    """Given the performer's tracking, the preview is twice as wide: each frame's left half is the take's face crop
    of the same moment (crops of known grey levels, one level per tracked frame; a 60 fps preview of a 30 fps take
    shows each crop twice), its right half the character; the other take of the tracking is never shown."""
    frames, crop = 20, 32
    levels = 40 + 8 * np.arange(frames)  # take "face": a level per frame; take "other": white
    crops = np.concatenate([np.full((10, crop, crop), 255), levels[:, None, None] * np.ones((frames, crop, crop))])
    arrays = {"crops": crops.astype(np.uint8), "sequence": np.r_[np.zeros(10, np.int32), np.ones(frames, np.int32)]}
    tracking = artifact(arrays, {"labels": ["other", "face"], "fps": [FPS, FPS]})
    inputs = {"character": character.view(), "blend": make_blend(frames), "performer": tracking}
    out = run_stage(Export, {"video_size": 64, "sequence": "face", "fps": 60}, inputs)
    assert out.meta["video"]["performer"] == "face"
    with av_container(out.arrays["preview"]) as container:
        shown = [f.to_ndarray(format="gray") for f in container.decode(video=0)]
    assert len(shown) == 2 * frames and shown[0].shape == (64, 128)
    left = np.array([f[8:56, 8:56].mean() for f in shown])
    assert np.abs(left - np.repeat(levels, 2)).max() < 3  # codec error only
    assert all(f[:, 64:].std() > 10 for f in shown)  # the character, drawn
    slow = artifact(arrays, {"labels": ["other", "face"], "fps": [25.0, 25.0]})
    with pytest.raises(UserError, match="tracked at 25 fps") as error:
        run_stage(Export, {"video_size": 64, "sequence": "face"}, dict(inputs, performer=slow))
    assert error.value.field == "inputs.performer"


def test_preview_video_frames_rate_and_audio_offset(exported):
    rate, frames, audio, audio_rate, duration = decode_mp4(exported.arrays["preview"].tobytes())
    assert rate == pytest.approx(FPS)
    assert len(frames) == FRAMES and frames[0].shape == (256, 256, 3)
    assert exported.meta["video"]["codec"] in ("libx264", "mpeg4")
    # the beep sits 0.6 s into its audio track, which starts 0.1 s after the first video frame
    envelope = np.convolve(np.abs(audio), np.ones(160) / 160, mode="same")
    loud = np.flatnonzero(envelope > 0.1) / audio_rate
    # (AAC's priming samples are skipped by the MP4 edit list: no extra delay)
    assert loud.min() == pytest.approx(0.7, abs=0.005)
    assert loud.max() == pytest.approx(0.9, abs=0.005)
    assert duration == pytest.approx(FRAMES / FPS, abs=1e-3)
    # the jaw opens between 0.5 s and 1 s: the red mouth interior shows in those frames only
    red = np.array([((f[..., 0].astype(int) - f[..., 1]) > 60).sum() for f in frames])
    t = np.arange(FRAMES) / FPS
    opened, closed = (t > 0.55) & (t < 0.95), (t < 0.45) | (t > 1.05)
    assert red[opened].min() > 5 * max(red[closed].max(), 10)


def test_a_camera_below_the_face_is_taken_out_of_the_head_motion(character):
    """A head that turns left and right, filmed by a camera tilted 15 degrees (and turned 5): its tracked rotation
    is the tilt times the head's own. By default the export takes the mean orientation out (the character faces
    the viewer on average), the head's positions left in the camera's axes (less their mean); "absolute" keeps the
    camera's view."""
    from stages.geometry.rotations import quat_multiply

    frames = 60
    phase = 2 * np.pi * np.arange(frames) / frames
    own = euler_to_quat(0.3 * np.sin(phase), np.zeros(frames), np.zeros(frames))  # its mean is level
    tilt = euler_to_quat(np.radians(5.0), np.radians(15.0), 0.0)
    seen = quat_multiply(tilt, own)
    position = np.c_[2.0 * np.sin(phase), np.zeros(frames), np.full(frames, 50.0)]  # cm, level axes
    seen_position = position @ quat_to_matrix(tilt).T
    head = artifact({"rotation": seen, "translation": seen_position}, {"fps": FPS, "translation_units": "cm"})
    inputs = {"character": character.view(), "blend": make_blend(frames), "head": head}

    out = run_stage(Export, {"preview": False}, inputs)
    assert np.allclose(np.abs((out.arrays["head_rotation"] * own).sum(axis=1)), 1.0, atol=1e-9)
    angles = csv_by_name(out.arrays["live_link"])
    assert np.allclose(angles["HeadYaw"], 0.3 * np.sin(phase), atol=1e-5)
    assert np.allclose(angles["HeadPitch"], 0.0, atol=1e-5) and np.allclose(angles["HeadRoll"], 0.0, atol=1e-5)
    moved = (seen_position - seen_position.mean(axis=0)) * 0.01
    assert np.allclose(out.arrays["head_translation"], moved, atol=1e-9)
    taken_out = out.meta["head"]["orientation_taken_out_deg"]
    assert taken_out["yaw"] == pytest.approx(5.0, abs=1e-3) and taken_out["pitch"] == pytest.approx(15.0, abs=1e-3)
    assert out.metrics["head_levelled_deg"] == pytest.approx(np.degrees(2 * np.arccos(tilt[0])), abs=1e-6)

    out = run_stage(Export, {"preview": False, "head_rotation": "absolute"}, inputs)
    assert np.allclose(np.abs((out.arrays["head_rotation"] * seen).sum(axis=1)), 1.0, atol=1e-9)
    assert "orientation_taken_out_deg" not in out.meta["head"] and "head_levelled_deg" not in out.metrics


def test_a_variable_frame_rate_take_is_exported_by_its_frame_times(character):
    """A phone's take at 30 fps that dropped frames (its tracking's frame times), whose jaw opens and head turns in
    proportion to time: exported at 30 fps by those times, every output frame's jaw and yaw are those of its
    time (exactly: linear in time, interpolated linearly). Read as rows at the average rate, the jaw ran up to two
    frames (67 ms) off its time around the dropped ones, a lip-sync error one sees."""
    kept = np.setdiff1d(np.arange(60), [10, 11, 12, 30, 31, 45])
    times = kept / 30.0 + 0.0004 * np.sin(kept)  # millisecond jitter, as containers store them
    average = len(kept) / ((kept[-1] + 1) / 30.0)
    w = np.zeros((len(kept), len(DRIVEN)))
    w[:, 0] = times / 2.0  # jawOpen
    blend = artifact({"weights": w}, {"target_names": DRIVEN, "fps": average})
    zeros = np.zeros(len(kept))
    tracking = artifact(
        {
            "rotation": euler_to_quat(0.3 * times, zeros, zeros),
            "translation": np.zeros((len(kept), 3)),
            "time": times,
            "sequence": np.zeros(len(kept), np.int32),
        },
        {"labels": ["take"], "fps": [average], "translation_units": "cm"},
    )
    inputs = {"character": character.view(), "blend": blend, "head": tracking}
    out = run_stage(Export, {"preview": False, "head_rotation": "absolute"}, inputs)
    assert out.meta["fps"] == 30.0 and out.meta["variable_frame_rate"] and out.meta["head"]["frame_times"]
    t = np.arange(60) / 30.0
    assert len(out.arrays["weights"]) == 60
    jaw = out.arrays["weights"][:, out.meta["target_names"].index("jawOpen")]
    inside = t <= times[-1]
    np.testing.assert_allclose(jaw[inside], t[inside] / 2.0, atol=1e-6)
    np.testing.assert_allclose(quat_to_euler(out.arrays["head_rotation"])[inside, 0], 0.3 * t[inside], atol=1e-6)
    rows = run_stage(Export, {"preview": False}, dict(inputs, head=None))  # no frame times: rows at the average rate
    assert not rows.meta["variable_frame_rate"] and rows.meta["fps"] == pytest.approx(average)
    read_as_rows = rows.arrays["weights"][:, rows.meta["target_names"].index("jawOpen")]
    early = read_as_rows - np.arange(len(read_as_rows)) / average / 2.0  # against its output frame's time
    assert np.abs(early).max() > 0.025  # 50 ms or more off its time (the ramp rises 0.5 a second)


def test_bvh_carries_the_head_rotation(exported):
    from stages.formats.bvh import joint_rotation, parse_bvh

    bvh = parse_bvh(exported.arrays["head_bvh"].tobytes().decode())
    assert bvh.frames == FRAMES and bvh.fps == pytest.approx(FPS)
    q = joint_rotation(bvh, "Head")
    assert np.allclose(np.abs((q * make_head()["rotation"]).sum(axis=1)), 1.0, atol=1e-6)


def test_export_without_head_or_audio(character, node_modules):
    out = run_stage(Export, {"preview": False}, {"character": character.view(), "blend": make_blend(12)})
    assert "head_bvh" not in out.arrays and "preview" not in out.arrays
    report = validate_glb(out.arrays["animation"].tobytes(), node_modules=node_modules)
    assert report["numErrors"] == 0 and report["numWarnings"] == 0, report["messages"]
    rows = list(csv.reader(io.StringIO(out.arrays["live_link"].tobytes().decode())))
    assert all(float(x) == 0.0 for r in rows[1:] for x in r[54:])


def test_a_take_whose_frame_times_do_not_increase_is_refused_naming_the_input(character):
    """A tracking whose frames all sit at 0 s (a video re-encoded without timestamps, tracked before such files were
    re-timed) gives no frame rate: a UserError naming the input, not a ZeroDivisionError in the timeline."""
    frames = 8
    blend = artifact({"weights": np.zeros((frames, len(DRIVEN)))}, {"target_names": DRIVEN, "fps": 25.0})
    tracking = artifact(
        {
            "rotation": np.tile([1.0, 0.0, 0.0, 0.0], (frames, 1)),
            "translation": np.zeros((frames, 3)),
            "time": np.zeros(frames),
            "sequence": np.zeros(frames, np.int32),
        },
        {"labels": ["take"], "fps": [25.0], "translation_units": "cm"},
    )
    inputs = {"character": character.view(), "blend": blend, "head": tracking}
    with pytest.raises(UserError, match="frame times do not increase") as caught:
        run_stage(Export, {"preview": False}, inputs)
    assert caught.value.field == "inputs.head"
    with pytest.raises(UserError, match="frame times do not increase"):
        nominal_rate(np.zeros(frames), "inputs.audio")


def test_export_errors(character):
    view = character.view()
    with pytest.raises(UserError, match="frame-rate mismatch"):
        run_stage(Export, {"preview": False}, {"character": view, "blend": make_blend(), "head": make_head(fps=25.0)})
    out = run_stage(
        Export,
        {"preview": False, "resample_head": True},
        {"character": view, "blend": make_blend(), "head": make_head(frames=38, fps=25.0)},
    )
    assert out.meta["head"]["resampled"]
    with pytest.raises(UserError, match="lasts"):
        run_stage(Export, {"preview": False}, {"character": view, "blend": make_blend(), "head": make_head(frames=20)})
    bad = artifact({"weights": np.zeros((5, 1), np.float32)}, {"target_names": ["tailWag"], "fps": FPS})
    with pytest.raises(UserError, match="tailWag"):
        run_stage(Export, {"preview": False}, {"character": view, "blend": bad})
    no_fps = artifact({"weights": np.zeros((5, 1), np.float32)}, {"target_names": ["jawOpen"]})
    with pytest.raises(UserError, match="fps"):
        run_stage(Export, {"preview": False}, {"character": view, "blend": no_fps})
    with pytest.raises(UserError, match="no take labelled 'sad'"):
        run_stage(
            Export,
            {"sequence": "sad", "video_size": 64},
            {"character": view, "blend": make_blend(6), "audio": make_audio(0.0)},
        )
    with pytest.raises(UserError, match="several takes"):
        run_stage(Export, {"video_size": 64}, {"character": view, "blend": make_blend(6), "audio": make_audio(0.0)})
    with pytest.raises(UserError, match="translation_scale"):
        run_stage(Export, {"preview": False}, {"character": view, "blend": make_blend(), "head": make_head(units="px")})
    out = run_stage(
        Export,
        {"preview": False, "head_translation": "none"},
        {"character": view, "blend": make_blend(), "head": make_head(units="px")},
    )
    assert np.all(out.arrays["head_translation"] == 0)
    out = run_stage(
        Export, {"preview": False}, {"character": view, "blend": make_blend(), "head": make_head(units="unknown")}
    )
    assert np.all(out.arrays["head_translation"] == 0) and out.metrics["head_translation_exported"] == 0
    assert "unknown" in out.meta["head"]["translation_units"]
    out = run_stage(
        Export,
        {"preview": False, "translation_scale": 0.5, "head_rotation": "absolute"},
        {"character": view, "blend": make_blend(), "head": make_head(units="unknown")},
    )
    tr = make_head()["translation"] * 0.5
    assert np.allclose(out.arrays["head_translation"], tr - tr.mean(axis=0))
    mismatched = make_audio(0.0)
    mismatched.meta["fps"] = [25.0, 25.0]
    with pytest.raises(UserError, match="frame-rate mismatch"):
        run_stage(
            Export,
            {"video_size": 64, "sequence": "beep"},
            {"character": view, "blend": make_blend(6), "audio": mismatched},
        )


def test_head_motion_of_several_takes_is_cut_to_the_chosen_one(character):
    """motion_blend holds every test utterance back to back (sequence + meta labels)."""
    a, b = make_head(FRAMES), make_head(FRAMES + 10)
    other = euler_to_quat(np.full(FRAMES + 10, -0.4), np.zeros(FRAMES + 10), np.zeros(FRAMES + 10))
    both = artifact(
        {
            "rotation": np.r_[other, a["rotation"]],
            "translation": np.r_[b["translation"], a["translation"]],
            "sequence": np.r_[np.zeros(FRAMES + 10, np.int32), np.ones(FRAMES, np.int32)],
        },
        {"fps": FPS, "labels": ["first", "second"], "translation_units": "cm"},
    )
    out = run_stage(
        Export,
        {"preview": False, "sequence": "second", "head_rotation": "absolute"},
        {"character": character.view(), "blend": make_blend(), "head": both},
    )
    assert out.meta["head"]["take"] == "second"
    assert np.allclose(np.abs((out.arrays["head_rotation"] * a["rotation"]).sum(axis=1)), 1.0)
    with pytest.raises(UserError, match="no take labelled 'third'"):
        run_stage(
            Export,
            {"preview": False, "sequence": "third"},
            {"character": character.view(), "blend": make_blend(), "head": both},
        )


def test_the_blends_take_picks_the_audio_and_head_takes(character):
    """A blend over two test takes (sequence + labels): params.sequence picks its frames, and the take's name
    picks the matching audio and head motion; a single-take blend's label does the same without the param."""
    w = make_blend()["weights"]
    two = artifact(
        {"weights": np.r_[w[:20] * 0, w], "sequence": np.r_[np.zeros(20, np.int32), np.ones(FRAMES, np.int32)]},
        {"target_names": DRIVEN, "fps": FPS, "labels": ["happy", "beep"]},
    )
    out = run_stage(
        Export,
        {"sequence": "beep", "video_size": 64},
        {"character": character.view(), "blend": two, "audio": make_audio(0.1)},
    )
    assert out.meta["take"] == "beep" and out.meta["audio"]["audio_label"] == "beep"
    assert len(out.arrays["weights"]) == FRAMES
    one = artifact({"weights": w}, {"target_names": DRIVEN, "fps": FPS, "labels": ["beep"]})
    out = run_stage(Export, {"video_size": 64}, {"character": character.view(), "blend": one, "audio": make_audio(0.1)})
    assert out.meta["audio"]["audio_label"] == "beep"


def test_weights_outside_unit_range_are_clipped_and_counted(character):
    w = np.array([[1.5], [0.5], [-0.2], [0.2]], np.float32)
    blend = artifact({"weights": w}, {"target_names": ["jawOpen"], "fps": FPS})
    out = run_stage(Export, {"preview": False}, {"character": character.view(), "blend": blend})
    jaw = out.arrays["weights"][:, character.meta["target_names"].index("jawOpen")]
    assert np.allclose(jaw, [1.0, 0.5, 0.0, 0.2])
    assert out.metrics["clipped_fraction"] == pytest.approx(0.5)


def test_real_take_audio_is_muxed(character):
    """The CREMA-D take's own audio (decoded from the FLV) rides along in the preview."""
    real = decode_audio(CLIP)
    frames = int(real.duration * FPS)
    out = run_stage(
        Export,
        {"sequence": "happy", "video_size": 256},
        {"character": character.view(), "blend": make_blend(frames), "audio": make_audio(0.0)},
    )
    _, video, audio, audio_rate, _ = decode_mp4(out.arrays["preview"].tobytes())
    assert len(video) == frames
    n = min(len(audio), len(real.samples)) - 4096
    shift = int(round(real.offset_to_video * audio_rate))
    ref = real.samples[max(0, -shift) :][:n] if shift <= 0 else np.r_[np.zeros(shift), real.samples][:n]
    lags = list(range(-64, 65, 4))
    scores = [np.dot(audio[64 + d : 64 + d + n - 2048], ref[64 : 64 + n - 2048]) for d in lags]
    assert abs(lags[int(np.argmax(scores))]) <= 4  # in sync
    corr = np.corrcoef(audio[64 : 64 + n - 2048], ref[64 : 64 + n - 2048])[0, 1]
    assert corr > 0.9


def run_with_warnings(params, inputs):
    """The stage's Result with its warnings (msflow.testing.run_stage keeps arrays, meta and metrics only)."""
    return Export("export").run(Export.Params(**params), prepare_inputs(Export, inputs))


def test_a_character_without_the_needed_morphs_is_warned_about():
    """Missing ARKit columns and moving morphs without an ARKit column are named in stage warnings."""
    rng = np.random.default_rng(2)
    neutral = rng.normal(size=(30, 3)).astype(np.float32)
    names = ["jawOpen", "wiggle", "PupilDilate_L", "smile_left"]
    deltas = rng.normal(size=(4, 30, 3)).astype(np.float32)
    toy = artifact(
        {
            "neutral": neutral,
            "triangles": np.arange(30).reshape(10, 3),
            "deltas": deltas,
            "landmark_ids": np.arange(68) % 30,
        },
        {"target_names": names},
    )
    blend = artifact({"weights": np.full((4, 4), 0.5, np.float32)}, {"target_names": names, "fps": FPS})
    result = run_with_warnings({"preview": False}, {"character": toy, "blend": blend})
    missing, dropped = result.warnings
    assert "EyeBlinkLeft" in missing and "JawOpen" not in missing and "TongueOut" not in missing
    assert "['wiggle', 'PupilDilate_L', 'smile_left']" in dropped
    assert result.meta["live_link"]["dropped_morphs"] == ["wiggle", "PupilDilate_L", "smile_left"]
    # an alias gives smile_left its column: no longer dropped, and the column is filled
    result = run_with_warnings(
        {"preview": False, "arkit_aliases": {"smile_left": {"MouthSmileLeft": 1.0}}}, {"character": toy, "blend": blend}
    )
    assert "smile_left" not in result.warnings[1] and "MouthSmileLeft" not in result.warnings[0]
    col = ARKIT_NAMES.index("MouthSmileLeft")
    assert np.allclose(result.arrays["arkit"][:, col], 0.5)
    # a bad alias is refused by Params, before anything runs
    with pytest.raises(ValueError, match="not one of the 52 ARKit columns"):
        Export.Params(arkit_aliases={"smile_left": {"Smile": 1.0}})


def test_a_long_list_of_missing_columns_is_cut_short_and_kept_whole_in_meta():
    """A character with hardly any ARKit morph misses most of the 52 columns: the warning names a few and says
    where all of them are; meta keeps the full list."""
    rng = np.random.default_rng(3)
    names = ["jawOpen", "wiggle"]
    toy = artifact(
        {
            "neutral": rng.normal(size=(30, 3)).astype(np.float32),
            "triangles": np.arange(30).reshape(10, 3),
            "deltas": rng.normal(size=(2, 30, 3)).astype(np.float32),
            "landmark_ids": np.arange(68) % 30,
        },
        {"target_names": names},
    )
    blend = artifact({"weights": np.zeros((4, 2), np.float32)}, {"target_names": names, "fps": FPS})
    result = run_with_warnings({"preview": False}, {"character": toy, "blend": blend})
    (missing,) = result.warnings
    empty = result.meta["live_link"]["empty_columns"]
    warned = [c for c in empty if c != "TongueOut"]  # untracked: never warned about
    assert len(warned) > 40 and "JawOpen" not in empty
    assert f"{warned[:8]} and {len(warned) - 8} more (msflow show STAGE: meta live_link.empty_columns" in missing
    assert warned[8] not in missing and len(missing) < 400


def test_the_ict_export_warns_about_nothing(exported):
    """ICT FaceKit: every ARKit column but TongueOut has a source, and no moving morph is dropped."""
    assert exported.meta["live_link"]["empty_columns"] == ["TongueOut"]
    assert exported.meta["live_link"]["dropped_morphs"] == []


def test_a_silent_take_gives_a_silent_preview_with_a_warning(character):
    """Tracking contract: a take without audio has meta has_audio[label] false (or no audio output at all)."""
    silent = make_audio(0.0)
    silent.meta["has_audio"] = {"happy": True, "beep": False}
    no_audio = artifact({"landmarks": np.zeros((3, 68, 2))}, {"labels": ["beep"], "fps": [FPS]})
    for audio in (silent, no_audio):
        inputs = {"character": character.view(), "blend": make_blend(6), "audio": audio}
        result = run_with_warnings({"sequence": "beep", "video_size": 32}, inputs)
        assert result.warnings == ["the take 'beep' has no audio: the preview is silent"]
        assert result.meta["video"]["audio"] is False
        with av.open(io.BytesIO(result.arrays["preview"])) as container:
            assert not container.streams.audio and container.streams.video[0].frames == 6


def test_h264_encoding_is_deterministic(character):
    """The same frames give the same MP4 bytes, encode after encode (x264's macroblock tree made them differ)."""
    from stages.export.preview import encode_mp4
    from stages.geometry.render import CharacterRenderer

    renderer = CharacterRenderer.from_artifact(character.view(), size=96)
    names = character.meta["target_names"]
    base = [renderer(np.eye(len(names))[names.index(n)] * 0.8) for n in DRIVEN]
    frames = [np.roll(base[i % len(base)], i // 3, axis=1) for i in range(240)]
    rng = np.random.default_rng(0)
    outputs = set()
    for _ in range(8):
        churn = [rng.bytes(int(n)) for n in rng.integers(100, 300_000, 20)]  # move the heap around
        outputs.add(encode_mp4(iter(frames), 30.0, (96, 96))[0])
        del churn
    assert len(outputs) == 1


def test_the_face_framing_holds_the_face_in_every_posed_frame(character):
    """A nod of 30 degrees and a lean of 3 cm with the jaw open: the face framing built from the posed landmarks of
    every frame shows all of them; the neutral face's box, the framing before, loses the chin."""
    from stages.geometry.render import CharacterRenderer, posed_points, project

    view = character.view()
    names = view.meta["target_names"]
    frames = 4
    weights = np.zeros((frames, len(names)))
    weights[:, names.index("jawOpen")] = [0.0, 0.5, 1.0, 1.0]
    rotation = euler_to_quat(np.zeros(frames), np.radians([0.0, 10.0, 20.0, 30.0]), np.zeros(frames))
    translation = np.c_[np.zeros(frames), [0.0, -0.01, -0.02, -0.03], np.zeros(frames)]
    pivot = np.asarray(view.meta["pivot"], np.float64)
    face = posed_points(view["neutral"], view["deltas"], view["landmark_ids"], weights, rotation, translation, pivot)

    def shown(renderer) -> bool:
        _, xy = project(face.reshape(-1, 3), renderer.view, 128)
        return bool(((xy >= 0) & (xy <= 128)).all())

    renderer = CharacterRenderer.from_artifact(view, size=128, framing="face", face_points=face)
    ids = np.asarray(view["landmark_ids"])
    for k in range(frames):  # the points are where the renderer poses those vertices
        posed = renderer.vertices(weights[k], rotation[k], translation[k])[ids]
        np.testing.assert_allclose(posed, face[k], atol=1e-5)
    assert shown(renderer)
    assert not shown(CharacterRenderer.from_artifact(view, size=128, framing="face"))


def test_preview_frames_come_in_order_whatever_the_jobs():
    """Blocks rendered by a thread pool reach the encoder in frame order (a renderer that draws its frame index)."""
    from stages.export.preview import Poses, rendered_frames

    class IndexRenderer:
        def __call__(self, weights, **_):
            return np.full((2, 2, 3), int(weights[0]), np.uint8)

    poses = Poses(np.arange(37, dtype=float)[:, None])
    for jobs in (1, 2, 3):
        for block in (1, 4, 16, 64):
            frames = list(rendered_frames(IndexRenderer(), poses, jobs=jobs, block=block))
            assert [int(f[0, 0, 0]) for f in frames] == list(range(37)), (jobs, block)


def test_preview_is_the_same_whatever_the_jobs(character):
    """Contract 6: results do not depend on the run's worker count (threads render blocks of 16 frames)."""
    inputs = {"character": character.view(), "blend": make_blend(40, gaze=True), "head": make_head(40)}
    params = Export.Params(video_size=96, preview="full")
    serial, parallel = (Export("export", jobs=jobs).run(params, prepare_inputs(Export, inputs)) for jobs in (1, 3))
    assert serial.arrays["preview"] == parallel.arrays["preview"]
    low = Export("export", jobs=2).run(Export.Params(video_size=96, preview="low"), prepare_inputs(Export, inputs))
    assert low.meta["video"]["size"] == 48 and low.meta["video"]["level"] == "low"
    assert Export.Params(preview=True).preview == "full" and Export.Params(preview=False).preview is False
    with pytest.raises(ValueError):
        Export.Params(preview="medium")


def test_preview_frames_drawn_by_worker_processes_equal_the_serial_ones(character):
    """Long takes render in spawned worker processes: the same pixels, in order, as one thread draws them."""
    from stages.export.preview import Poses, rendered_frames
    from stages.geometry.render import CharacterRenderer
    from stages.geometry.rotations import euler_to_quat

    renderer = CharacterRenderer.from_artifact(character.view(), size=32)
    t = np.arange(24) / 30.0
    names = character.view().meta["target_names"]
    weights = np.zeros((24, len(names)), np.float32)
    weights[:, 0] = np.linspace(0, 1, 24)
    poses = Poses(weights, euler_to_quat(0.3 * np.sin(4 * t), 0.1 * t, 0 * t))
    serial = list(rendered_frames(renderer, poses, jobs=1))
    pooled = list(rendered_frames(renderer, poses, jobs=2, block=5, processes=True))
    assert len(pooled) == 24 and all(np.array_equal(a, b) for a, b in zip(serial, pooled))
    assert not all(np.array_equal(serial[0], f) for f in serial[1:])  # the frames differ: order is checked


#: a process with a preview render pool that prints its worker's pid and waits (until killed)
RENDER_POOL_OWNER = """
import os, sys
from stages.export.preview import _render_pool
with _render_pool(None, 1, processes=True) as (pool, _):
    print(pool.submit(os.getpid).result(), flush=True)
    sys.stdin.read()
"""


def test_preview_render_workers_exit_when_their_parent_is_killed():
    """A render worker whose parent died without shutting the pool down (SIGKILL: the stage's worker, or msflow
    itself with -j 1) exits, instead of waiting for blocks forever holding the run's pipes."""
    import subprocess
    import sys
    import time

    from conftest import cli_env, process_running

    owner = subprocess.Popen(
        [sys.executable, "-c", RENDER_POOL_OWNER], env=cli_env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE
    )
    worker = None
    try:
        worker = int(owner.stdout.readline())
        owner.kill()
        owner.wait()
        deadline = time.monotonic() + 10  # a guard against hanging, not a speed assertion
        while process_running(worker) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not process_running(worker)
    finally:
        owner.kill()
        owner.wait()
        if worker is not None and process_running(worker):
            os.kill(worker, signal.SIGKILL)
        owner.stdin.close()
        owner.stdout.close()


def test_a_bad_frame_rate_is_refused_before_anything_runs(default_run):
    """Params hold the rule: `msflow status` names stage and field, exit 2, and runs nothing."""
    proj, _ = default_run
    for value in ("0", "-25", "241"):
        out = run_cli(proj, "status", "-S", f"export.fps={value}")
        assert out.returncode == 2, out.stderr
        assert "export" in out.stderr and "fps" in out.stderr and "Traceback" not in out.stderr


def test_figures(exported):
    from stages.export.animation import plot_curves, preview_video

    view = artifact(exported.arrays, exported.meta, exported.metrics)
    fig = plot_curves(view)
    assert len(fig.axes) == 2 and len(fig.axes[0].lines) == 10
    assert preview_video(view)[4:8] == b"ftyp"


def test_exports_are_byte_identical_from_run_to_run(character):
    """Same inputs, same bytes (GLB, CSV, MP4, BVH): content-addressed caching and diffing rely on it."""
    inputs = {
        "character": character.view(),
        "blend": make_blend(12),
        "head": make_head(12),
        "audio": make_audio(offset=0.1),
    }
    first, second = (run_stage(Export, {"sequence": "beep", "video_size": 128}, inputs) for _ in range(2))
    for name in ("animation", "live_link", "preview", "head_bvh"):
        assert np.array_equal(first.arrays[name], second.arrays[name]), name
