"""Motion blending (paper Sec. 5.4): the stage that stitches the database motion of the trellis's chosen segments
into new head motion, and measures it.

The stitching (resampling, anchoring of sub-sentences, velocity blending at the joins) is in
``stages.head.stitching``; bringing the motion to the target speaker's amplitude in ``stages.head.amplitude``.

Beyond the paper (each behind a param, the paper's behaviour available): head strokes moved onto the test audio's
onsets by a smooth time warp (``timing``, ``timing_warp``); every source speaker's motion brought to the target
speaker's amplitude and the output centred and scaled to it (``amplitude``); slow wander removed (``rest_anchor``).

Motion is blended as (yaw, pitch, roll) angles and translation: the database is centred on each take's mean pose,
so angles stay small and far from the Euler singularity, where angle rates are close to the angular velocity.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.geometry.rotations import euler_to_quat
from stages.head.amplitude import (
    amplitude_gains,
    amplitude_target,
    knows_speaker,
    match_amplitude,
    mirrored_to_side,
    proportion_correction,
    range_spreads,
    reference_ranges,
    speaker_spreads,
)
from stages.head.measures import (
    JOIN_MEASURE_WINDOW,
    angular_acceleration,
    angular_speed,
    join_acceleration,
    reference_angles,
    wasserstein_speed,
)
from stages.head.stitching import JOIN_BUDGET_OF_MEDIAN, DatabaseMotion, Stitched, segment_knots, stitch_segments

# ---------------------------------------------------------------------------------------------- the stage

MOTION_BLEND_OUTPUTS = {
    "rotation": Output.array(
        "f", shape=("frames", 4), dtype="float64", doc="unit quaternions (stages.geometry.rotations)"
    ),
    "translation": Output.array("f", shape=("frames", 3), dtype="float64", doc="offset from the rest position"),
    "angles": Output.array("f", shape=("frames", 3), dtype="float64", doc="yaw, pitch, roll in radians"),
    "time": Output.array("f", shape=("frames",), dtype="float64", doc="seconds since the utterance's start"),
    "sequence": Output.array("i", shape=("frames",), dtype="int32", doc="test utterance (meta labels)"),
    "joins": Output.array("f", shape=("joins",), dtype="float64", doc="join times on each utterance's clock"),
    "join_utterance": Output.array("i", shape=("joins",), dtype="int32"),
    "join_window": Output.array(
        "f", shape=("joins", 2), dtype="float64", doc="start and end of each join's blend (seconds, utterance clock)"
    ),
    "join_velocity_step": Output.array(
        "f",
        shape=("joins",),
        dtype="float64",
        doc="angular velocity step between the joined segments (deg/s; NaN for the crossfade)",
    ),
    "bvh": Output.file(".bvh", doc="the head joint's motion, utterances back to back"),
}


def _plot_head_angles(view, inputs=None):
    """Head yaw, pitch and roll over time: synthesised (and real, when a reference was given); joins marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fps = float(view.meta["fps"])
    labels = view.meta.get("labels", [])
    mask = view["sequence"] == 0
    angles = np.degrees(view["angles"][mask])
    t = view["time"][mask]
    reference = None
    if inputs and inputs.get("reference") is not None and labels:
        ref = reference_angles(inputs["reference"], labels[0], len(labels), fps)
        reference = None if ref is None else np.degrees(ref)
    joins = view["joins"][view["join_utterance"] == 0]
    windows = view["join_window"][view["join_utterance"] == 0] if "join_window" in view else np.zeros((0, 2))
    fig, axes = plt.subplots(3, 1, figsize=(9, 6), sharex=True, constrained_layout=True)
    for c, (ax, name) in enumerate(zip(axes, ("yaw", "pitch", "roll"))):
        for lo, hi in windows:
            ax.axvspan(lo, hi, color="0.5", alpha=0.06, lw=0, zorder=0)
        for j in joins:
            ax.axvline(j, color="0.85", lw=0.8, zorder=0)
        ax.plot(t, angles[:, c], color="crimson", lw=1.6, label="synthesised")
        if reference is not None:
            ax.plot(np.arange(len(reference)) / fps, reference[:, c], color="0.25", lw=1.2, label="real")
        ax.set_ylabel(f"{name} (deg)")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title(
        f"head angles: {labels[0] if labels else ''} (grey lines: segment joins, shaded: their blend windows)"
    )
    axes[-1].set_xlabel("time (s)")
    return fig


