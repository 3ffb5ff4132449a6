"""The 3D character the animation is retargeted onto (paper Sec 4.3: "commercial models that have built-in morph
targets"): a neutral mesh, its morph targets (blendshapes) and the 68 landmark vertices that correspond to the
tracked iBUG points.

Implementations:
- ``GltfCharacter``: a .glb/.gltf whose mesh has morph targets, names in ``mesh.extras.targetNames``;
- ``ObjBlendshapes``: a neutral OBJ plus one OBJ per blendshape (``.obj`` or ``.obj.gz``), names from the file
  names, quads and n-gons fan-triangulated (the layout of ICT FaceKit).
Both can mix an identity: neutral + sum_i c_i (identity_i - neutral), the expression deltas transfer unchanged.

The embedded default character, data/characters/ict-facekit.glb, is built from the ICT FaceKit OBJs by this module:
``python -m stages.retarget.character build /path/to/ict-facekit data/characters/ict-facekit.glb``.
"""

from __future__ import annotations

import gzip
import json
import re
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field, model_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.data import DATA
from stages.formats.gltf import MaterialGroup, MorphMesh, read_morph_mesh, write_morph_glb

#: the embedded default character (built by ``python -m stages.retarget.character build``)
DEFAULT_CHARACTER = DATA / "characters" / "ict-facekit.glb"
N_LANDMARKS = 68
LANDMARK_SCHEME = "ibug68"
#: mesh.extras keys of the glTF characters this project writes (and reads from any glTF that has them)
EXTRAS_LANDMARKS = "landmarkVertexIds"
EXTRAS_IDENTITY = "identityTargetNames"
EXTRAS_PIVOT = "headPivot"

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


# ------------------------------------------------------------------------------------------------ OBJ reading


def read_obj_text(path: Path) -> str:
    try:
        if path.name.endswith(".gz"):
            with gzip.open(path, "rt", encoding="utf-8", errors="replace") as fh:
                return fh.read()
        return path.read_text(encoding="utf-8", errors="replace")
    except (OSError, EOFError, gzip.BadGzipFile) as exc:
        raise UserError(f"cannot read OBJ file ({exc})", file=str(path)) from None


def parse_obj_vertices(text: str, path: Path) -> np.ndarray:
    """The ``v`` lines of an OBJ as (V, 3) float64 (a 4th homogeneous or colour component is ignored)."""
    rows = [line.split()[1:4] for line in text.splitlines() if line.startswith("v ")]
    if not rows:
        raise UserError("OBJ file has no vertices ('v' lines)", file=str(path))
    try:
        return np.array(rows, dtype=np.float64)
    except ValueError:
        raise UserError("OBJ file has a malformed 'v' line (expected three numbers)", file=str(path)) from None


