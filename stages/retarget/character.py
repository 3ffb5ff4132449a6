"""The 3D character the animation is retargeted onto (paper Sec 4.3: "commercial models that have built-in morph
targets"): a neutral mesh, its morph targets (blendshapes) and the 68 landmark vertices that correspond to the
tracked iBUG points.

Implementations:
- ``GltfCharacter``: a .glb/.gltf whose mesh has morph targets, names in ``mesh.extras.targetNames``;
- ``ObjBlendshapes``: a neutral OBJ plus one OBJ per blendshape (``.obj`` or ``.obj.gz``), names from the file
  names, quads and n-gons fan-triangulated (the layout of ICT FaceKit).
Both can mix an identity: neutral + sum_i c_i (identity_i - neutral), the expression deltas transfer unchanged.

The embedded default character, data/characters/ict-facekit.glb, is built from the ICT FaceKit OBJs by
``stages.retarget.ict_facekit``; the OBJ folder reader is ``stages.retarget.obj_blendshapes``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.data import DATA
from stages.formats.gltf import MorphMesh, read_morph_mesh
from stages.retarget.obj_blendshapes import load_obj_blendshapes
from stages.tracking.stages import DETECTOR_MODEL, LANDMARK_MODEL

#: the embedded default character (built by ``python -m stages.retarget.ict_facekit build``)
DEFAULT_CHARACTER = DATA / "characters" / "ict-facekit.glb"
N_LANDMARKS = 68
LANDMARK_SCHEME = "ibug68"
#: mesh.extras keys of the glTF characters this project writes (and reads from any glTF that has them)
EXTRAS_LANDMARKS = "landmarkVertexIds"
EXTRAS_IDENTITY = "identityTargetNames"
EXTRAS_PIVOT = "headPivot"
#: the tracker's models, which place the landmarks of a character that has none (in the cache key)
TRACKER_RESOURCES = {"detector": DETECTOR_MODEL, "face_mesh": LANDMARK_MODEL}

CHARACTER_OUTPUTS = {
    "neutral": Output.array(
        "f",
        shape=("vertices", 3),
        dtype="float32",
        doc="neutral vertex positions (identity mix applied), metres for glTF characters",
    ),
    "triangles": Output.array("i", shape=("triangles", 3), dtype="int32", doc="vertex ids, counter-clockwise"),
    "deltas": Output.array(
        "f",
        shape=("targets", "vertices", 3),
        dtype="float32",
        doc="morph target offsets from the neutral, in meta['target_names'] order",
    ),
    "landmark_ids": Output.array(
        "i", shape=(N_LANDMARKS,), dtype="int32", doc="vertex id of each of the 68 iBUG landmarks"
    ),
    "triangle_groups": Output.array(
        "i", shape=("triangles",), dtype="int32", doc="material group of each triangle, index into meta['groups']"
    ),
}


# ------------------------------------------------------------------------------------------------ the maths


def mix_identity(neutral: np.ndarray, identity_deltas: np.ndarray, coefficients: np.ndarray) -> np.ndarray:
    """neutral + sum_i c_i (identity_i - neutral); identity_deltas are (I, V, 3) = identity_i - neutral.

    Expression deltas are left as they are: the blendshapes of an identity-parametric model (ICT FaceKit) are
    defined as offsets that transfer onto any identity.
    """
    c = np.asarray(coefficients, dtype=np.float64)
    if c.size == 0:
        return np.asarray(neutral, dtype=np.float32)
    return (neutral + np.tensordot(c, identity_deltas, axes=1)).astype(np.float32)


def check_landmark_ids(ids: Any, n_vertices: int, *, file: str | None = None, field: str | None = None) -> np.ndarray:
    """68 vertex ids as int32; a wrong count or an id outside [0, n_vertices) is the user's error."""
    try:
        arr = np.asarray(ids, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise UserError("landmark ids must be a list of 68 integers", file=file, field=field) from None
    if arr.size != N_LANDMARKS:
        raise UserError(
            f"expected {N_LANDMARKS} landmark vertex ids (iBUG 68-point order), got {arr.size}", file=file, field=field
        )
    if not np.all(arr == np.round(arr)):
        raise UserError("landmark ids must be integers", file=file, field=field)
    bad = np.flatnonzero((arr < 0) | (arr >= n_vertices))
    if bad.size:
        raise UserError(
            f"landmark ids out of range for a mesh of {n_vertices} vertices: "
            + ", ".join(f"#{i}={int(arr[i])}" for i in bad[:8]),
            file=file,
            field=field,
        )
    return arr.astype(np.int32)


def read_landmark_json(path: Path, n_vertices: int, field: str) -> np.ndarray:
    """Landmark ids from JSON: a list of 68 ints, or an object with ``idx_to_landmark_verts`` (ICT FaceKit's
    vertex_indices.json) or ``landmark_ids``."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise UserError(f"cannot read landmark JSON ({exc})", file=str(path), field=field) from None
    if isinstance(data, dict):
        for key in ("idx_to_landmark_verts", "landmark_ids", EXTRAS_LANDMARKS):
            if key in data:
                data = data[key]
                break
        else:
            raise UserError(
                "landmark JSON object needs a key 'idx_to_landmark_verts' or 'landmark_ids'",
                file=str(path),
                field=field,
            )
    return check_landmark_ids(data, n_vertices, file=str(path), field=field)


def head_pivot(neutral: np.ndarray, landmark_ids: np.ndarray) -> np.ndarray:
    """An approximate head-neck joint to turn the head about: on the mid-plane, below and behind the ears.

    The atlanto-occipital joint sits about a third of the ear-to-chin height below the ear landmarks (iBUG 0/16)
    and slightly behind them; a heuristic, overridable by ``headPivot`` in a glTF's mesh extras.
    """
    p = np.asarray(neutral, dtype=np.float64)[landmark_ids]
    ears = 0.5 * (p[0] + p[16])
    down = ears[1] - p[8][1]
    back = p[30][2] - ears[2]  # nose tip ahead of the ears
    return np.array([0.5 * (p[0][0] + p[16][0]), ears[1] - 0.3 * down, ears[2] - 0.1 * back])


def drop_triangles(
    mesh: MorphMesh, keep: np.ndarray, landmark_ids: np.ndarray, identity_deltas: np.ndarray | None = None
):
    """Keep the triangles where ``keep`` is True and the vertices they use; renumber vertices, landmark ids and
    drop material groups left empty. A landmark on a removed vertex is an error."""
    used = np.zeros(len(mesh.positions), dtype=bool)
    used[mesh.triangles[keep].reshape(-1)] = True
    if not used[landmark_ids].all():
        raise UserError("removing those triangles would remove landmark vertices", field="params.drop_groups")
    new_index = np.cumsum(used) - 1
    groups_kept = np.unique(mesh.triangle_groups[keep])
    group_map = np.full(len(mesh.groups), -1)
    group_map[groups_kept] = np.arange(len(groups_kept))
    reduced = MorphMesh(
        positions=mesh.positions[used],
        triangles=new_index[mesh.triangles[keep]].astype(np.int32),
        target_names=list(mesh.target_names),
        deltas=mesh.deltas[:, used],
        triangle_groups=group_map[mesh.triangle_groups[keep]].astype(np.int32),
        groups=[mesh.groups[i] for i in groups_kept],
        extras=dict(mesh.extras),
        name=mesh.name,
    )
    ids = new_index[landmark_ids].astype(np.int32)
    return reduced, ids, (identity_deltas[:, used] if identity_deltas is not None else None)


def drop_triangle_groups(
    mesh: MorphMesh, landmark_ids: np.ndarray, drop: list[str], identity_deltas: np.ndarray | None = None
):
    """Remove the triangles of the named material groups and every vertex no remaining triangle uses."""
    names = [g.name for g in mesh.groups]
    unknown = [d for d in drop if d not in names]
    if unknown:
        raise UserError(f"unknown material groups {unknown}; the mesh has {names}", field="params.drop_groups")
    keep = ~np.isin(mesh.triangle_groups, [names.index(d) for d in drop])
    return drop_triangles(mesh, keep, landmark_ids, identity_deltas)


# ------------------------------------------------------------------------------------------------ identity and the result


def split_identity_targets(mesh: MorphMesh, identity_names: list[str]) -> tuple[MorphMesh, dict[str, np.ndarray]]:
    """Separate identity morph targets (shape parameters, not animated) from the expression targets."""
    keep = [i for i, n in enumerate(mesh.target_names) if n not in identity_names]
    identities = {n: mesh.deltas[mesh.target_names.index(n)] for n in identity_names if n in mesh.target_names}
    expr = MorphMesh(
        positions=mesh.positions,
        triangles=mesh.triangles,
        target_names=[mesh.target_names[i] for i in keep],
        deltas=mesh.deltas[keep],
        triangle_groups=mesh.triangle_groups,
        groups=mesh.groups,
        extras=mesh.extras,
        name=mesh.name,
    )
    return expr, identities


def apply_identity(mesh: MorphMesh, identities: dict[str, np.ndarray], weights: dict[str, float]) -> MorphMesh:
    unknown = sorted(set(weights) - set(identities))
    if unknown:
        raise UserError(
            f"unknown identity targets {unknown}; available: {sorted(identities) or 'none'}", field="params.identity"
        )
    if weights:
        names = sorted(weights)
        mesh.positions = mix_identity(
            mesh.positions, np.stack([identities[n] for n in names]), np.array([weights[n] for n in names])
        )
    return mesh


def performer_identity(mesh: MorphMesh, identities: dict, landmark_ids, tracks, ridge: float) -> dict[str, float]:
    """Identity coefficients (name -> value) fitted to the rest face of the performer in ``tracks``
    (``stages.retarget.identity``); several speakers in the tracking get one identity for all, with a warning."""
    import warnings

    from stages.retarget.identity import fit_identity, performer_rest_face

    if tracks is None or "mesh" not in tracks:
        raise UserError(
            "fit_identity needs the performer's FaceMesh tracking: wire it as input tracks (e.g. tracks: track)",
            field="inputs.tracks",
        )
    if not identities:
        raise UserError("fit_identity: the character has no identity targets", field="params.fit_identity")
    speakers = {f.get("speaker") for f in (tracks.meta.get("fields") or {}).values() if f.get("speaker")}
    if len(speakers) > 1:
        warnings.warn(
            f"fit_identity: the tracking holds {len(speakers)} speakers ({sorted(speakers)}); the character gets "
            "one identity fitted to all of them together",
            UserWarning,
        )
    names = sorted(identities)
    ids = np.asarray(landmark_ids, np.int64)
    deltas = np.stack([np.asarray(identities[n], np.float64)[ids] for n in names])
    c = fit_identity(performer_rest_face(tracks["mesh"]), np.asarray(mesh.positions, np.float64)[ids], deltas, ridge)
    return {n: float(v) for n, v in zip(names, c)}


def character_result(
    mesh: MorphMesh,
    landmark_ids: np.ndarray,
    source: dict,
    identity: dict[str, float],
    pivot: np.ndarray | None = None,
    units: str = "m",
) -> Result:
    if not len(mesh.target_names):
        raise UserError("the character has no morph targets", field="inputs")
    if len(set(mesh.target_names)) != len(mesh.target_names):
        dupes = sorted({n for n in mesh.target_names if mesh.target_names.count(n) > 1})
        raise UserError(f"duplicate morph target names {dupes}", field="inputs")
    if pivot is None:
        pivot = head_pivot(mesh.positions, landmark_ids)
    lo, hi = mesh.positions.min(axis=0), mesh.positions.max(axis=0)
    meta = {
        "target_names": list(mesh.target_names),
        "groups": [{"name": g.name, "color": [float(c) for c in g.color]} for g in mesh.groups],
        "landmark_scheme": LANDMARK_SCHEME,
        "pivot": [float(v) for v in pivot],
        "units": units,
        "bounds": [[float(v) for v in lo], [float(v) for v in hi]],
        "identity": {k: float(v) for k, v in identity.items()},
        "source": source,
        "axes": "glTF: +y up, the face looks along +z",
    }
    metrics = {
        "vertices": int(len(mesh.positions)),
        "triangles": int(len(mesh.triangles)),
        "targets": int(len(mesh.target_names)),
        "max_delta": float(np.abs(mesh.deltas).max()) if mesh.deltas.size else 0.0,
    }
    return Result(
        {
            "neutral": mesh.positions.astype(np.float32),
            "triangles": mesh.triangles.astype(np.int32),
            "deltas": mesh.deltas.astype(np.float32),
            "landmark_ids": landmark_ids.astype(np.int32),
            "triangle_groups": mesh.triangle_groups.astype(np.int32),
        },
        meta=meta,
        metrics=metrics,
    )


def _single_file(files: dict[str, Path] | None, field: str, suffixes: tuple[str, ...]) -> Path | None:
    if not files:
        return None
    paths = [Path(p) for p in files.values()]
    matching = [p for p in paths if p.name.lower().endswith(suffixes)]
    if len(matching) != 1:
        raise UserError(f"expected one {'/'.join(suffixes)} file, got {[p.name for p in paths]}", field=field)
    return matching[0]


def tracked_landmark_ids(mesh: MorphMesh, path: Path, asked: bool) -> tuple[np.ndarray, dict]:
    """The landmark vertices the tracker finds on the character (stages.retarget.auto_landmarks), its notes as
    warnings; unasked (nothing given), a warning says so and how to check them."""
    import warnings

    from stages.retarget.auto_landmarks import NoFaceFound, track_character_landmarks

    try:
        ids, placed, notes = track_character_landmarks(mesh)
    except NoFaceFound as exc:
        raise UserError(
            f"{exc}, so its 68 landmark vertices cannot be found (the face must look along +z, glTF's front; "
            "a whole figure: choose the head's mesh with params.mesh_name); or give them as a JSON file input "
            "'landmarks'",
            file=str(path),
            field="inputs.landmarks",
        ) from None
    if not asked:
        notes.insert(
            0,
            f"no landmark vertices given (no JSON input 'landmarks', no mesh.extras.{EXTRAS_LANDMARKS}): found by "
            f"tracking the character's front render (presence {placed['presence']:.2f}, every point within "
            f"{placed['largest_offset_iod']:.3f} eye distances of its vertex); the stage's 'landmarks' figure "
            "(msflow report) shows them numbered, and a JSON file input 'landmarks' overrides them",
        )
    for note in notes:
        warnings.warn(note, UserWarning, stacklevel=2)
    return ids, placed


class GltfCharacter(Stage):
    """A glTF 2.0 character (.glb or .gltf) with morph targets; landmark ids from a JSON input, the mesh extras
    (``landmarkVertexIds``), or found by the tracker on the character's front render."""

    cheap = True

    class Params(Stage.Params):
        mesh_name: str | None = None
        #: the 68 landmark vertices: 'given' (the JSON input, else the glTF's mesh extras, else tracked, with a
        #: warning), or 'tracked': found by the tracker on the neutral face rendered from the front, the
        #: tracking's own reading of each point (stages.retarget.auto_landmarks)
        landmarks: Literal["given", "tracked"] = "given"
        #: identity target name -> coefficient, e.g. {identity000: 1.5}; identity targets are listed in the mesh
        #: extras (identityTargetNames) or by ``identity_targets``, and are left out of the animated targets
        identity: dict[str, float] = {}
        identity_targets: list[str] | None = None
        #: fit the identity coefficients to the performer of input ``tracks`` (its FaceMesh rest face) instead:
        #: a digital double; the expression deltas are unchanged (``stages.retarget.identity``, docs/retarget.md)
        fit_identity: bool = False
        #: the fit's ridge, relative to the identity shapes' mean landmark energy (0.1: the lowest absolute mouth
        #: error of 0.01 / 0.1 / 1 on the CREMA-D and talking-head takes, docs/retarget.md)
        identity_ridge: float = Field(0.1, gt=0)

        @model_validator(mode="after")
        def _one_identity(self):
            if self.fit_identity and self.identity:
                raise ValueError("give identity coefficients or fit_identity, not both")
            return self

    inputs = {
        "mesh": Input.files(
            optional=True,
            doc="one .glb/.gltf file; default: the embedded ICT FaceKit character (data/characters/ict-facekit.glb)",
        ),
        "landmarks": Input.files(
            optional=True, doc="JSON with the 68 landmark vertex ids (overrides the ids stored in the glTF)"
        ),
        "tracks": Input.artifact(
            "mesh", optional=True, doc="tracking of one performer (FaceMesh), for fit_identity; ignored otherwise"
        ),
    }
    outputs = CHARACTER_OUTPUTS
    resources = {"character": DEFAULT_CHARACTER, **TRACKER_RESOURCES}

    def run(self, params, inputs):
        path = _single_file(inputs.get("mesh") or {"default": DEFAULT_CHARACTER}, "inputs.mesh", (".glb", ".gltf"))
        mesh = read_morph_mesh(path, params.mesh_name)
        identity_names = params.identity_targets
        if identity_names is None:
            identity_names = list(mesh.extras.get(EXTRAS_IDENTITY, []))
        missing = sorted(set(identity_names) - set(mesh.target_names))
        if missing:
            raise UserError(
                f"identity targets {missing} are not morph targets of the mesh",
                file=str(path),
                field="params.identity_targets",
            )
        mesh, identities = split_identity_targets(mesh, identity_names)
        if not mesh.target_names:
            raise UserError("the character has no expression morph targets (all are identity targets)", file=str(path))
        ids, placed = self._landmark_ids(params, inputs, mesh, path)
        identity = dict(params.identity)
        if params.fit_identity:
            identity = performer_identity(mesh, identities, ids, inputs.get("tracks"), params.identity_ridge)
        mesh = apply_identity(mesh, identities, identity)
        pivot = mesh.extras.get(EXTRAS_PIVOT)
        pivot = np.asarray(pivot, dtype=np.float64) if pivot is not None and not identity else None
        source = {
            "file": path.name,
            "mesh": mesh.name,
            "target_names_from": mesh.extras.get("_target_names_from"),
            "identity_targets": sorted(identities),
            "landmarks": placed,
        }
        return character_result(mesh, ids, source, identity, pivot)

    @staticmethod
    def _landmark_ids(params, inputs, mesh: MorphMesh, path: Path) -> tuple[np.ndarray, dict]:
        """(ids, how they were found)."""
        landmark_file = _single_file(inputs.get("landmarks"), "inputs.landmarks", (".json",))
        if params.landmarks == "given" and landmark_file is not None:
            return read_landmark_json(landmark_file, len(mesh.positions), "inputs.landmarks"), {"from": "json"}
        if params.landmarks == "given" and EXTRAS_LANDMARKS in mesh.extras:
            ids = check_landmark_ids(
                mesh.extras[EXTRAS_LANDMARKS],
                len(mesh.positions),
                file=str(path),
                field=f"mesh.extras.{EXTRAS_LANDMARKS}",
            )
            return ids, {"from": "mesh extras"}
        return tracked_landmark_ids(mesh, path, asked=params.landmarks == "tracked")


class ObjBlendshapes(Stage):
    """A neutral OBJ plus one OBJ per blendshape (.obj or .obj.gz, same vertex order); optional identity OBJs
    (names starting with ``identity_prefix``) for the identity mix."""

    cheap = True

    class Params(Stage.Params):
        #: name (file name without .obj/.obj.gz) of the neutral mesh; default: the one file with 'neutral' in it
        neutral: str | None = None
        identity_prefix: str = "identity"
        identity: dict[str, float] = {}
        #: multiply coordinates into metres (ICT FaceKit is in centimetres: 0.01)
        scale: float = Field(1.0, gt=0)
        #: material groups (OBJ usemtl names) to leave out, e.g. transparent overlay shells
        drop_groups: list[str] = []
        #: the 68 landmark vertices: 'given' (the JSON input; without one, tracked with a warning) or 'tracked'
        #: (found by the tracker on the neutral face's front render: stages.retarget.auto_landmarks)
        landmarks: Literal["given", "tracked"] = "given"

    inputs = {
        "shapes": Input.files(doc="neutral and blendshape OBJs (a glob or a mapping), plus an optional .mtl"),
        "landmarks": Input.files(
            optional=True,
            doc="JSON with the 68 landmark vertex ids (list, or ICT vertex_indices.json); without it they are "
            "found by the tracker (params.landmarks)",
        ),
    }
    outputs = CHARACTER_OUTPUTS
    resources = TRACKER_RESOURCES

    def run(self, params, inputs):
        files = inputs["shapes"]
        mtl = next((Path(p) for p in files.values() if Path(p).name.lower().endswith(".mtl")), None)
        mesh, identities = load_obj_blendshapes(files, params.neutral, params.identity_prefix, mtl)
        landmark_file = _single_file(inputs.get("landmarks"), "inputs.landmarks", (".json",))
        given = params.landmarks == "given" and landmark_file is not None
        ids = read_landmark_json(landmark_file, len(mesh.positions), "inputs.landmarks") if given else np.zeros(0, int)
        identity_deltas = np.stack(list(identities.values())) if identities else None
        if params.drop_groups:
            mesh, ids, identity_deltas = drop_triangle_groups(mesh, ids, list(params.drop_groups), identity_deltas)
            identities = dict(zip(identities, identity_deltas)) if identities else {}
        placed = {"from": "json"}
        if not given:  # on the mesh as it will be (overlay shells dropped: they would cover the eyes)
            folder = Path(next(iter(files.values()))).parent
            ids, placed = tracked_landmark_ids(mesh, folder, asked=params.landmarks == "tracked")
        mesh.positions = (mesh.positions * params.scale).astype(np.float32)
        mesh.deltas = (mesh.deltas * params.scale).astype(np.float32)
        identities = {k: v * params.scale for k, v in identities.items()}
        mesh = apply_identity(mesh, identities, dict(params.identity))
        source = {
            "neutral": mesh.name,
            "files": len(files),
            "identity_targets": sorted(identities),
            "landmarks": placed,
        }
        return character_result(mesh, ids, source, dict(params.identity))


# ------------------------------------------------------------------------------------------------ figures


def figure_landmarks(view, inputs=None, size: int = 512) -> bytes:
    """PNG: the neutral character from the front with its 68 landmark vertices numbered (checks the map)."""
    import cv2

    from stages.geometry.render import CharacterRenderer, project

    renderer = CharacterRenderer.from_artifact(view, size=size, supersample=2)
    image = np.ascontiguousarray(renderer()[..., ::-1])
    points = view["neutral"][view["landmark_ids"]]
    cam, xy = project(points, renderer.view, size)
    for i, (x, y) in enumerate(xy):
        cv2.circle(image, (int(round(x)), int(round(y))), 3, (0, 200, 255), -1, cv2.LINE_AA)
        cv2.putText(
            image,
            str(i),
            (int(round(x)) + 3, int(round(y)) - 3),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.3,
            (255, 255, 255),
            1,
            cv2.LINE_AA,
        )
    return cv2.imencode(".png", image)[1].tobytes()


def figure_targets(view, inputs=None, tile: int = 160, columns: int = 10) -> bytes:
    """PNG: every morph target at weight 1, named, as a contact sheet."""
    import cv2

    from stages.geometry.render import CharacterRenderer

    renderer = CharacterRenderer.from_artifact(view, size=tile)
    names = view.meta["target_names"]
    tiles = []
    for i, name in enumerate(names):
        w = np.zeros(len(names))
        w[i] = 1.0
        image = np.ascontiguousarray(renderer(w)[..., ::-1])
        cv2.putText(image, name, (4, tile - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(image)
    rows = -(-len(tiles) // columns)
    tiles += [np.zeros_like(tiles[0])] * (rows * columns - len(tiles))
    sheet = np.vstack([np.hstack(tiles[r * columns : (r + 1) * columns]) for r in range(rows)])
    return cv2.imencode(".png", sheet)[1].tobytes()


GltfCharacter.figures = {"landmarks": figure_landmarks, "targets": figure_targets}
ObjBlendshapes.figures = {"landmarks": figure_landmarks, "targets": figure_targets}