class MotionBlendParams(Stage.Params):
    fps: float | None = Field(
        None, gt=0, description="output rate; None: the test take's video rate, else the database's"
    )
    join_smoothing: Literal["velocity", "crossfade"] = Field(
        "velocity",
        description="velocity-domain blend, or the earlier position crossfade (overshoots the velocity inside its "
        "window)",
    )
    blend_window: float = Field(0.15, ge=0, description="seconds either side of a join to blend over (at least)")
    break_blend_window: float = Field(0.25, ge=0, description="the same at joins between sub-sentences")
    max_blend_window: float = Field(0.5, ge=0, description="widest half-window a large velocity step may get")
    join_acceleration: float | None = Field(
        None,
        ge=0,
        description="deg/s^2 a join's velocity step may add (sets its window); None: half the database's median "
        "angular acceleration; 0: fixed windows",
    )
    preserve_speed: bool = Field(False, description="keep the blended velocity as fast as the joined segments' own")
    timing: Literal["segment", "onsets", "strokes"] = Field(
        "strokes",
        description="resampling of each chosen segment onto its test segment: 'segment', uniform from onset to onset "
        "(the paper); or piecewise, moving the segment's head strokes ('strokes') or its audio onsets ('onsets') "
        "onto the test's audio onsets",
    )
    timing_tolerance: float = Field(0.15, gt=0, description="farthest (s) the timing warp moves an event")
    timing_warp: Literal["monotone", "linear"] = Field(
        "monotone",
        description="the timing warp's time map through its knots: a monotone C1 cubic (the playback rate changes "
        "smoothly) or piecewise linear (the rate steps at each moved event)",
    )
    amplitude: Literal["database", "speaker", "match"] = Field(
        "match",
        description="'database': motion amplitude as recorded (the paper); 'speaker': each source speaker's motion "
        "scaled to the target spread (the test speaker's own from its other takes, else the database's typical "
        "speaker's); 'match': that, and the output centred on the rest pose with its spread set to the target",
    )
    amplitude_target: Literal["auto", "database", "reference"] = Field(
        "auto",
        description="where 'speaker' and 'match' take the angles' target spread: the database (the test speaker's "
        "other takes, else its typical speaker's), the reference input (the performer's own tracked motion in "
        "the test take), or 'auto': the database when it holds the test's speaker (by its speaker label), else "
        "the reference when given",
    )
    max_amplitude_gain: float = Field(3.0, ge=1, description="'match': largest gain (either way) on the output")
    reference_seconds: float | None = Field(
        None,
        gt=0,
        description="amplitude_target 'reference': the target from the first this many seconds of each reference "
        "take (an enrolment stretch of the performer's motion; None: the whole take)",
    )
    source_gain: Literal["auto", "common", "per_angle"] = Field(
        "auto",
        description="'speaker', 'match': one gain per source speaker for its three angles, or one per angle (its "
        "proportions between yaw, pitch and roll brought to the target's before its strokes are timed); 'auto': "
        "per angle where the target is the performer's own motion (the reference), common where it is the "
        "database's",
    )
    refine_proportions: bool = Field(
        True,
        description="where the sources are scaled per angle (source_gain), stitch a second time with their gains "
        "corrected by the first output's proportions between yaw, pitch and roll (blending changes them)",
    )
    side: Literal["performer", "as_stitched"] = Field(
        "performer",
        description="'performer': where the angles' target is the performer's own motion (amplitude_target), the "
        "output mirrored (yaw, roll and the sideways translation negated) when that brings its yaw and roll "
        "p5..p95 closer to the performer's, so a speaker who turns mostly one way keeps doing so; 'as_stitched': "
        "never mirrored",
    )
    output_cutoff: float | None = Field(
        4.0,
        gt=0,
        description="zero-phase low-pass (Hz) of the stitched motion, against the acceleration of segments played "
        "faster than recorded (None: off, the paper)",
    )
    rest_anchor: float = Field(
        0.0, ge=0, description="remove wander slower than this many seconds, back to the rest pose (0: off)"
    )
    max_stretch: float = Field(
        2.0, ge=1, description="fastest or slowest a piece of the warp plays, x the uniform rate"
    )
    drift_correction: bool = Field(True, description="warp each sub-sentence to meet the next")
    translation: bool = Field(True, description="False: rotation only (translation zero)")
    bvh_joint: str = Field("Head", min_length=1)
    bvh_order: Literal["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"] = Field(
        "ZXY", description="Euler channel order written to the BVH"
    )

    @model_validator(mode="after")
    def _target_needs_scaling(self):
        if self.amplitude_target == "reference" and self.amplitude == "database":
            raise ValueError("amplitude_target 'reference' needs amplitude 'speaker' or 'match' (not 'database')")
        return self