def parse_obj_faces(text: str, n_vertices: int, path: Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Faces fan-triangulated: (T, 3) int32 vertex ids, (T,) material group per triangle, group names.

    Polygons keep their winding; negative (relative) indices resolve against the vertices read so far.
    """
    triangles: list[list[int]] = []
    groups: list[int] = []
    names: list[str] = []
    current = -1
    seen_vertices = 0
    for line in text.splitlines():
        if line.startswith("v "):
            seen_vertices += 1
        elif line.startswith("usemtl"):
            parts = line.split(maxsplit=1)
            name = parts[1].strip() if len(parts) > 1 else "default"
            if name not in names:
                names.append(name)
            current = names.index(name)
        elif line.startswith("f "):
            try:
                ids = [int(tok.split("/", 1)[0]) for tok in line.split()[1:]]
            except ValueError:
                raise UserError(f"malformed face line '{line.strip()}'", file=str(path)) from None
            ids = [i - 1 if i > 0 else seen_vertices + i for i in ids]
            for k in range(1, len(ids) - 1):
                triangles.append([ids[0], ids[k], ids[k + 1]])
                groups.append(current)
    if not triangles:
        raise UserError("OBJ file has no faces ('f' lines) with three or more vertices", file=str(path))
    tris = np.array(triangles, dtype=np.int64)
    if tris.min() < 0 or tris.max() >= n_vertices:
        raise UserError(
            f"a face refers to vertex {int(tris.max()) + 1} but the file has {n_vertices} vertices", file=str(path)
        )
    group_ids = np.array(groups, dtype=np.int32)
    if (group_ids < 0).any():  # faces before any usemtl
        names = ["default"] + names
        group_ids = group_ids + 1
    return tris.astype(np.int32), group_ids, names


def read_mtl_colors(path: Path) -> dict[str, tuple[float, float, float, float]]:
    """Diffuse colours (Kd) of an MTL file; ``d``/``Tr`` give alpha when below 1."""
    colors: dict[str, list[float]] = {}
    current = None
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "newmtl" and len(parts) > 1:
            current = parts[1]
            colors[current] = [0.8, 0.8, 0.8, 1.0]
        elif current is not None and parts[0] == "Kd" and len(parts) >= 4:
            colors[current][:3] = [float(v) for v in parts[1:4]]
        elif current is not None and parts[0] == "d" and len(parts) >= 2:
            colors[current][3] = float(parts[1])
        elif current is not None and parts[0] == "Tr" and len(parts) >= 2:
            colors[current][3] = 1.0 - float(parts[1])
    return {k: tuple(float(np.clip(c, 0, 1)) for c in v) for k, v in colors.items()}


def shape_name(path: Path) -> str:
    """Blendshape name from a file name: ``mouthSmile_L.obj.gz`` -> ``mouthSmile_L``."""
    return re.sub(r"\.obj(\.gz)?$", "", path.name, flags=re.IGNORECASE)


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


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere through points: centre and radius."""
    p = np.asarray(points, dtype=np.float64)
    sol = np.linalg.lstsq(np.c_[2 * p, np.ones(len(p))], (p**2).sum(axis=1), rcond=None)[0]
    return sol[:3], float(np.sqrt(sol[3] + sol[:3] @ sol[:3]))


def paint_eyeball(
    mesh: MorphMesh,
    shell: str,
    ball: str,
    *,
    iris_degrees: float = 22.0,
    pupil_degrees: float = 8.0,
    colors: dict[str, tuple] | None = None,
) -> np.ndarray:
    """Give an untextured eyeball its iris and pupil: split the triangles of the inner ``ball`` by their angle
    from the eye axis into sclera / iris / pupil groups (triangles facing the ball's centre, the walls of the
    pupil's tunnel, are pupil too); return the mask of ``shell`` triangles (the outer cornea-and-sclera shell,
    transparent in front, which hides the ball when drawn opaque).

    The axis runs from the ball's centre through the mean of its vertices (the ball is meshed densest around
    the iris, which pulls the mean forward).
    """
    colors = colors or {
        "sclera": (0.72, 0.70, 0.66, 1.0),
        "iris": (0.10, 0.055, 0.03, 1.0),
        "pupil": (0.01, 0.01, 0.01, 1.0),
    }
    names = [g.name for g in mesh.groups]
    ball_id = names.index(ball)
    ball_tri = np.flatnonzero(mesh.triangle_groups == ball_id)
    p = mesh.positions.astype(np.float64)
    vid = np.unique(mesh.triangles[ball_tri])
    centre, _ = fit_sphere(p[vid])
    axis = p[vid].mean(axis=0) - centre
    axis /= np.linalg.norm(axis)
    corners = p[mesh.triangles[ball_tri]]
    d = corners.mean(axis=1) - centre
    angle = np.degrees(np.arccos(np.clip(d @ axis / np.linalg.norm(d, axis=1), -1, 1)))
    # the pupil is a tunnel into the ball, whose inner walls face the centre: the inside of an eye is dark
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    inward = (normal * d).sum(axis=1) < 0
    side = ball.replace("M_Iris", "")
    new_ids = {}
    for part in ("iris", "pupil"):
        new_ids[part] = len(mesh.groups)
        mesh.groups.append(MaterialGroup(f"M_Eye{part.capitalize()}{side}", colors[part]))
    mesh.groups[ball_id] = MaterialGroup(f"M_EyeSclera{side}", colors["sclera"])
    mesh.triangle_groups = mesh.triangle_groups.copy()
    mesh.triangle_groups[ball_tri[angle < iris_degrees]] = new_ids["iris"]
    mesh.triangle_groups[ball_tri[(angle < pupil_degrees) | inward]] = new_ids["pupil"]
    return mesh.triangle_groups == names.index(shell)


# ------------------------------------------------------------------------------------------------ loading


def load_obj_blendshapes(
    files: dict[str, Path],
    neutral: str | None,
    identity_prefix: str = "identity",
    mtl: Path | None = None,
    field: str = "inputs.shapes",
) -> tuple[MorphMesh, dict]:
    """Read a neutral OBJ and its blendshape OBJs: returns the mesh (deltas = shape - neutral) and the
    identity deltas by name (files whose name starts with ``identity_prefix``)."""
    by_name = _obj_files_by_shape_name(files, field)
    neutral = _neutral_shape_name(by_name, neutral)
    base, triangles, tri_groups, groups = _read_neutral_obj(by_name.pop(neutral), mtl)
    expression_names = [n for n in by_name if not (identity_prefix and n.startswith(identity_prefix))]
    identity_names = sorted(n for n in by_name if identity_prefix and n.startswith(identity_prefix))
    if not expression_names:
        raise UserError(
            "the character has no morph targets: only the neutral mesh (and identities) were given", field=field
        )
    deltas = np.stack([_shape_delta(by_name[n], n, base, field) for n in expression_names])
    identities = {n: _shape_delta(by_name[n], n, base, field) for n in identity_names}
    mesh = MorphMesh(
        positions=base.astype(np.float32),
        triangles=triangles,
        target_names=expression_names,
        deltas=deltas,
        triangle_groups=tri_groups,
        groups=groups,
        name=neutral,
    )
    return mesh, identities


def _obj_files_by_shape_name(files: dict[str, Path], field: str) -> dict[str, Path]:
    """The .obj/.obj.gz inputs by blendshape name (other files ignored); a name given twice is an error."""
    paths = [Path(p) for p in files.values() if re.search(r"\.obj(\.gz)?$", Path(p).name, re.IGNORECASE)]
    if not paths:
        raise UserError("no .obj or .obj.gz files among the inputs", field=field)
    by_name: dict[str, Path] = {}
    for p in paths:
        name = shape_name(p)
        if name in by_name:
            raise UserError(f"two files give the blendshape name '{name}': {by_name[name]} and {p}", field=field)
        by_name[name] = p
    return by_name


def _neutral_shape_name(by_name: dict[str, Path], neutral: str | None) -> str:
    """The neutral mesh's name: the one given, else the one name with 'neutral' in it."""
    if neutral is None:
        candidates = [n for n in by_name if "neutral" in n.lower()]
        if len(candidates) != 1:
            raise UserError(
                f"cannot tell which file is the neutral mesh (candidates {candidates}); set the "
                f"'neutral' param to its name",
                field="params.neutral",
            )
        neutral = candidates[0]
    if neutral not in by_name:
        raise UserError(
            f"no file named '{neutral}' (.obj/.obj.gz) for the neutral mesh; files: {sorted(by_name)}",
            field="params.neutral",
        )
    return neutral


def _read_neutral_obj(path: Path, mtl: Path | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[MaterialGroup]]:
    """The neutral OBJ's vertices, triangles, triangle groups and material groups (colours from the .mtl, if
    any; grey otherwise)."""
    text = read_obj_text(path)
    base = parse_obj_vertices(text, path)
    triangles, tri_groups, group_names = parse_obj_faces(text, len(base), path)
    colors = read_mtl_colors(mtl) if mtl is not None else {}
    groups = [MaterialGroup(n, colors.get(n, (0.75, 0.75, 0.75, 1.0))) for n in group_names]
    return base, triangles, tri_groups, groups


def _shape_delta(path: Path, name: str, base: np.ndarray, field: str) -> np.ndarray:
    """One blendshape OBJ minus the neutral (float32); it must have the neutral's vertex count."""
    verts = parse_obj_vertices(read_obj_text(path), path)
    if len(verts) != len(base):
        raise UserError(
            f"blendshape '{name}' has {len(verts)} vertices but the neutral mesh has {len(base)}; "
            f"every blendshape must share the neutral's topology",
            file=str(path),
            field=field,
        )
    return (verts - base).astype(np.float32)


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


class GltfCharacter(Stage):
    """A glTF 2.0 character (.glb or .gltf) with morph targets; landmark ids from the mesh extras
    (``landmarkVertexIds``) or a JSON input."""

    class Params(Stage.Params):
        mesh_name: str | None = None
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
    resources = {"character": DEFAULT_CHARACTER}

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
        ids = self._landmark_ids(inputs, mesh, path)
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
        }
        return character_result(mesh, ids, source, identity, pivot)

    @staticmethod
    def _landmark_ids(inputs, mesh: MorphMesh, path: Path) -> np.ndarray:
        landmark_file = _single_file(inputs.get("landmarks"), "inputs.landmarks", (".json",))
        if landmark_file is not None:
            return read_landmark_json(landmark_file, len(mesh.positions), "inputs.landmarks")
        if EXTRAS_LANDMARKS in mesh.extras:
            return check_landmark_ids(
                mesh.extras[EXTRAS_LANDMARKS],
                len(mesh.positions),
                file=str(path),
                field=f"mesh.extras.{EXTRAS_LANDMARKS}",
            )
        raise UserError(
            f"the glTF has no '{EXTRAS_LANDMARKS}' in its mesh extras; give the 68 landmark vertex "
            f"ids as a JSON file input 'landmarks'",
            file=str(path),
            field="inputs.landmarks",
        )


