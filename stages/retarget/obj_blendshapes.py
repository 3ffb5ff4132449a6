"""Reading OBJ blendshape folders: a neutral OBJ plus one OBJ per blendshape (``.obj`` or ``.obj.gz``), names from
the file names, quads and n-gons fan-triangulated, material colours from an optional .mtl (the layout of ICT
FaceKit). Used by the ``ObjBlendshapes`` stage (``stages.retarget.character``) and the ICT FaceKit character build
(``stages.retarget.ict_facekit``).
"""

from __future__ import annotations

import gzip
import re
from pathlib import Path

import numpy as np

from msflow import UserError
from stages.formats.gltf import MaterialGroup, MorphMesh

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