class MotionBlend(Stage):
    """Stitch, drift-correct and smooth the joins of the chosen database motion (Sec. 5.4); head rotation,
    translation and a BVH of the head joint at the output rate."""

    cheap = True

    Params = MotionBlendParams
    inputs = {
        "trellis": Input.artifact("segments", "chosen", "db_segments", "db_segment_sequence"),
        "database": Input.artifact("angles", "translation", "sequence", doc="the headdb artifact searched"),
        "reference": Input.artifact(
            "rotation",
            "sequence",
            optional=True,
            doc="real motion of the test take (tracking artifact) for the figure and metrics",
        ),
    }
    outputs = MOTION_BLEND_OUTPUTS
    figures = {"head_angles": _plot_head_angles}

    def run(self, params, inputs):
        trellis, database = inputs["trellis"], inputs["database"]
        check_same_database(trellis, database)
        db = database_motion(database, use_translation=params.translation)
        options = stitch_options(params, db, trellis)
        fps = output_rate(params, trellis, db)
        labels = list(trellis.meta.get("labels") or [])
        if params.amplitude_target == "reference" or (
            params.amplitude_target == "auto" and params.amplitude != "database" and inputs.get("reference") is not None
        ):
            if inputs.get("reference") is None:
                raise UserError(
                    "amplitude_target 'reference' needs the reference input (the test take's tracking)",
                    field="inputs.reference",
                )
            ranges = reference_ranges(inputs["reference"], labels, fps, params.reference_seconds)
            options["targets"] = range_spreads(ranges)
            if params.side == "performer":
                options["sides"] = ranges
        synth = synthesise(trellis, db, fps, **options)
        arrays = pack_motion(synth, fps, params)
        metrics = motion_metrics(arrays, fps, JOIN_MEASURE_WINDOW, inputs.get("reference"), labels)
        metrics.update(join_metrics(arrays))
        meta = {
            "fps": fps,
            "labels": labels,
            "frames": [len(s.channels) for s in synth],
            "join_smoothing": params.join_smoothing,
            "join_acceleration_budget": float(options["acceleration_budget"] or 0.0),
            "stitch": options,
            "translation_units": database.meta.get("translation_units", "unknown"),
            "bvh_joint": params.bvh_joint,
            "db_labels": list(database.meta.get("labels") or []),
        }
        return Result(arrays, meta, metrics, rest_warnings(trellis, labels) + target_warnings(options, labels))


def check_same_database(trellis, database) -> None:
    db_labels = list(database.meta.get("labels") or [])
    if trellis.meta.get("db_labels") is not None and list(trellis.meta["db_labels"]) != db_labels:
        raise UserError(
            "the trellis was searched over a different database than the one given", field="inputs.database"
        )


def stitch_options(params, db: DatabaseMotion, trellis) -> dict:
    """Keyword arguments of ``stitch_segments`` from the stage's params (JSON, kept in the artifact's meta so the
    evaluation can stitch its baselines exactly alike)."""
    budget = (
        JOIN_BUDGET_OF_MEDIAN * db.typical_acceleration()
        if params.join_acceleration is None
        else params.join_acceleration
    )
    return {
        "smoothing": params.join_smoothing,
        "blend_window": params.blend_window,
        "break_blend_window": params.break_blend_window,
        "max_blend_window": params.max_blend_window,
        "acceleration_budget": float(budget) or None,
        "preserve_speed": params.preserve_speed,
        "drift_correction": params.drift_correction,
        "boundary_window": float(trellis.meta.get("boundary_window", 0.1)),
        "timing": params.timing,
        "timing_tolerance": params.timing_tolerance,
        "warp": params.timing_warp,
        "max_stretch": params.max_stretch,
        "amplitude": params.amplitude,
        "max_amplitude_gain": params.max_amplitude_gain,
        "source_gain": params.source_gain,
        "targets": None,  # per utterance, the angles' target spread from the reference (amplitude_target)
        "targets_for": "unknown" if params.amplitude_target == "auto" else "all",
        "sides": None,  # per utterance, the performer's p5..p95 per angle (side), where its amplitude is the target
        "refine_proportions": params.refine_proportions,
        "output_cutoff": params.output_cutoff,
        "rest_anchor": params.rest_anchor,
    }