class ObjBlendshapes(Stage):
    """A neutral OBJ plus one OBJ per blendshape (.obj or .obj.gz, same vertex order); optional identity OBJs
    (names starting with ``identity_prefix``) for the identity mix."""

    class Params(Stage.Params):
        #: name (file name without .obj/.obj.gz) of the neutral mesh; default: the one file with 'neutral' in it
        neutral: str | None = None
        identity_prefix: str = "identity"
        identity: dict[str, float] = {}
        #: multiply coordinates into metres (ICT FaceKit is in centimetres: 0.01)
        scale: float = Field(1.0, gt=0)
        #: material groups (OBJ usemtl names) to leave out, e.g. transparent overlay shells
        drop_groups: list[str] = []

    inputs = {
        "shapes": Input.files(doc="neutral and blendshape OBJs (a glob or a mapping), plus an optional .mtl"),
        "landmarks": Input.files(doc="JSON with the 68 landmark vertex ids (list, or ICT vertex_indices.json)"),
    }
    outputs = CHARACTER_OUTPUTS

    def run(self, params, inputs):
        files = inputs["shapes"]
        mtl = next((Path(p) for p in files.values() if Path(p).name.lower().endswith(".mtl")), None)
        mesh, identities = load_obj_blendshapes(files, params.neutral, params.identity_prefix, mtl)
        landmark_file = _single_file(inputs["landmarks"], "inputs.landmarks", (".json",))
        ids = read_landmark_json(landmark_file, len(mesh.positions), "inputs.landmarks")
        identity_deltas = np.stack(list(identities.values())) if identities else None
        if params.drop_groups:
            mesh, ids, identity_deltas = drop_triangle_groups(mesh, ids, list(params.drop_groups), identity_deltas)
            identities = dict(zip(identities, identity_deltas)) if identities else {}
        mesh.positions = (mesh.positions * params.scale).astype(np.float32)
        mesh.deltas = (mesh.deltas * params.scale).astype(np.float32)
        identities = {k: v * params.scale for k, v in identities.items()}
        mesh = apply_identity(mesh, identities, dict(params.identity))
        source = {"neutral": mesh.name, "files": len(files), "identity_targets": sorted(identities)}
        return character_result(mesh, ids, source, dict(params.identity))


