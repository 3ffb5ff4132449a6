"""Build script of the embedded default character, data/characters/ict-facekit.glb, from the ICT FaceKit OBJs
(the project's own code: OBJ reader, identity split, sparse GLB writer), with the mesh preparation only it uses
(painting the untextured eyeballs' iris and pupil):
``python -m stages.retarget.ict_facekit build /path/to/ict-facekit data/characters/ict-facekit.glb``.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from msflow import UserError
from stages.formats.gltf import MaterialGroup, MorphMesh, write_morph_glb
from stages.retarget.character import (
    EXTRAS_IDENTITY,
    EXTRAS_LANDMARKS,
    EXTRAS_PIVOT,
    LANDMARK_SCHEME,
    check_landmark_ids,
    drop_triangle_groups,
    drop_triangles,
    head_pivot,
)
from stages.retarget.obj_blendshapes import load_obj_blendshapes

# ------------------------------------------------------------------------------------------------ eyeballs


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
        generator="msflow stages.retarget.ict_facekit build",
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
            "components), built by msflow stages.retarget.ict_facekit",
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
            f"    python -m stages.retarget.ict_facekit build /path/to/ict-facekit data/characters/{summary['file']}",
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
        prog="python -m stages.retarget.ict_facekit", description="Build the embedded ICT FaceKit character GLB."
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