def target_warnings(options: dict, labels: list[str]) -> list[str]:
    targets = options.get("targets")
    if targets is None:
        return []
    return [
        f"'{label}' is not in the reference: its amplitude comes from the database"
        for label, target in zip(labels, targets)
        if target is None
    ]


def output_rate(params, trellis, db: DatabaseMotion) -> float:
    test_fps = [f for f in (trellis.meta.get("fps") or []) if f]
    return float(params.fps or (test_fps[0] if test_fps else db.fps))


def pack_motion(synth: list, fps: float, params) -> dict:
    """The blend's arrays: angles, rotation, translation, per-frame time and utterance, joins, BVH."""
    from stages.formats.bvh import head_bvh

    def cat(parts, empty):
        return np.concatenate(parts) if parts else empty

    angles = cat([s.channels[:, :3] for s in synth], np.zeros((0, 3)))
    translation = cat([s.channels[:, 3:] for s in synth], np.zeros((0, 3)))
    rotation = euler_to_quat(angles[:, 0], angles[:, 1], angles[:, 2])
    return {
        "rotation": rotation,
        "translation": translation,
        "angles": angles,
        "time": cat([np.arange(len(s.channels)) / fps for s in synth], np.zeros(0)),
        "sequence": cat([np.full(len(s.channels), u, np.int32) for u, s in enumerate(synth)], np.zeros(0, np.int32)),
        "joins": cat([s.joins for s in synth], np.zeros(0)),
        "join_utterance": cat([np.full(len(s.joins), u, np.int32) for u, s in enumerate(synth)], np.zeros(0, np.int32)),
        "join_window": cat([s.windows for s in synth], np.zeros((0, 2))).reshape(-1, 2),
        "join_velocity_step": cat([s.velocity_mismatch for s in synth], np.zeros(0)),
        "bvh": head_bvh(rotation, translation, fps, joint=params.bvh_joint, order=params.bvh_order).encode(),
    }


def join_metrics(arrays: dict) -> dict:
    """Mean velocity step the joins absorbed (deg/s) and mean blend window (s); none for the crossfade."""
    steps = arrays["join_velocity_step"][np.isfinite(arrays["join_velocity_step"])]
    if not len(steps):
        return {}
    widths = np.diff(arrays["join_window"], axis=1)[:, 0]
    return {"mean_join_velocity_step": float(steps.mean()), "mean_join_window": float(widths.mean())}


def rest_warnings(trellis, labels: list[str]) -> list[str]:
    """A warning per test utterance with no voiced segment: its head stays at the rest pose."""
    counts = np.bincount(np.asarray(trellis["segment_utterance"], dtype=np.int64), minlength=len(labels))
    return [
        f"'{label}' has no voiced speech: its head stays at the rest pose" for label, n in zip(labels, counts) if n == 0
    ]


def database_motion(view, *, use_translation: bool = True) -> DatabaseMotion:
    sequence = np.asarray(view["sequence"], dtype=np.int64)
    n_seq = int(sequence.max()) + 1 if len(sequence) else 0
    frames = np.bincount(sequence, minlength=n_seq)
    translation = np.asarray(view["translation"], dtype=np.float64)
    channels = np.concatenate(
        [np.asarray(view["angles"], dtype=np.float64), translation if use_translation else np.zeros_like(translation)],
        axis=1,
    )
    if not np.isfinite(channels).all():
        raise UserError("NaN in the database motion", field="inputs.database")
    first = np.concatenate([[0], np.cumsum(frames)[:-1]])
    return DatabaseMotion(channels, first, frames, float(view.meta["fps"]), view.meta.get("speakers"))


def database_events(trellis, db: DatabaseMotion, timing: str) -> list[np.ndarray]:
    """Per database sequence, the events the timing warp moves: its audio onsets (``timing="onsets"``) or the
    strokes of its head motion (``"strokes"``: maxima of the smoothed angular speed, stages.head.beats)."""
    from stages.head.beats import kinematic_beats

    if timing == "strokes":
        return [
            kinematic_beats(db.channels[first : first + n, :3], db.fps, kind="peaks", smoothing=0.1)
            for first, n in zip(db.first, db.frames)
        ]
    times = np.asarray(trellis["db_onsets"]) if "db_onsets" in trellis else np.zeros(0)
    owner = np.asarray(trellis["db_onset_sequence"]) if "db_onset_sequence" in trellis else np.zeros(0, int)
    return [times[owner == k] for k in range(len(db.frames))]


