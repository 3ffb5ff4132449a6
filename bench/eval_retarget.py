"""The retargeting evaluation as tables: ``eval/retarget.yaml`` on the embedded CREMA-D takes (the capture branch
and the default run's paper branch) and, given folders, the capture branch on each.

    python bench/eval_retarget.py [FOLDER ...]          # from the project root
    python bench/eval_retarget.py ../shared/data/talking-heads
    python bench/eval_retarget.py --blinks ../shared/data/talking-heads     # the blink detector vs hand marks
    python bench/eval_retarget.py --identity ../shared/data/talking-heads   # absolute mouth error, identity fitted
    python bench/eval_retarget.py --probes ../shared/data/talking-heads     # dead-where-moved probes, read two ways
    python bench/eval_retarget.py --focal ../shared/data/talking-heads      # the probes' focal length per take
    python bench/eval_retarget.py --resting ../shared/data/talking-heads    # median morph weights per take
    python bench/eval_retarget.py --capture ../shared/data/talking-heads/{hdtf_kh,retalking_2,vlog_31}.mp4
    python bench/eval_retarget.py -S capture_character.fit_identity=true           # CREMA-D, identity fitted
    python bench/eval_retarget.py --capture -S character.fit_identity=true ../shared/data/talking-heads/hdtf_kh.mp4

``-S key=value`` overrides go to every pipeline run (``eval/retarget.yaml``, or ``pipelines/capture.yaml`` with
``--capture``); the capture files of a run with overrides are published as ``out/<clip>_captured_variant.*``.

Prints one markdown row per run (pooled over its takes) and one per take, then, per run, the ARKit columns that
stay dead: where the performer made the movement (by the movement probes of ``stages.retarget.movements``) and
where not, and the movements the character's face makes where the performer made none (false movements). Every
number is a stage metric or meta entry of ``stages.eval.retarget:RetargetEval`` (``msflow show -f
eval/retarget.yaml capture_eval`` shows the same). ``--capture`` runs the performance-capture pipeline
``pipelines/capture.yaml`` on each clip (GLB, CSV, preview in out/) and scores it the same way.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's msflow and stages, whichever one pip installed
PIPELINE = ROOT / "eval" / "retarget.yaml"
COLUMNS = [
    ("mouth err", "mouth_motion_error_iod", "{:.1%}"),
    ("shifted", "mouth_motion_error_iod_shifted", "{:.1%}"),
    ("mouth err, rest aligned", "mouth_neutral_error_iod", "{:.1%}"),
    ("mouth abs", "mouth_error_iod", "{:.1%}"),
    ("mouth abs, own face pose", "mouth_face_posed_error_iod", "{:.1%}"),
    ("eyes err", "eyes_motion_error_iod", "{:.1%}"),
    ("brows err", "brows_motion_error_iod", "{:.1%}"),
    ("keyshape residual", "keyshape_residual_rms_iod", "{:.1%}"),
    ("closures", ("closures_reproduced", "closures"), "{:.0f}/{:.0f}"),
    ("blinks found", ("blinks_found", "blinks"), "{:.0f}/{:.0f}"),
    ("false blinks", "false_blinks", "{:.0f}"),
    ("jaw > funnel", "jaw_over_funnel_fraction", "{:.0%}"),
    ("jawOpen at widest", "jaw_open_at_widest", "{:.2f}"),
    ("press, lips apart", "press_apart_fraction", "{:.0%}"),
    ("env r char/perf/shift", ("envelope_r_character", "envelope_r_performer", "envelope_r_shifted"), "{:.2f}"),
    (
        "dead ARKit: moved (missing) / not",
        ("dead_arkit_moved", "dead_arkit_moved_missing", "dead_arkit_not_moved"),
        "{:.0f} ({:.0f}) / {:.0f}",
    ),
    ("movements missed (chance)", ("movements_missed", "movements_missed_shuffled"), "{:.1%} ({:.1%})"),
    (
        "following r (chance); weak",
        ("following_r_median", "following_r_median_shifted", "following_weak"),
        "{:.2f} ({:.2f}); {:.0%}",
    ),
    ("movement gain; below 0.5", ("movement_gain_median", "movement_gain_below_half"), "{:.2f}; {:.0%}"),
    ("false movements (rate)", ("false_movements", "false_movement_rate"), "{:.0f} ({:.0%})"),
    ("false rate, takes paired wrongly", "false_movement_rate_shuffled", "{:.0%}"),
]


def cell(m: dict, key, fmt: str) -> str:
    if isinstance(key, str):
        return fmt.format(m[key]) if key in m else "-"
    if any(k not in m for k in key):
        return "-"
    values = [m[k] for k in key]
    return fmt.format(*values) if fmt.count("{") == len(values) else "/".join(fmt.format(v) for v in values)


def row(name: str, m: dict) -> str:
    return "| " + " | ".join([name] + [cell(m, key, fmt) for _, key, fmt in COLUMNS]) + " |"


def header(first: str = "run") -> str:
    return f"| {first} | " + " | ".join(c for c, _, _ in COLUMNS) + " |\n|" + "---|" * (len(COLUMNS) + 1)


def take_rows(view) -> list[str]:
    """One row per take, from the evaluation's meta["takes"]."""
    return [row(f"  {Path(label).name}", take["metrics"]) for label, take in view.meta["takes"].items()]