# ------------------------------------------------------------------------------------------------ the builder

#: ICT FaceKit's overlay geometry made for alpha textures (eye occlusion shadow, tear film, eye blend, eyelash
#: cards): without their textures they render as opaque bands around the eyes
ICT_OVERLAY_GROUPS = ["M_EyeOcclusion", "M_LacrimalFluid", "M_EyeBlend", "M_EyeLashes"]
ICT_EYES = [("M_ScleraLeft", "M_IrisLeft"), ("M_ScleraRight", "M_IrisRight")]
ICT_COPYRIGHT = "ICT FaceKit, Copyright (c) 2020 USC Institute for Creative Technologies, MIT License"


def build_ict_character(source: Path, destination: Path, *, sparse_tolerance: float = 1e-5) -> dict:
    """Build the embedded default character from an ICT FaceKit folder (the project's own code: OBJ reader,
    identity split, sparse GLB writer). Writes the GLB plus LICENSE, CREDITS.md and README.md beside it."""
    source, destination = Path(source), Path(destination)
    mesh, ids, identities = _read_ict_facekit(source)
    identity_names = sorted(identities)
    identity_deltas = np.stack([identities[n] for n in identity_names])
    drop = [g for g in ICT_OVERLAY_GROUPS if g in [x.name for x in mesh.groups]]
    mesh, ids, identity_deltas = drop_triangle_groups(mesh, ids, drop, identity_deltas)
    mesh, ids, identity_deltas, shells = _ict_without_eye_shells(mesh, ids, identity_deltas)
    out = _ict_glb_mesh(mesh, ids, identity_names, identity_deltas)
    glb = write_morph_glb(
        out,
        sparse_tolerance=sparse_tolerance,
        generator="msflow stages.retarget.character build",
        copyright=ICT_COPYRIGHT,
    )
    destination.parent.mkdir(parents=True, exist_ok=True)
    destination.write_bytes(glb)
    for name in ("LICENSE", "CREDITS.md"):
        if (source / name).is_file():
            (destination.parent / name).write_bytes((source / name).read_bytes())
    summary = {
        "file": destination.name,
        "bytes": len(glb),
        "vertices": int(len(out.positions)),
        "triangles": int(len(out.triangles)),
        "expression_targets": len(mesh.target_names),
        "identity_targets": len(identity_names),
        "dropped_groups": drop,
        "eye_shell_triangles_removed": int(shells.sum()),
        "sparse_tolerance_m": sparse_tolerance,
    }
    (destination.parent / "README.md").write_text(_readme(summary, list(mesh.target_names), identity_names))
    return summary


