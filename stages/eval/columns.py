"""Retargeting evaluation, the ARKit columns against the performer's movements: which columns never move in a take
though the performer made their movement (dead where moved), whether the character's face makes such a movement
through other morphs all the same (made or missing), how closely each column follows its movement over the frames,
and how large the face makes each movement (movement gain). The movements are the probes of
``stages.retarget.movements`` on the tracked FaceMesh (pose and perspective taken out) and the eye outputs of
tracking; the character's face is read by the same probes (``character_movements``); ``stages.eval.retarget``
calls these per take and pools them. The converse of a dead column is a *false movement*: the character's face
makes a movement in a take where the performer made none (``false_movements``), with its chance level from the
takes paired wrongly (``pooled_false_movements``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.eval.events import eye_aperture, pearson


def performer_shapes(tracks_mesh, rows: np.ndarray, camera: np.ndarray, focal: str = "estimated"):
    """One take's performer in the head frame, IOD units (frames, 68 + cheek points, 3), from the tracked FaceMesh
    with a pinhole's perspective taken out, and the focal length used (pixels; inf: none). ``focal``: the one
    ``shapes3d.estimate_focal`` finds in the take (``estimated``), or the tracked ``camera``'s (``tracked``:
    tracking's own estimate, or what it was given)."""
    from stages.retarget.movements import EXTRA_VERTICES
    from stages.retarget.shapes3d import estimate_focal, head_frame_shapes, undo_perspective, with_focal

    index = np.flatnonzero(rows)  # a take's frames are contiguous: read them as one slice of the stored mesh
    mesh = np.asarray(tracks_mesh[index[0] : index[-1] + 1], np.float64)
    used = estimate_focal(mesh, camera)[0] if focal == "estimated" else float(camera[0, 0])
    return head_frame_shapes(undo_perspective(mesh, with_focal(camera, used)), EXTRA_VERTICES), used


@dataclass(frozen=True)
class PerformerFrame:
    """One take's performer as the probes read it: head-frame shapes (frames, 68 + cheek points, 3) in IOD, the
    closed-mouth frames its rest is the mean of, that rest, and the focal length the perspective came out with."""

    shapes: np.ndarray
    rest_frames: np.ndarray
    rest: np.ndarray
    focal: float


def performer_frame(data: dict, rows: np.ndarray, params) -> PerformerFrame | None:
    """The take's ``PerformerFrame`` from its FaceMesh (None without one: 2D landmarks read a turn of the head
    as a sideways jaw or a frown)."""
    if data.get("mesh") is None:
        return None
    camera = data["camera"][np.flatnonzero(rows)[0]]
    shapes, focal = performer_shapes(data["mesh"], rows, camera, params.probe_focal)
    return PerformerFrame(shapes, *closed_mouth_rest(shapes, params.brow_rest), focal)


def closed_mouth_rest(shapes: np.ndarray, brow_rest: str) -> tuple[np.ndarray, np.ndarray]:
    """The closed-mouth frames of head-frame ``shapes`` (frames, 68 [+ cheek points], 3), seen from the front,
    and the rest pose they give (``face_measures.rest_pose`` with ``brow_rest``)."""
    from stages.retarget.face_measures import rest_frames, rest_pose
    from stages.retarget.shapes3d import front_view

    closed = rest_frames(front_view(shapes[:, :68]))
    return closed, rest_pose(shapes, closed, brow_rest)


def take_movements(data: dict, rows: np.ndarray, gap: np.ndarray, performer: PerformerFrame | None, params):
    """Per ARKit column with a probe: did the performer make that movement in this take
    (``stages.retarget.movements``)? With the probes themselves (column -> (frames,)). ``gap``: the take's
    inner-lip gap / IOD."""
    from stages.retarget.movements import eye_probes, landmark_probes, moved

    probes = {}
    if performer is not None:
        probes = landmark_probes(performer.shapes, performer.rest, gap, params.closure_gap)
    aperture = data["aperture"][rows] if data["aperture"] is not None else eye_aperture(data["landmarks"][rows])
    gaze = data["gaze"][rows] if data["gaze"] is not None else None
    probes.update(eye_probes(aperture, gaze))
    return moved(probes, moved_levels(params)), probes


def moved_levels(params):
    """The evaluation's ``MovedLevels`` from its params."""
    from stages.retarget.movements import MovedLevels

    return MovedLevels(params.moved_level, params.moved_closure, params.moved_degrees, params.moved_frames)