def utterance_time_maps(
    test_segments: np.ndarray,
    db_segments: np.ndarray,
    db_sequence: np.ndarray,
    test_events: np.ndarray,
    db_events: list[np.ndarray],
    tolerance: float,
    max_stretch: float,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``segment_knots`` of every chosen segment of one utterance."""
    return [
        segment_knots(
            (test_segments[k, 0], test_segments[k, 2]),
            (db_segments[k, 0], db_segments[k, 2]),
            test_events,
            db_events[int(db_sequence[k])],
            tolerance=tolerance,
            max_stretch=max_stretch,
        )
        for k in range(len(test_segments))
    ]


@dataclass
class TrellisPath:
    """What the blend reads from a trellis artifact: test segments, the chosen database segments, onsets."""

    labels: list[str]
    speakers: list
    segments: np.ndarray  # (N, 3) test segments
    utterance: np.ndarray  # (N,)
    subsentence_start: np.ndarray  # (N,)
    db_sequence: np.ndarray  # (N,) database sequence of the chosen segment
    db_segments: np.ndarray  # (N, 3) its times
    onsets: np.ndarray  # test audio onsets
    onset_utterance: np.ndarray
    db_labels: list[str] | None = None  # the searched database's sequences
    excluded: list[list[str]] | None = None  # per utterance, the database sequences held out of its search

    def allowed(self, u: int) -> np.ndarray | None:
        """Database sequences utterance ``u``'s search could use (None: all): its amplitude target must not come
        from the takes held out for it (its own take, or its whole speaker)."""
        if self.db_labels is None or self.excluded is None or u >= len(self.excluded):
            return None
        held_out = set(self.excluded[u])
        return np.array([name not in held_out for name in self.db_labels], dtype=bool)

    @classmethod
    def of(cls, trellis) -> TrellisPath:
        labels = list(trellis.meta.get("labels") or [])
        chosen = np.asarray(trellis["chosen"], dtype=np.int64)
        has_onsets = "test_onsets" in trellis and "test_onset_utterance" in trellis
        return cls(
            labels,
            list(trellis.meta.get("speakers") or [None] * len(labels)),
            np.asarray(trellis["segments"]).reshape(-1, 3),
            np.asarray(trellis["segment_utterance"]),
            np.asarray(trellis["subsentence_start"], dtype=bool),
            np.asarray(trellis["db_segment_sequence"], dtype=np.int64)[chosen],
            np.asarray(trellis["db_segments"]).reshape(-1, 3)[chosen],
            np.asarray(trellis["test_onsets"]) if has_onsets else np.zeros(0),
            np.asarray(trellis["test_onset_utterance"]) if has_onsets else np.zeros(0, int),
            trellis.meta.get("db_labels"),
            trellis.meta.get("excluded"),
        )


def utterance_frames(trellis, u: int, fps: float) -> int:
    """Output frames of test utterance ``u``: its own frame count at its own rate, else its duration at ``fps``."""
    test_fps = (trellis.meta.get("fps") or [None] * (u + 1))[u]
    test_frames = (trellis.meta.get("frames") or [None] * (u + 1))[u]
    if test_frames and test_fps and abs(float(test_fps) - fps) < 1e-6:
        return int(test_frames)
    return int(round(float(trellis.meta["durations"][u]) * fps))


def synthesise(
    trellis,
    db: DatabaseMotion,
    fps: float,
    *,
    timing: str = "segment",
    timing_tolerance: float = 0.15,
    max_stretch: float = 2.0,
    amplitude: str = "database",
    rest_anchor: float = 0.0,
    max_amplitude_gain: float = 3.0,
    output_cutoff: float | None = None,
    source_gain: str = "common",
    targets: list | None = None,
    targets_for: str = "all",
    refine_proportions: bool = False,
    sides: list | None = None,
    **blend,
) -> list[Stitched]:
    """The stitched motion of each test utterance of a trellis artifact (a still head where silent). ``timing``:
    each chosen segment resampled uniformly onto its test segment (``"segment"``, the paper), or with its audio
    onsets (``"onsets"``) or its head strokes (``"strokes"``) moved onto the test's audio onsets
    (``segment_knots``). ``amplitude="speaker"`` scales every source speaker's motion to the test speaker's
    spread (``amplitude_source``), ``"match"`` also centres the output on the rest pose and scales it to that
    spread (``match_amplitude``, gain at most ``max_amplitude_gain``); ``rest_anchor`` > 0 removes wander slower
    than that many seconds (a Gaussian low-pass of that sd), so the head keeps returning to its rest pose;
    ``output_cutoff`` (Hz) low-passes the stitched motion (``lowpass_channels``); ``targets`` (per utterance, the
    angles' spread or None) replaces the database's amplitude target of the angles (``targets_for="unknown"``:
    only where the database does not know the utterance's speaker). ``refine_proportions``: where the sources
    were scaled per angle and the output is matched, stitch a second time with the per-angle gains corrected by
    the first output's proportions (``proportion_correction``). ``sides`` (per utterance, the performer's
    p5..p95 per angle, or None): where the angles' target is the performer's, the output is mirrored when that
    matches its side better (``mirrored_to_side``). ``blend``: keyword arguments of ``stitch_segments``."""
    path = TrellisPath.of(trellis)
    shared_events = database_events(trellis, db, timing) if timing != "segment" else None
    finishing = {"rest_anchor": rest_anchor, "max_gain": max_amplitude_gain, "cutoff": output_cutoff}
    out = []
    for u in range(len(path.labels)):
        given = targets[u] if targets is not None and u < len(targets) else None
        duration = utterance_frames(trellis, u, fps) / fps
        source, target, per_angle, performers = amplitude_source(
            db, path, u, duration, amplitude, given, source_gain, targets_for == "unknown"
        )
        rows = np.flatnonzero(path.utterance == u)
        times = np.arange(utterance_frames(trellis, u, fps)) / fps

        def render(source: DatabaseMotion) -> Stitched:
            events = shared_events
            if timing == "strokes" and source is not db:
                events = database_events(trellis, source, timing)  # the strokes of the motion as it will play
            maps = None
            if events is not None:
                onsets = path.onsets[path.onset_utterance == u]
                maps = utterance_time_maps(
                    path.segments[rows], path.db_segments[rows], path.db_sequence[rows], onsets, events,
                    timing_tolerance, max_stretch,
                )  # fmt: skip
            stitched = stitch_segments(
                source, path.segments[rows], path.subsentence_start[rows], path.db_sequence[rows],
                path.db_segments[rows], times, time_maps=maps, **blend,
            )  # fmt: skip
            if len(rows):
                stitched.channels = finish_channels(stitched.channels, fps, amplitude, target, **finishing)
            return stitched

        stitched = render(source)
        if refine_proportions and per_angle and amplitude == "match" and len(rows):
            stitched = render(source.scaled(proportion_correction(stitched.channels, target, len(db.frames))))
        side = sides[u] if sides is not None and u < len(sides) else None
        if performers and side is not None and len(rows):
            stitched.channels = mirrored_to_side(stitched.channels, side)
        out.append(stitched)
    return out


def finish_channels(
    channels: np.ndarray, fps: float, amplitude: str, target, *, rest_anchor: float, max_gain: float, cutoff
) -> np.ndarray:
    """The stitched channels of an utterance finished: wander slower than ``rest_anchor`` seconds removed (0:
    kept), the amplitude matched to ``target`` (``amplitude="match"``, ``match_amplitude``), low-passed at
    ``cutoff`` Hz (None: not)."""
    if rest_anchor > 0 and len(channels) > 1:
        channels = channels - low_pass(channels, rest_anchor * fps)
    if amplitude == "match":
        channels = match_amplitude(channels, target, max_gain)
    if cutoff:
        channels = lowpass_channels(channels, fps, cutoff)
    return channels


def amplitude_source(
    db: DatabaseMotion,
    path: TrellisPath,
    u: int,
    duration: float,
    amplitude: str,
    angles_target=None,
    source_gain: str = "common",
    database_first: bool = False,
) -> tuple[DatabaseMotion, np.ndarray | None, bool, bool]:
    """The database motion utterance ``u`` is stitched from and its amplitude target: as recorded
    (``amplitude="database"``), or every source speaker brought to the target spread at the utterance's
    ``duration`` (``speaker_spreads`` over the sequences its search could use, ``amplitude_target``), the angles'
    part replaced by ``angles_target`` when given (the performer's own, ``reference_spreads``; with
    ``database_first`` only when the database does not know the speaker, ``knows_speaker``). ``source_gain``:
    each source speaker scaled by one gain for its angles, by one per angle, or (``"auto"``) per angle only where
    the angles' target is the performer's own: only then are its proportions between the angles known. Returns
    the motion, the target, whether the gains are per angle and whether the angles' target is the performer's."""
    if amplitude == "database":
        return db, None, False, False
    spreads = speaker_spreads(db, path.allowed(u), duration)
    target = amplitude_target(spreads, path.speakers[u])
    performers = angles_target is not None and not (database_first and knows_speaker(spreads, path.speakers[u]))
    if performers:
        target = np.array(target, dtype=np.float64)
        target[:3] = angles_target
    per_angle = source_gain == "per_angle" or (source_gain == "auto" and performers)
    return db.scaled(amplitude_gains(db, spreads, target, per_angle)), target, per_angle, performers


def lowpass_channels(channels: np.ndarray, fps: float, cutoff: float) -> np.ndarray:
    """Zero-phase Butterworth low-pass of the output channels at ``cutoff`` Hz (the database's jitter filter,
    stages.head.database.lowpass_motion, applied to the stitched motion).

    Resampling a database segment onto a shorter test segment, and more so the timing warp that moves a stroke,
    plays the motion faster: a rate r multiplies its acceleration by r^2 and moves its frequencies up by r, so a
    nod recorded at 3 Hz comes out at 6-8 Hz where the warp plays a piece at 2-2.7x. The filter takes those
    sped-up peaks (and any velocity kink left at a join) back into the band of real head strokes; the strokes'
    timing, below the cutoff, stays."""
    from scipy.signal import butter, sosfiltfilt

    if cutoff >= 0.5 * fps or len(channels) < 3:
        return channels
    sos = butter(4, cutoff / (0.5 * fps), output="sos")
    return sosfiltfilt(sos, channels, axis=0, padlen=min(3 * (2 * len(sos) + 1), len(channels) - 1))


def low_pass(channels: np.ndarray, sd_frames: float) -> np.ndarray:
    """Gaussian low-pass along frames (edges extended with the end values)."""
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(channels, sd_frames, axis=0, mode="nearest")


def accelerations_at_joins(arrays, fps: float, window: float = JOIN_MEASURE_WINDOW) -> np.ndarray:
    """The largest angular acceleration within +-``window`` s of each join (deg/s^2), utterance by utterance, of a
    MotionBlend output (``angles``, ``sequence``, ``joins``, ``join_utterance``); utterances under 3 frames have none."""
    found = [np.zeros(0)]
    for u in np.unique(arrays["sequence"]):
        angles = arrays["angles"][arrays["sequence"] == u]
        if len(angles) >= 3:
            joins = arrays["joins"][arrays["join_utterance"] == u]
            found.append(join_acceleration(angles, fps, joins, max(window, 1.0 / fps)))
    return np.concatenate(found)


def motion_metrics(arrays: dict, fps: float, window: float, reference, labels: list[str]) -> dict:
    """Speed and join smoothness of the synthesis; against the real motion when a reference is given."""
    metrics = {}
    speeds, ref_speed, ref_acc99, w1 = [], [], [], []
    for u in range(len(labels)):
        mask = arrays["sequence"] == u
        angles = arrays["angles"][mask]
        if len(angles) < 3:
            continue
        speeds.append(angular_speed(angles, fps))
        if reference is not None:
            real = reference_angles(reference, labels[u], len(labels), fps)
            if real is not None and len(real) >= 3:
                ref_speed.append(angular_speed(real, fps))
                ref_acc99.append(np.percentile(angular_acceleration(real, fps), 99))
                w1.append(wasserstein_speed(angles, real, fps))
    if speeds:
        metrics["mean_angular_speed"] = float(np.mean(np.concatenate(speeds)))
    joins = accelerations_at_joins(arrays, fps, window)
    if len(joins):
        metrics["max_join_acceleration"] = float(joins.max())
    if ref_speed:
        metrics["real_mean_angular_speed"] = float(np.mean(np.concatenate(ref_speed)))
        metrics["real_acceleration_p99"] = float(np.max(ref_acc99))
        metrics["speed_wasserstein"] = float(np.mean(w1))
    return metrics
