"""What the character's morphs can make of the performer's face at best: the retargeting evaluation of the
capture branch (``eval/retarget.yaml``) beside the same evaluation of a *ceiling* animation, every frame of every
take fitted on its own by bounded least squares with every morph but the gaze's (no keyshapes, no regulariser, no
prior: ``stages.retarget.morph_fit.bounded_fit`` with every penalty 0) to the performer's own FaceMesh deformation
on every point of the 3D keymorph fit (``region_fit.DEFAULT_FIT_REGIONS``), in the head frame as the keymorph fit
reads it. A goal the ceiling misses is beyond what the character's morphs make of these landmarks; the gaze
morphs are the blend's (they come from the iris, not from landmarks). The ceiling has no lip seal and no blink
from the eye aperture (the blend's), so its closures and blinks are the landmarks' alone.

    python bench/retarget_ceiling.py [--head-frame] [--priors] [FOLDER ...]          # from the project root
    python bench/retarget_ceiling.py ../shared/data/talking-heads

The morphs' landmark motion is the keymorph fit's (``Rig3D``: the character's deltas as they are). With
``--head-frame`` it is what the head frame sees of them (``head_frame_rig``): the tracked face is carried into the
head frame frame by frame by the similarity of its rigid points, nostrils among them, which ICT FaceKit's jawOpen,
mouthUpperUp and noseSneer move (0.02-0.07 IOD per unit), so part of those morphs' motion never reaches the
keyshapes. ``--priors`` fits every frame with the keymorph fit itself instead (``region_fit.fit_regions_3d`` with
``KeymorphFit``'s default regions, penalties, antagonisms, correctives, Huber's loss and lip-contact bounds): what
the penalties and priors cost, keyshapes aside.

Prints, per run (CREMA-D's six takes, then each folder), the evaluation table's row for the animation and for the
ceiling, one row per take of each; then, for every column the animation leaves dead where the performer moved it,
the movement on the performer, the animation and the ceiling; then the ceiling's dead ARKit columns and how its
columns follow their movements (the tables of ``bench/eval_retarget.py``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# this checkout's msflow and stages, and eval_retarget's tables
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]
PIPELINE = ROOT / "eval" / "retarget.yaml"


def head_frame_rig(rig, step: float = 1e-3):
    """``rig`` (a ``Rig3D``) as the head frame sees it: each morph's landmark motion less the similarity of the
    rigid points it moves too, to first order (the alignment of a small ``step`` along each delta)."""
    from stages.retarget.region_fit import Rig3D
    from stages.retarget.shapes3d import similarity_align

    aligned = similarity_align(rig.rest[None] + step * rig.deltas, rig.rest) - rig.rest
    return Rig3D(rig.rest, aligned / step)


def frame_fit_weights(data: dict, keyshapes, gaze_weights, head_frame: bool = False, priors: bool = False):
    """(frames, M) morph weights: every frame of every take fitted on its own (``take_frame_fit``); the morphs
    named eyeLook* keep ``gaze_weights``' values."""
    names = data["names"]
    gaze = np.array([n.lower().startswith("eyelook") for n in names])
    out = np.where(gaze[None], gaze_weights, 0.0)
    labels = list(keyshapes.meta["labels"])
    expression = np.asarray(keyshapes["keyshape_expression"])
    rests = np.concatenate([keyshapes["keyshape_rest3d"], keyshapes["keyshape_cheek_rest3d"]], axis=1)
    for take in np.unique(data["sequence"]):
        rows = np.flatnonzero(data["sequence"] == take)
        rest = rests[np.flatnonzero(expression == labels.index(data["labels"][take]))[0]]
        out[rows] += take_frame_fit(data, data["mesh"][rows[0] : rows[-1] + 1], rest, ~gaze, head_frame, priors)
    return out


def take_frame_fit(data: dict, mesh, rest, usable, head_frame: bool = False, priors: bool = False) -> np.ndarray:
    """One take's frames (its FaceMesh, ``mesh``) fitted one by one: each frame's fit points in the head frame,
    carried onto the take's ``rest`` (the keyshapes' closed-mouth rest, 68 + cheek points) by the similarity of the
    rigid points, their deformation from it carried into the character's units and axes
    (``Rig3D.to_character``), and the ``usable`` morphs' weights in [0, 1] that best make it (frames, M); with
    ``priors``, the keymorph fit's weights for it (``prior_fit``)."""
    from stages.retarget.morph_fit import bounded_fit
    from stages.retarget.movements import EXTRA_VERTICES
    from stages.retarget.region_fit import DEFAULT_FIT_REGIONS, Rig3D
    from stages.retarget.shapes3d import head_frame_shapes, similarity_align

    points = sorted({p for region in DEFAULT_FIT_REGIONS for p in region.landmarks})
    rig = Rig3D.build_with_points_near(data["neutral"], data["deltas"], data["landmark_ids"], rest[None])
    shapes = similarity_align(head_frame_shapes(np.asarray(mesh, np.float64), EXTRA_VERTICES), rest)
    deformation = rig.to_character(rest[:68]).apply_linear(shapes - rest)
    if head_frame:
        rig = head_frame_rig(rig)
    if priors:
        return prior_fit(rig, deformation, shapes, data["names"])
    targets = deformation[:, points].reshape(len(shapes), -1)
    jacobian = rig.deltas[:, points].reshape(len(rig.deltas), -1).T
    weights, _ = bounded_fit(jacobian, targets, data["names"], usable, l2=0.0, l1=0.0, symmetry=0.0)
    return weights