def column_report(name: str, view) -> list[str]:
    """The ARKit columns that stay dead in some take, with the takes where the performer moved them or not."""
    lines = [f"**{name}**: ARKit columns dead in some take (the animation never above 0.02; made: the character's"]
    lines += ["face makes the movement through other morphs, read by the performer's probes)", ""]
    lines += ["| column | performer moved (takes) | dead where moved | dead, not moved |", "|---|---|---|---|"]
    for column, where in view.meta["arkit_columns"].items():
        if not where.get("dead_moved") and not where.get("dead_not_moved") and not where.get("dead_unmeasured"):
            continue
        made = set(where.get("dead_moved_made", []))  # the character's face makes the movement, other morphs
        names = {k: ", ".join(Path(t).stem + (" (made)" if t in made else "") for t in v) for k, v in where.items()}
        moved = len(where.get("moved", []))
        unmeasured = " (no probe)" if where.get("dead_unmeasured") else ""
        lines.append(
            f"| {column}{unmeasured} | {moved} | {names.get('dead_moved', '')} | "
            f"{len(where.get('dead_not_moved', []))} takes |"
        )
    return lines + [""]


def false_report(name: str, view) -> list[str]:
    """Per take, the movements the character's face makes where the performer's probe did not move (false
    movements), with both probes' sustained peaks and levels (IOD)."""
    rows = [
        f"| {Path(label).stem} | {column} | {take['movements'][column][0]:.4f} / {take['movements'][column][1]:.4f} "
        f"| {take['character_movements'][column][0]:.4f} / {take['character_movements'][column][1]:.4f} |"
        for label, take in view.meta["takes"].items()
        for column in take["columns"].get("made_not_moved", [])
    ]
    if not rows:
        return []
    lines = [f"**{name}**: movements the character's face makes where the performer made none (false movements;"]
    lines += ["both read by the performer's probes, sustained peak / level, IOD)", ""]
    return lines + ["| take | column | performer | character |", "|---|---|---|---|", *rows, ""]


def following_report(name: str, view) -> list[str]:
    """Per ARKit column, how closely it follows the movement the performer made (the takes where the probe moved):
    the median correlation of weight and probe over those takes, its chance level, and the weakest takes."""
    per_column: dict[str, list[tuple[float, float, str]]] = {}
    gains: dict[str, list[float]] = {}
    for label, take in view.meta["takes"].items():
        for column, (r, shifted) in take.get("following", {}).items():
            per_column.setdefault(column, []).append((r, shifted, Path(label).stem))
        for column, gain in take.get("movement_gains", {}).items():
            gains.setdefault(column, []).append(gain)
    if not per_column:
        return []
    lines = [f"**{name}**: how closely each column follows the movement where the performer made it, and how large"]
    lines += ["the character's face makes it (movement gain: its probe's spread over the performer's)", ""]
    lines += ["| column | takes | median r | chance | weakest | gain |", "|---|---|---|---|---|---|"]
    for column, values in sorted(per_column.items(), key=lambda kv: float(np.median([v[0] for v in kv[1]]))):
        weakest = ", ".join(f"{t} {r:+.2f}" for r, _, t in sorted(values)[:2])
        median, chance = np.median([v[0] for v in values]), np.median([v[1] for v in values])
        gain = f"{np.median(gains[column]):.2f}" if column in gains else "-"
        lines.append(f"| {column} | {len(values)} | {median:+.2f} | {chance:+.2f} | {weakest} | {gain} |")
    return lines + [""]