def _read_ict_facekit(source: Path) -> tuple[MorphMesh, np.ndarray, dict[str, np.ndarray]]:
    """ICT FaceKit's generic neutral with its expressions in ICT's order, the 68 landmark ids and the identity
    deltas by name, in ICT's centimetres."""
    indices = json.loads((source / "vertex_indices.json").read_text())
    files = {p.name: p for p in sorted(source.iterdir()) if re.search(r"\.obj(\.gz)?$", p.name)}
    mtl = next(iter(sorted(source.glob("*.mtl"))), None)
    mesh, identities = load_obj_blendshapes(files, "generic_neutral_mesh", "identity", mtl)
    # ICT's canonical expression order first (vertex_indices.json), the extra shapes after
    order = [n for n in indices["expressions"] if n in mesh.target_names]
    order += sorted(n for n in mesh.target_names if n not in order)
    perm = [mesh.target_names.index(n) for n in order]
    mesh.target_names, mesh.deltas = order, mesh.deltas[perm]
    ids = check_landmark_ids(
        indices["idx_to_landmark_verts"], len(mesh.positions), file=str(source / "vertex_indices.json")
    )
    return mesh, ids, identities


def _ict_without_eye_shells(mesh: MorphMesh, ids: np.ndarray, identity_deltas: np.ndarray):
    """Paint each inner eyeball (sclera, iris, pupil) and remove the outer eye shell in front of it; also returns
    which triangles were the shells."""
    group_names = [x.name for x in mesh.groups]
    shells = np.zeros(len(mesh.triangles), dtype=bool)
    for shell, ball in ICT_EYES:
        if shell in group_names and ball in group_names:
            shells |= paint_eyeball(mesh, shell, ball)
    mesh, ids, identity_deltas = drop_triangles(mesh, ~shells, ids, identity_deltas)
    return mesh, ids, identity_deltas, shells


def _ict_glb_mesh(
    mesh: MorphMesh, ids: np.ndarray, identity_names: list[str], identity_deltas: np.ndarray
) -> MorphMesh:
    """The mesh as the GLB holds it: metres, the identity targets after the expressions, and the landmark ids,
    identity names and head pivot in its extras."""
    scale = 0.01  # centimetres -> metres (glTF)
    mesh.positions = (mesh.positions * scale).astype(np.float32)
    all_deltas = np.concatenate([mesh.deltas, identity_deltas]) * scale
    pivot = head_pivot(mesh.positions, ids)
    return MorphMesh(
        positions=mesh.positions,
        triangles=mesh.triangles,
        target_names=list(mesh.target_names) + identity_names,
        deltas=all_deltas.astype(np.float32),
        triangle_groups=mesh.triangle_groups,
        groups=mesh.groups,
        name="ICTFaceKit",
        extras={
            EXTRAS_LANDMARKS: [int(i) for i in ids],
            "landmarkScheme": LANDMARK_SCHEME,
            EXTRAS_IDENTITY: identity_names,
            EXTRAS_PIVOT: [float(v) for v in pivot],
            "source": "ICT FaceKit light face model (generic neutral, 57 expressions, 10 identity "
            "components), built by msflow stages.retarget.character",
        },
    )