def prior_fit(rig, deformation: np.ndarray, shapes: np.ndarray, names: list[str]) -> np.ndarray:
    """The keymorph fit with ``KeymorphFit``'s default params (``keymorphs.fit_3d``) of every frame's
    ``deformation`` (character units), the lip-contact bounds from each frame's ``shapes`` (head frame)."""
    from stages.retarget.face_measures import lip_gap_iod
    from stages.retarget.keymorphs import KeymorphFit, contact_bounds, fit_3d
    from stages.retarget.shapes3d import front_view

    params = KeymorphFit.Params()
    gaps = lip_gap_iod(front_view(shapes[:, :68]))
    bounds = contact_bounds(gaps, names, list(params.contact_morphs), params.contact_gap)
    return fit_3d(params, rig, deformation, names, bounds)[0]


def ceiling_view(result, head_frame: bool = False, priors: bool = False):
    """The capture branch's evaluation of ``result`` (an msflow run), the same evaluation of its ceiling animation
    (a view with ``metrics``, ``meta`` and ``arrays``: what ``bench/eval_retarget.py``'s tables read), the evaluation's
    validated inputs and the ceiling's weights."""
    from stages.eval.retarget import RetargetEval, evaluate

    inputs = {
        "tracks": result.artifact("capture_track"),
        "blend": result.artifact("capture_blend"),
        "character": result.artifact("capture_character"),
        "keyshapes": result.artifact("capture_keyshapes"),
    }
    data = RetargetEval._validate(inputs)
    weights = frame_fit_weights(data, inputs["keyshapes"], data["weights"], head_frame, priors)
    ceiling = evaluate(RetargetEval.Params(), **{**data, "weights": weights})
    view = SimpleNamespace(metrics=ceiling["metrics"], meta=ceiling["meta"], arrays=ceiling["arrays"])
    return result.artifact("capture_eval"), view, data, weights


def dead_column_rows(animation, ceiling, data: dict, weights: np.ndarray) -> list[str]:
    """A row per take and ARKit column the animation leaves dead where the performer moved it: the performer's
    probe peak over its level, the animation's and the ceiling's movement read by the performer's probes
    (``columns.character_movements``), the ceiling's column peak and its following (r, chance)."""
    from stages.eval.columns import character_movements, performer_frame
    from stages.eval.retarget import RetargetEval
    from stages.formats.live_link import ARKIT_NAMES, arkit_weights

    params = RetargetEval.Params()
    lip_gap = ceiling.arrays["lip_gap"]  # the performer's and the ceiling's, as its evaluation measured them
    arkit, _ = arkit_weights(weights, data["names"], data["deltas"])
    rows = []
    for label, take in animation.meta["takes"].items():
        frames = data["sequence"] == data["labels"].index(label)
        performer = performer_frame(data, frames, params)
        gaps = (lip_gap[frames, 0], lip_gap[frames, 1])
        made, _ = character_movements(data, weights[frames], performer, gaps, params)
        for column in take["columns"]["dead_moved"]:
            peak, level = take["movements"][column]
            own = take["character_movements"].get(column, ["-", "-"])[0]
            r, chance = ceiling.meta["takes"][label]["following"].get(column, ["-", "-"])
            column_peak = float(arkit[frames, list(ARKIT_NAMES).index(column)].max())
            rows.append(
                f"| {Path(label).stem} | {column} | {peak:.4f} / {level:.4f} | {own} | {made[column]['peak']:.4f} | "
                f"{column_peak:.2f} | {r} ({chance}) |"
            )
    return rows


def main(args: list[str]) -> None:
    from eval_retarget import column_report, following_report, header, row, take_rows

    import msflow

    head_frame, priors = "--head-frame" in args, "--priors" in args
    folders = [Path(f).resolve() for f in args if f not in ("--head-frame", "--priors")]
    os.chdir(ROOT)
    runs = [("CREMA-D 1001, 6 takes", msflow.run(PIPELINE, until="capture_eval"))]
    for folder in folders:
        relative = os.path.relpath(folder, PIPELINE.parent)
        result = msflow.run(PIPELINE, [f"vars.takes={relative}"], until="capture_eval")
        runs.append((folder.name, result))
    views = [(name, *ceiling_view(result, head_frame, priors)) for name, result in runs]
    model = ("head-frame morphs" if head_frame else "the fit's morphs") + (", the fit's priors" if priors else "")
    print(header())
    for name, animation, ceiling, _, _ in views:
        for label, view in ((f"{name}, the animation", animation), (f"{name}, ceiling ({model})", ceiling)):
            print(row(label, view.metrics))
            print("\n".join(take_rows(view)))
    print("\nColumns the animation leaves dead where the performer moved them, and the ceiling's (movements read by")
    print("the performer's probes, IOD):\n")
    print(
        "| take | column | performer: peak / level | the animation's | the ceiling's | ceiling column peak | "
        "ceiling following r (chance) |"
    )
    print("|---|---|---|---|---|---|---|")
    for _, animation, ceiling, data, weights in views:
        print("\n".join(dead_column_rows(animation, ceiling, data, weights)))
    print()
    for name, _, ceiling, _, _ in views:
        print("\n".join(column_report(f"{name}, ceiling", ceiling)))
        print("\n".join(following_report(f"{name}, ceiling", ceiling)))


if __name__ == "__main__":
    main(sys.argv[1:])