def split_overrides(args: list[str]) -> tuple[list[str], list[str]]:
    """``-S key=value`` pairs out of the command line: (overrides, the other arguments)."""
    overrides, rest = [], []
    args = iter(args)
    for arg in args:
        if arg == "-S":
            overrides.append(next(args))
        else:
            rest.append(arg)
    return overrides, rest


def main(folders: list[str], overrides: list[str] = ()) -> None:
    import msflow

    folders = [Path(f).resolve() for f in folders]
    os.chdir(ROOT)
    default = msflow.run(PIPELINE, list(overrides))
    runs = [
        ("CREMA-D 1001, default run's path (edit of the unseen sad take)", default.artifact("paper_eval")),
        ("CREMA-D 1001, capture of the 6 takes", default.artifact("capture_eval")),
    ]
    for folder in folders:
        relative = os.path.relpath(folder, PIPELINE.parent)
        result = msflow.run(PIPELINE, [f"vars.takes={relative}", *overrides], until="capture_eval")
        view = result.artifact("capture_eval")
        runs.append((f"{folder.name}, capture of {len(view.meta['labels'])} takes", view))
    print(header())
    for name, view in runs:
        print(row(name, view.metrics))
        if len(view.meta["takes"]) > 1:
            print("\n".join(take_rows(view)))
    print()
    for name, view in runs:
        print("\n".join(column_report(name, view)))
        print("\n".join(false_report(name, view)))
        print("\n".join(following_report(name, view)))


def blinks(folders: list[str]) -> None:
    """The evaluation's blink detector on the performer's eyelid aperture against the blinks marked by hand
    (``bench/bench_tracking.py`` HAND_BLINKS: CREMA-D and three talking-head clips)."""

    import msflow
    from stages.eval.retarget import RetargetEval

    os.chdir(ROOT)
    params = RetargetEval.Params()
    tracks = [msflow.run(PIPELINE, until="capture_track").artifact("capture_track")]
    for folder in folders:
        relative = os.path.relpath(Path(folder).resolve(), PIPELINE.parent)
        tracks.append(msflow.run(PIPELINE, [f"vars.takes={relative}"], until="capture_track").artifact("capture_track"))
    total = {"reference": 0, "predicted": 0, "found": 0, "false": 0}
    for view in tracks:
        for key, count in hand_blink_agreement(view, params).items():
            total[key] += count
    print(
        f"blink_ratio {params.blink_ratio}, blink_narrow_ratio {params.blink_narrow_ratio}, blink_max_seconds "
        f"{params.blink_max_seconds}: {total['found']}/{total['reference']} hand-marked blinks found, "
        f"{total['predicted']} detected, {total['false']} false"
    )


def hand_blink_agreement(tracks, params) -> dict[str, int]:
    """The evaluation's blink detector (``params``: RetargetEval's) on a tracking artifact's eyelid aperture,
    against the blinks marked by hand (``bench_tracking.HAND_BLINKS``) in its takes that have them: marked
    ("reference"), detected ("predicted"), marked and found, detected but not marked ("false")."""
    from bench_tracking import HAND_BLINKS

    from stages.eval.events import blink_events, blink_frame_limits, event_agreement

    total = {"reference": 0, "predicted": 0, "found": 0, "false": 0}
    sequence, aperture = np.asarray(tracks["sequence"]), np.asarray(tracks["eye_aperture"])
    for take, label in enumerate(tracks.meta["labels"]):
        limit, hand = HAND_BLINKS.get(Path(label).stem, (None, None))
        if hand is None:
            continue
        rows = np.flatnonzero(sequence == take)[: limit or None]
        one = np.zeros(len(rows), np.int64)
        longest = blink_frame_limits([tracks.meta["fps"][take]], one, params.blink_max_seconds)
        found = blink_events(aperture[rows], one, params.blink_ratio, params.blink_narrow_ratio, longest)
        agreement = event_agreement([(a, b + 1) for a, b in hand], found, 0)
        for key in total:
            total[key] += agreement[key]
    return total