def character_movements(data: dict, weights: np.ndarray, performer: PerformerFrame, gaps: tuple, params):
    """The landmark movements the character's animation makes in one take, whichever morphs make them, measured
    as the performer's are: its landmark vertices (and those nearest to the performer's cheek points) under
    ``weights`` (frames, M), each frame carried onto the performer's rest by the similarity of the rigid points
    (so a rigid point that moves tilts the head frame as it does the performer's), taken from their pose at the
    performer's rest frames and read by the performer's probes (``movements.probes_read_on``). ``gaps``: the
    performer's and the character's inner-lip gaps / IOD over the take's frames. Returns ``moved`` of those probes
    and the probes themselves (column -> (frames,))."""
    from stages.retarget.face_measures import rest_pose
    from stages.retarget.movements import moved, probes_read_on
    from stages.retarget.region_fit import Rig3D
    from stages.retarget.shapes3d import similarity_align

    rest = performer.rest
    rig = Rig3D.build_with_points_near(data["neutral"], data["deltas"], data["landmark_ids"], rest[None])
    animated = similarity_align(rig.rest[None] + rig.motion(weights), rest)
    motion = animated - rest_pose(animated, performer.rest_frames, params.brow_rest)
    probes = probes_read_on(performer.shapes, rest, gaps[0], params.closure_gap, motion, gaps[1])
    return moved(probes, moved_levels(params)), probes


def movement_gains(performer: dict, character: dict, movements: dict, frames: np.ndarray) -> dict[str, float]:
    """Per column whose movement the performer made in a take (landmark probes the character is read by,
    ``character_movements``): how large the character's movement is against the performer's, the standard
    deviation of its probe over the take's ``frames`` (bool mask) over the performer's, the performer's taken
    without its frame-to-frame jitter (``movements.jitter``: tracking noise the animation should not copy). 1: as
    large; the slower part of the tracking noise still counts as movement, so a faithful animation reads somewhat
    below 1."""
    from stages.retarget.movements import jitter

    out = {}
    for column, probe in performer.items():
        if column not in character or not movements[column]["moved"]:
            continue
        own = np.asarray(probe)[frames]
        spread = float(np.var(own) - jitter(own) ** 2)
        if spread > 0:
            out[column] = round(float(np.std(np.asarray(character[column])[frames]) / np.sqrt(spread)), 3)
    return out


def outside_blinks(blinks: list[tuple[int, int]], frames: int, margin: int = 1) -> np.ndarray:
    """(frames,) bool: the frames outside every blink event (start, stop), ``margin`` frames either side."""
    out = np.ones(frames, bool)
    for start, stop in blinks:
        out[max(start - margin, 0) : stop + margin] = False
    return out


def pooled_gains(takes: dict) -> dict[str, float]:
    """The median of ``movement_gains`` over every (take, column) pair, and the share of pairs below a half."""
    gains = np.array([g for t in takes.values() for g in t.get("movement_gains", {}).values()], np.float64)
    if not gains.size:
        return {}
    return {"movement_gain_median": float(np.median(gains)), "movement_gain_below_half": float(np.mean(gains < 0.5))}