def _readme(summary: dict, expressions: list[str], identities: list[str]) -> str:
    """The README.md beside the built GLB: provenance, the command that built it, and what it contains."""
    return "\n".join(
        [
            "# Embedded default character: ICT FaceKit",
            "",
            f"`{summary['file']}` is the default character of the retargeting stages (`stages.retarget.character:GltfCharacter`).",
            "",
            "## Provenance",
            _readme_paragraph(
                "Built from the ICT FaceKit light face model (USC Institute for Creative Technologies, MIT licence: "
                "see `LICENSE` and `CREDITS.md` in this folder; https://github.com/ICT-VGL/ICT-FaceKit) with this "
                "project's own code (OBJ reader, identity split, sparse glTF writer in `stages/`):"
            ),
            "",
            f"    python -m stages.retarget.character build /path/to/ict-facekit data/characters/{summary['file']}",
            "",
            _readme_paragraph(
                "The source folder holds `generic_neutral_mesh.obj.gz`, one `.obj.gz` per blendshape, "
                "`identity000..009.obj.gz`, `ICTFaceModelMaterial.mtl`, `vertex_indices.json`, `LICENSE` and "
                "`CREDITS.md`. The build is deterministic (same input, same bytes)."
            ),
            "",
            "## Contents",
            *[_readme_paragraph(item, "- ") for item in _readme_contents(summary, expressions, identities)],
            "",
        ]
    )


def _readme_paragraph(text: str, indent: str = "") -> str:
    """``text`` with its whitespace collapsed, wrapped at 110 columns; later lines indented under ``indent``."""
    import textwrap

    return textwrap.fill(" ".join(text.split()), width=110, initial_indent=indent, subsequent_indent=" " * len(indent))


def _readme_contents(summary: dict, expressions: list[str], identities: list[str]) -> list[str]:
    """The README's "Contents" items: mesh, what was left out, expression and identity targets, extras, size."""
    return [
        f"One mesh `ICTFaceKit`: {summary['vertices']} vertices, {summary['triangles']} triangles (ICT's quads split "
        f"in two), one primitive per material; metres (ICT's centimetres x 0.01), +y up, facing +z.",
        f"Left out: the overlay geometry made for alpha textures ({', '.join(summary['dropped_groups'])}) and the "
        f"outer eye shells M_ScleraLeft/Right ({summary['eye_shell_triangles_removed']} triangles; transparent "
        f"cornea in front, they hide the eyeball without textures). The inner eyeballs (M_IrisLeft/Right) are "
        f"split by the angle from the eye axis into sclera, iris (< 22 degrees) and pupil (< 8 degrees, plus the "
        f"inward-facing walls of the pupil's tunnel that PupilDilate opens) materials. Vertex ids are renumbered "
        f"and the landmark ids remapped with them.",
        f"{summary['expression_targets']} expression morph targets as sparse accessors (deltas below "
        f"{summary['sparse_tolerance_m'] * 1e6:.0f} micrometres are not stored): {', '.join(expressions)}.",
        f"{summary['identity_targets']} identity morph targets ({', '.join(identities)}), listed in "
        f"`mesh.extras.identityTargetNames`: shape parameters that the character stage mixes into the neutral "
        f"(`params.identity`, neutral + sum c_i delta_i) and does not animate.",
        "`mesh.extras.landmarkVertexIds`: the 68 iBUG landmark vertex ids (ICT's `idx_to_landmark_verts`, "
        "remapped); `mesh.extras.headPivot`: the point the head turns about (metres).",
        f"Size: {summary['bytes']} bytes. Passes the Khronos glTF Validator without errors or warnings.",
    ]


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m stages.retarget.character", description="Build the embedded ICT FaceKit character GLB."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    build = sub.add_parser("build", help="ICT FaceKit folder -> GLB (+ LICENSE, CREDITS.md, README.md)")
    build.add_argument("source", type=Path)
    build.add_argument("destination", type=Path)
    build.add_argument("--sparse-tolerance", type=float, default=1e-5, help="metres; smaller deltas are dropped")
    args = parser.parse_args(argv)
    try:
        summary = build_ict_character(args.source, args.destination, sparse_tolerance=args.sparse_tolerance)
    except UserError as exc:
        print(f"error: {exc}")
        return 2
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


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