def identity(folders: list[str]) -> None:
    """Absolute mouth error with the character's identity fitted to each take's performer (ICT FaceKit's ten
    identity shapes, ridge least squares on the performer's closed-mouth rest in 3D): how much of the absolute
    error is the two faces' different shapes, against the rest-aligned error the evaluation reports."""
    import msflow
    from msflow.testing import run_stage
    from stages.eval.retarget import RetargetEval

    os.chdir(ROOT)
    runs = [("CREMA-D capture", msflow.run(PIPELINE, until="capture_eval"))]
    for folder in folders:
        relative = os.path.relpath(Path(folder).resolve(), PIPELINE.parent)
        runs.append((Path(folder).name, msflow.run(PIPELINE, [f"vars.takes={relative}"], until="capture_eval")))
    identities, ids = identity_landmark_deltas()
    print(
        "| run | take | mouth abs | abs, identity fitted | abs, own face pose | own face pose, identity fitted "
        "| rest aligned | rest aligned, identity fitted |"
    )
    print("|---|---|---|---|---|---|---|---|")
    pooled = {}
    for name, result in runs:
        tracks, blend, character = (result.artifact(s) for s in ("capture_track", "capture_blend", "capture_character"))
        for take, label in enumerate(tracks.meta["labels"]):
            plain, fitted = take_identity_errors(
                tracks, blend, character, take, identities, ids, run_stage, RetargetEval
            )
            keys = ("mouth_error_iod", "mouth_face_posed_error_iod", "mouth_neutral_error_iod")
            cells = [f"{m[k]:.1%}" for k in keys for m in (plain, fitted)]
            print(f"| {name} | {Path(label).name} | " + " | ".join(cells) + " |")
            frames = int(np.sum(np.asarray(tracks["sequence"]) == take))
            for k in keys:  # pooled as the evaluation pools: RMS over all frames
                for tag, m in (("", plain), (" fitted", fitted)):
                    pooled.setdefault((name, k + tag), []).append((frames, m[k]))
        cells = []
        for k in keys:
            for tag in ("", " fitted"):
                n, e = np.array(pooled[(name, k + tag)]).T
                cells.append(f"{np.sqrt((n * e**2).sum() / n.sum()):.1%}")
        print(f"| {name} | all takes | " + " | ".join(cells) + " |")


def identity_landmark_deltas():
    """ICT FaceKit's identity shapes at its 68 landmark vertices (10, 68, 3), and the landmark vertex ids."""
    from stages.retarget.character import DEFAULT_CHARACTER, EXTRAS_IDENTITY, EXTRAS_LANDMARKS, read_morph_mesh

    mesh = read_morph_mesh(DEFAULT_CHARACTER, None)
    ids = np.asarray(mesh.extras[EXTRAS_LANDMARKS])
    names = list(mesh.extras[EXTRAS_IDENTITY])
    deltas = np.stack([mesh.deltas[mesh.target_names.index(n)][ids] for n in names]).astype(np.float64)
    return deltas, ids


