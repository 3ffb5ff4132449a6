"""The generic 3D face used for head pose and the optical-flow shape model: the 68 iBUG landmark vertices of
the ICT FaceKit neutral mesh (plus their expression and identity offsets).

``extract_ict_landmarks`` builds ``data/face3d/ict_landmarks68.json`` once from an ICT FaceKit copy
(``generic_neutral_mesh.obj.gz`` + ``vertex_indices.json["idx_to_landmark_verts"]``); the stages read only the
JSON. Units are the FaceKit's centimetres; axes are glTF's head frame (x to the viewer's right when the face
looks at the viewer, y up, z out of the face), the frame of stages.geometry.rotations.
"""

from __future__ import annotations

import gzip
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msflow import UserError
from stages.data import DATA

DEFAULT_FACE3D = DATA / "face3d" / "ict_landmarks68.json"


def read_obj_vertices(path: str | Path) -> np.ndarray:
    """(V, 3) vertex positions of an OBJ file (gzip-compressed when the name ends in .gz)."""
    path = Path(path)
    opener = gzip.open if path.suffix == ".gz" else open
    rows = []
    with opener(path, "rt") as fh:
        for line in fh:
            if line.startswith("v "):
                rows.append(line.split()[1:4])
    return np.array(rows, dtype=np.float64)


def extract_ict_landmarks(facekit_dir: str | Path, *, with_shapes: bool = True) -> dict:
    """The 68 landmark vertices of the ICT FaceKit neutral mesh, and (``with_shapes``) each expression's and
    identity's offset at those vertices, as a JSON-ready dict."""
    facekit_dir = Path(facekit_dir)
    indices = json.loads((facekit_dir / "vertex_indices.json").read_text())
    landmark_ids = [int(i) for i in indices["idx_to_landmark_verts"]]
    if len(landmark_ids) != 68:
        raise ValueError(f"expected 68 landmark vertices, found {len(landmark_ids)}")
    neutral = read_obj_vertices(facekit_dir / "generic_neutral_mesh.obj.gz")
    out = {
        "source": "ICT FaceKit generic_neutral_mesh.obj, vertex_indices.json idx_to_landmark_verts",
        "units": "cm",
        "axes": "glTF head frame: +x viewer's right, +y up, +z out of the face",
        "landmark_scheme": "ibug68",
        "vertex_ids": landmark_ids,
        "rigid_landmarks": [int(i) for i in indices.get("idx_to_rigid_landmark_idx", [])],
        "neutral": np.round(neutral[landmark_ids], 5).tolist(),
    }
    if with_shapes:
        names = list(indices["expressions"])
        shapes = {}
        for name in names + [f"identity{i:03d}" for i in range(100)]:
            path = facekit_dir / f"{name}.obj.gz"
            if path.is_file():
                delta = read_obj_vertices(path)[landmark_ids] - neutral[landmark_ids]
                shapes[name] = np.round(delta, 5).tolist()
        out["expression_offsets"] = {k: v for k, v in shapes.items() if not k.startswith("identity")}
        out["identity_offsets"] = {k: v for k, v in shapes.items() if k.startswith("identity")}
    return out


def write_face3d(facekit_dir: str | Path, out_dir: str | Path) -> Path:
    """Write ict_landmarks68.json, LICENSE and CREDITS.md (copied from the FaceKit) into ``out_dir``."""
    import shutil

    facekit_dir, out_dir = Path(facekit_dir), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / "ict_landmarks68.json"
    target.write_text(json.dumps(extract_ict_landmarks(facekit_dir), separators=(",", ":")) + "\n")
    for name in ("LICENSE", "CREDITS.md"):
        shutil.copyfile(facekit_dir / name, out_dir / name)
    return target


@dataclass(frozen=True)
class Face3D:
    """68 3D landmarks (cm, glTF head frame) plus per-shape offsets (name -> (68, 3))."""

    neutral: np.ndarray
    expression_offsets: dict
    identity_offsets: dict
    rigid: tuple[int, ...]


def load_face3d(path: str | Path = DEFAULT_FACE3D, *, field: str | None = None) -> Face3D:
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        neutral = np.asarray(data["neutral"], dtype=np.float64)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UserError(f"cannot read the 3D face landmarks ({exc})", file=str(path), field=field) from None
    if neutral.shape != (68, 3):
        raise UserError(
            f"3D face must hold 68 points of (x, y, z), got shape {neutral.shape}", file=str(path), field=field
        )
    expr = {k: np.asarray(v, dtype=np.float64) for k, v in data.get("expression_offsets", {}).items()}
    ident = {k: np.asarray(v, dtype=np.float64) for k, v in data.get("identity_offsets", {}).items()}
    return Face3D(neutral, expr, ident, tuple(data.get("rigid_landmarks", ())))


if __name__ == "__main__":  # python -m stages.tracking.face3d <ict-facekit dir> [out dir]
    import sys

    if len(sys.argv) < 2:
        sys.exit("usage: python -m stages.tracking.face3d <ICT FaceKit folder> [out dir]")
    src = sys.argv[1]
    dst = sys.argv[2] if len(sys.argv) > 2 else str(DEFAULT_FACE3D.parent)
    print(write_face3d(src, dst))