def column_following(arkit: np.ndarray, columns: list[str], probes: dict, movements: dict) -> dict[str, list[float]]:
    """Per column whose movement the performer made in this take: the Pearson correlation over its frames of
    the column's weight with its probe, and of the weight rolled by half the take (chance: no timing)."""
    out = {}
    for c, column in enumerate(columns):
        probe = probes.get(column)
        if probe is None or not movements[column]["moved"]:
            continue
        weight = np.asarray(arkit[:, c], np.float64)
        pair = [pearson(probe, weight), pearson(probe, np.roll(weight, len(weight) // 2))]
        out[column] = [round(r, 3) for r in pair]
    return out


def dead_where_moved(
    arkit: np.ndarray, columns: list[str], movements: dict, rows: np.ndarray, level: float, made: dict | None = None
) -> dict:
    """One take's ARKit columns sorted by what the animation and the performer did: ``dead_moved`` (never above
    ``level`` though the performer made the movement), ``dead_not_moved``, ``dead_unmeasured`` (no probe); of the
    ``dead_moved``, ``dead_moved_made``: those whose movement the character's face makes all the same, through
    other morphs (``made``: ``character_movements``)."""
    peak = np.asarray(arkit)[rows].max(axis=0, initial=0.0)
    out: dict[str, list[str]] = {k: [] for k in ("dead_moved", "dead_moved_made", "dead_not_moved", "dead_unmeasured")}
    out.update(moved=[], measured=[])
    for c, column in enumerate(columns):
        if movements.get(column) is not None:
            out["measured"].append(column)
        probe = movements.get(column)
        if probe is not None and probe["moved"]:
            out["moved"].append(column)
        if peak[c] >= level:
            continue
        key = "dead_unmeasured" if probe is None else "dead_moved" if probe["moved"] else "dead_not_moved"
        out[key].append(column)
        if key == "dead_moved" and (made or {}).get(column, {}).get("moved"):
            out["dead_moved_made"].append(column)
    return out


def pooled_dead(takes: dict, arkit: np.ndarray, columns: list[str], level: float) -> dict[str, float]:
    """Dead ARKit columns over all takes: never above ``level`` anywhere (``dead_arkit_columns``), dead in some take
    where the performer made the movement (``dead_arkit_moved``; ``dead_arkit_moved_missing``: of those, the ones
    whose movement the character's face did not make through other morphs either, in some take), dead everywhere
    and the movement never made (``dead_arkit_not_moved``), and the share of (take, column) movements the
    animation never showed."""
    peak = np.asarray(arkit).max(axis=0, initial=0.0)
    dead = {c for c, p in zip(columns, peak) if p < level}
    moved_anywhere = {c for t in takes.values() for c in t["columns"]["moved"]}
    dead_moved = {c for t in takes.values() for c in t["columns"]["dead_moved"]}
    missing = {
        c for t in takes.values() for c in set(t["columns"]["dead_moved"]) - set(t["columns"]["dead_moved_made"])
    }
    measured = {c for t in takes.values() for c in t["columns"]["measured"]}
    return {
        "dead_arkit_columns": float(len(dead)),
        "dead_arkit_moved": float(len(dead_moved)),
        "dead_arkit_moved_missing": float(len(missing)),
        "dead_arkit_not_moved": float(len((dead & measured) - moved_anywhere)),
        "dead_arkit_unmeasured": float(len(dead - measured)),
        "moved_arkit_columns": float(len(moved_anywhere)),
        **pooled_missed(takes),
    }


def paired_wrongly(takes: dict, count) -> tuple[int, int]:
    """``count(animated, performed)`` -> (hits, pairs), summed over every ordered pair of two different takes: a
    metric's chance level, each take's real animation set against another take's performer."""
    values = list(takes.values())
    sums = np.array([count(a, b) for a in values for b in values if a is not b]).reshape(-1, 2).sum(axis=0)
    return int(sums[0]), int(sums[1])


def pooled_missed(takes: dict) -> dict[str, float]:
    """The share of the performer's (take, column) movements whose column the animation leaves dead there
    (``movements_missed``) and its chance level (``movements_missed_shuffled``, ``paired_wrongly``; none with one
    take)."""

    def count(animated: dict, performed: dict) -> tuple[int, int]:
        columns = animated["columns"]
        dead = {*columns["dead_moved"], *columns["dead_not_moved"], *columns["dead_unmeasured"]}
        moved = set(performed["columns"]["moved"])
        return len(moved & dead), len(moved)

    moves = sum(len(t["columns"]["moved"]) for t in takes.values())
    out = {"movements_missed": float(sum(len(t["columns"]["dead_moved"]) for t in takes.values()) / max(moves, 1))}
    missed, pairs = paired_wrongly(takes, count)
    if pairs:
        out["movements_missed_shuffled"] = missed / pairs
    return out


def false_movements(movements: dict, made: dict | None) -> list[str]:
    """The columns whose movement the character's face makes in a take (``made``: ``character_movements``, read
    by the performer's probes, whichever morphs make it) though the performer's probe did not move there
    (``movements``: ``take_movements``): an animation that frowns, sneers or juts the jaw where the performer did
    not. Landmark probes only (the character's face is not read for the eyes' aperture and gaze)."""
    return sorted(c for c, m in (made or {}).items() if m["moved"] and c in movements and not movements[c]["moved"])


def pooled_false_movements(takes: dict) -> dict[str, float]:
    """False movements over every (take, column) pair the performer did not move and the character was read on
    (``character_movements`` per take: column -> [peak, level]; ``columns["moved"]``, ``columns["made"]``): their
    count, their share of those pairs, and the same share with the character's movements of each take set
    against the performer's of every other take (chance, ``paired_wrongly``; none with one take). Empty where
    the character was read on no column (no FaceMesh)."""

    def count(animated: dict, performed: dict) -> tuple[int, int]:
        moved, made = set(performed["columns"]["moved"]), set(animated["columns"]["made"])
        still = [c for c in animated["character_movements"] if c in performed["movements"] and c not in moved]
        return sum(c in made for c in still), len(still)

    real = np.array([count(t, t) for t in takes.values()]).reshape(-1, 2).sum(axis=0)
    if not real[1]:  # the character read nowhere (no FaceMesh): nothing measured, not "none"
        return {}
    out = {"false_movements": float(real[0]), "false_movement_rate": float(real[0] / real[1])}
    wrong, pairs = paired_wrongly(takes, count)
    if pairs:
        out["false_movement_rate_shuffled"] = wrong / pairs
    return out


def pooled_following(takes: dict) -> dict[str, float]:
    """How closely the columns follow the movements the performer made (``column_following``), over every
    (take, column) pair: the median correlation, the same for the weights rolled by half a take (chance), and the
    share of pairs below 0.3."""
    pairs = np.array([r for t in takes.values() for r in t["following"].values()], np.float64).reshape(-1, 2)
    if not len(pairs):
        return {}
    return {
        "following_r_median": float(np.median(pairs[:, 0])),
        "following_r_median_shifted": float(np.median(pairs[:, 1])),
        "following_weak": float(np.mean(pairs[:, 0] < 0.3)),
    }