def take_identity_errors(tracks, blend, character, take, identities, ids, run_stage, stage, ridge=0.1):
    """The evaluation of one take with the character as it is and with its identity fitted to the performer."""
    from msflow.testing import artifact
    from stages.retarget.identity import fit_identity, performer_rest_face

    rows = np.flatnonzero(np.asarray(tracks["sequence"]) == take)
    one = slice(rows[0], rows[-1] + 1)
    arrays = {k: np.asarray(tracks[k])[one] for k in ("landmarks", "rotation", "translation", "mesh")}
    arrays["sequence"] = np.zeros(len(rows), np.int32)
    meta = {k: [tracks.meta[k][take]] for k in ("labels", "fps", "frame_size", "focal_length")}
    take_tracks = artifact(arrays, meta=meta)
    take_blend = artifact({"weights": np.asarray(blend["weights"])[one]}, meta=blend.meta)
    plain = run_stage(stage, {}, {"tracks": take_tracks, "blend": take_blend, "character": character}).metrics
    neutral = np.asarray(character["neutral"], np.float64)
    c = fit_identity(performer_rest_face(arrays["mesh"]), neutral[ids], identities, ridge)
    fitted_neutral = neutral.copy()
    fitted_neutral[ids] += np.tensordot(c, identities, axes=1)
    arrays = {k: np.asarray(character[k]) for k in character.names}
    fitted_character = artifact(dict(arrays, neutral=fitted_neutral), meta=character.meta)
    fitted = run_stage(stage, {}, {"tracks": take_tracks, "blend": take_blend, "character": fitted_character}).metrics
    return plain, fitted


def character_shapes(character, weights: np.ndarray, performer_rest: np.ndarray) -> np.ndarray:
    """The character's landmark vertices under ``weights`` (frames, 68 + cheek points, 3) in IOD units, the cheek
    points being the character's vertices nearest to the performer's FaceMesh cheek points at rest
    (``performer_rest`` (68 + 12, 3)) carried onto the character by the similarity of the rigid points."""
    from stages.retarget.region_fit import Rig3D

    neutral, deltas, ids = character["neutral"], character["deltas"], character["landmark_ids"]
    rig = Rig3D.build_with_points_near(neutral, deltas, ids, performer_rest[None])
    return (rig.rest[None] + rig.motion(weights)) / rig.iod


def probes(folders: list[str]) -> None:
    """For every ARKit column dead where the performer moved it: the movement probe as the evaluation reads it
    (the FaceMesh with a pinhole's perspective taken out, the focal length found in the take) beside
    the same probe on the FaceMesh as the retarget reads it (no perspective removal), and for the chin raise a
    check on the 2D landmarks: how far the chin-to-nose-bridge distance is below its closed-mouth rest (IOD) at
    the frame where the evaluated probe peaks; last, the evaluation's reading of the character's animation by
    the performer's probes (``stages.eval.columns.character_movements``): how much of the movement the animation
    makes, whichever morph makes it."""
    import msflow
    from stages.eval.retarget import RetargetEval
    from stages.retarget.movements import MovedLevels

    os.chdir(ROOT)
    params = RetargetEval.Params()
    levels = MovedLevels(params.moved_level, params.moved_closure, params.moved_degrees, params.moved_frames)
    runs = [msflow.run(PIPELINE, until="capture_eval")]
    for folder in folders:
        relative = os.path.relpath(Path(folder).resolve(), PIPELINE.parent)
        runs.append(msflow.run(PIPELINE, [f"vars.takes={relative}"], until="capture_eval"))
    print(
        "| take | column | probe peak / level, as evaluated | without perspective removal | 2D chin rise at the "
        "peak | the character's probe peak / level |"
    )
    print("|---|---|---|---|---|---|")
    for result in runs:
        _print_dead_moved_probes(result, params, levels)
    _print_smile_cheek_shares(runs[0], params.brow_rest)


def _probe_rest(shapes: np.ndarray, brow_rest: str) -> np.ndarray:
    """The rest pose of head-frame ``shapes`` as the evaluation takes it (RetargetEval's brow_rest)."""
    from stages.eval.columns import closed_mouth_rest

    return closed_mouth_rest(shapes, brow_rest)[1]


def _print_dead_moved_probes(result, params, levels) -> None:
    """One table row per take of the run and ARKit column dead where the performer moved it."""
    tracks, view = result.artifact("capture_track"), result.artifact("capture_eval")
    sequence, labels = np.asarray(tracks["sequence"]), list(tracks.meta["labels"])
    for label, take in view.meta["takes"].items():
        rows = np.flatnonzero(sequence == labels.index(label))
        plain, evaluated, chin = _take_probes(tracks, sequence, labels.index(label), rows, params)
        for column in take["columns"]["dead_moved"]:
            cells = _probe_cells(column, take, plain, evaluated, chin, rows[0], levels)
            print(f"| {Path(label).stem} | {column} | " + " | ".join(cells) + " |")


def _take_probes(tracks, sequence: np.ndarray, index: int, rows: np.ndarray, params):
    """One take's movement probes without perspective removal and as evaluated (perspective taken out), and the
    2D chin rise above its closed-mouth rest per frame (IOD)."""
    from stages.eval.columns import performer_shapes
    from stages.eval.retarget import jaw_drop, take_cameras
    from stages.retarget.face_measures import level, lip_gap_iod, rest_frames
    from stages.retarget.movements import EXTRA_VERTICES, landmark_probes
    from stages.retarget.shapes3d import head_frame_shapes

    landmarks = np.asarray(tracks["landmarks"])[rows[0] : rows[-1] + 1]
    shapes = head_frame_shapes(np.asarray(tracks["mesh"][rows[0] : rows[-1] + 1], np.float64), EXTRA_VERTICES)
    gap = lip_gap_iod(level(landmarks))
    plain = landmark_probes(shapes, _probe_rest(shapes, params.brow_rest), gap, params.closure_gap)
    camera = take_cameras(tracks.meta, sequence)[index]
    evaluated, _ = performer_shapes(tracks["mesh"], sequence == index, camera, params.probe_focal)
    evaluated = landmark_probes(evaluated, _probe_rest(evaluated, params.brow_rest), gap, params.closure_gap)
    drop = jaw_drop(landmarks)
    chin = drop[rest_frames(landmarks)].mean() - drop
    return plain, evaluated, chin


def _probe_cells(column: str, take: dict, plain: dict, evaluated: dict, chin, first_row: int, levels) -> list[str]:
    """The row's cells after take and column: the evaluated probe, the plain one, the chin rise, the character's."""
    from stages.retarget.movements import moved

    peak, at = take["movements"][column]
    seen = moved({column: plain[column]}, levels)[column] if column in plain else None
    cells = [f"{peak:.4f} / {at:.4f}", f"{seen['peak']:.4f} / {seen['level']:.4f}" if seen else "-"]
    peak_frame = int(np.argmax(evaluated[column]))
    cells.append(f"{chin[peak_frame]:.3f} (frame {first_row + peak_frame})" if column == "MouthShrugLower" else "")
    made = take["character_movements"].get(column)
    cells.append(f"{made[0]:.4f} / {made[1]:.4f}" if made else "-")
    return cells


def _print_smile_cheek_shares(result, brow_rest: str) -> None:
    """The character's smile cheek lift per unit corner rise, beside the probe's SMILE_CHEEK_LIFT."""
    from stages.retarget.movements import EXTRA_VERTICES, SMILE_CHEEK_LIFT
    from stages.retarget.shapes3d import head_frame_shapes

    character, tracks = result.artifact("capture_character"), result.artifact("capture_track")
    rows = np.flatnonzero(np.asarray(tracks["sequence"]) == 0)
    mesh = np.asarray(tracks["mesh"][rows[0] : rows[-1] + 1], np.float64)
    rest = _probe_rest(head_frame_shapes(mesh, EXTRA_VERTICES), brow_rest)
    shares = " / ".join(f"{share:.2f}" for share in smile_cheek_shares(character, rest))
    print(f"\nThe character's smile lifts the skin below its lids by {shares} of its corner's rise (left / right; the")
    print(f"cheek-raise probe takes out SMILE_CHEEK_LIFT = {SMILE_CHEEK_LIFT} of the performer's corner rise)")


def smile_cheek_shares(character, performer_rest: np.ndarray) -> list[float]:
    """Per side (left, right), how far the character's mouthSmile lifts the skin below the lower lid (its vertices
    nearest to the FaceMesh cheek-raise points, ``character_shapes``) per unit of its lip corner's rise."""
    from stages.retarget.movements import CHEEK_VERTICES, EXTRA_VERTICES, SIDE_POINTS

    names = list(character.meta["target_names"])
    sides = (("Left", "L"), ("Right", "R"))
    weights = np.zeros((3, len(names)))  # the neutral face, then each side's smile
    for row, (_, suffix) in enumerate(sides, start=1):
        weights[row, names.index(f"mouthSmile_{suffix}")] = 1.0
    shapes = character_shapes(character, weights, performer_rest)
    out = []
    for row, (side, _) in enumerate(sides, start=1):
        moved = shapes[row] - shapes[0]
        cheek = [68 + EXTRA_VERTICES.index(v) for v in CHEEK_VERTICES[side]["raise"]]
        out.append(float(moved[cheek, 1].mean() / moved[SIDE_POINTS[side]["corner"], 1]))
    return out


def capture(clips: list[str], overrides: list[str] = ()) -> None:
    """pipelines/capture.yaml on each clip, scored against the clip's tracking (RetargetEval on its artifacts)."""
    import resource

    import msflow
    from msflow.testing import run_stage
    from stages.eval.retarget import RetargetEval

    pipeline = ROOT / "pipelines" / "capture.yaml"
    clips = [Path(c).resolve() for c in clips]
    os.chdir(ROOT)
    print(header("clip").replace("| clip |", "| clip | frames | CPU s |", 1).replace("|---|", "|---|---|---|", 1))

    def cpu_seconds():  # this process and the FFmpeg processes it waited for (decoding, the preview's encoder)
        usage = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
        return sum(u.ru_utime + u.ru_stime for u in usage)

    for clip in clips:
        before = cpu_seconds()
        take = os.path.relpath(clip, pipeline.parent)
        name = f"{clip.stem}_captured" + ("_variant" if overrides else "")
        result = msflow.run(pipeline, [f"vars.take={take}", f"vars.name={name}", *overrides])
        cpu = cpu_seconds() - before
        inputs = {
            n: result.artifact(s) for n, s in (("tracks", "track"), ("blend", "blend"), ("character", "character"))
        }
        metrics = run_stage(RetargetEval, {}, dict(inputs, keyshapes=result.artifact("keyshapes"))).metrics
        frames = len(result.artifact("blend")["weights"])
        cells = row(clip.name, metrics).strip("| ").split(" | ")
        print("| " + " | ".join([cells[0], str(frames), f"{cpu:.1f}"] + cells[1:]) + " |")


def focal(folders: list[str]) -> None:
    """Per take, the scatter of the rigid points (% IOD, ``shapes3d.rigid_scatter``) after taking a pinhole's
    perspective out of the FaceMesh with multiples of tracking's focal length (the frame width) and with none,
    and the focal length the movement probes use (``shapes3d.estimate_focal``)."""
    import msflow
    from stages.eval.retarget import take_cameras
    from stages.retarget.shapes3d import estimate_focal

    os.chdir(ROOT)
    multiples = [0.5, 1.0, 2.0, 4.0, 8.0, np.inf]
    runs = [msflow.run(PIPELINE, until="capture_track")]
    for folder in folders:
        relative = os.path.relpath(Path(folder).resolve(), PIPELINE.parent)
        runs.append(msflow.run(PIPELINE, [f"vars.takes={relative}"], until="capture_track"))
    names = ["none" if not np.isfinite(m) else f"f x{m:g}" for m in multiples]
    print("| take (tracked f, px) | " + " | ".join(names) + " | f found |")
    print("|---" * (len(multiples) + 2) + "|")
    for result in runs:
        tracks = result.artifact("capture_track")
        sequence, labels = np.asarray(tracks["sequence"]), list(tracks.meta["labels"])
        cameras = take_cameras(tracks.meta, sequence)
        for i, label in enumerate(labels):
            rows = np.flatnonzero(sequence == i)
            mesh = np.asarray(tracks["mesh"][rows[0] : rows[-1] + 1], np.float64)
            _, scatter = estimate_focal(mesh, cameras[i], multiples)
            found, _ = estimate_focal(mesh, cameras[i])
            cells = [f"{100 * v:.2f}" for v in scatter] + [f"{found:.0f}" if np.isfinite(found) else "none"]
            print(f"| {Path(label).stem} ({cameras[i][0, 0]:.0f}) | " + " | ".join(cells) + " |")


#: morph groups whose median weight over a take says what expression the character holds at rest
RESTING_GROUPS = {
    "browDown": ("browDown_L", "browDown_R"),
    "browInnerUp/OuterUp": ("browInnerUp_L", "browInnerUp_R", "browOuterUp_L", "browOuterUp_R"),
    "eyeWide": ("eyeWide_L", "eyeWide_R"),
    "eyeBlink": ("eyeBlink_L", "eyeBlink_R"),
    "mouthFrown": ("mouthFrown_L", "mouthFrown_R"),
    "mouthSmile": ("mouthSmile_L", "mouthSmile_R"),
}


def closed_mouth_brow_bias(mesh: np.ndarray) -> float:
    """How much higher the brows sit above the eyes in a take's closed-mouth frames than their median (IOD)."""
    from stages.retarget.face_measures import rest_frames
    from stages.retarget.regions import BROWS, EYES
    from stages.retarget.shapes3d import front_view, head_frame_shapes

    shapes = head_frame_shapes(np.asarray(mesh, np.float64))
    shapes = shapes[np.isfinite(shapes).all(axis=(1, 2))]
    height = shapes[:, list(BROWS), 1].mean(axis=1) - shapes[:, list(EYES), 1].mean(axis=1)
    return float(height[rest_frames(front_view(shapes))].mean() - np.median(height))


def resting(folders: list[str], overrides: list[str] = ()) -> None:
    """Per take, the median over its frames of the capture blend's weights (each group: the mean of its morphs)
    and of their sum: what the character holds through the take; and the performer's brows in the take's
    closed-mouth frames against their median (height above the eyes, IOD, head frame: the bias of a rest taken at
    the closed-mouth frames). Overrides compare settings, e.g. -S capture_keyshapes.brow_rest=median."""
    import msflow

    os.chdir(ROOT)
    takes = ["../data/crema-d"] + [os.path.relpath(Path(f).resolve(), PIPELINE.parent) for f in folders]
    print("| take | brows at closed mouth - median (IOD) | sum of the weights | " + " | ".join(RESTING_GROUPS) + " |")
    print("|---|---|" + "---|" * (len(RESTING_GROUPS) + 1))
    for folder in takes:
        result = msflow.run(PIPELINE, [f"vars.takes={folder}", *overrides], until="capture_blend")
        blend, tracks = result.artifact("capture_blend"), result.artifact("capture_track")
        names, weights = list(blend.meta["target_names"]), np.asarray(blend["weights"], np.float64)
        weights = weights.reshape(-1, weights.shape[-1])
        sequence, mesh = np.asarray(tracks["sequence"]), np.asarray(tracks["mesh"])
        for take, label in enumerate(tracks.meta["labels"]):
            mine = weights[sequence == take]
            cells = [closed_mouth_brow_bias(mesh[sequence == take]), np.median(mine.sum(axis=1))]
            for group in RESTING_GROUPS.values():
                cells.append(np.median(mine[:, [names.index(n) for n in group if n in names]].mean(axis=1)))
            print(f"| {Path(label).stem} | {cells[0]:+.4f} | " + " | ".join(f"{c:.2f}" for c in cells[1:]) + " |")


def dispatch(argv: list[str]) -> None:
    """The command line: the docstring's forms; -h prints it; a user error is one line, exit 2."""
    import msflow

    overrides, args = split_overrides(argv)
    if args[:1] in (["-h"], ["--help"]):
        print(__doc__)
        return
    modes = {"--blinks": blinks, "--identity": identity, "--probes": probes, "--focal": focal}  # no overrides
    try:
        if args[:1] == ["--capture"]:
            capture(args[1:], overrides)
        elif args[:1] == ["--resting"]:
            resting(args[1:], overrides)
        elif args[:1] and args[0] in modes:
            modes[args[0]](args[1:])
        elif args[:1] and args[0].startswith("-"):
            raise msflow.UserError(f"unknown option {args[0]} (python bench/eval_retarget.py --help)")
        else:
            main(args, overrides)
    except msflow.UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT / "bench"))
    dispatch(sys.argv[1:])
