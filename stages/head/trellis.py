"""The ``trellis`` stage: pitch matching and path search over the head-motion database (paper Sec. 5.2-5.3,
Eq. 10-15).

The segments and their distance (Eq. 10-12) are ``stages.head.segments``; the trellis search (Eq. 13-15) and the
database it searches are ``stages.head.search``. This module holds the stage: its params and outputs, what each test
take may match (speaker reference, holdout, excluded takes), the artifact's packing and metrics, and the trellis
figure (paper Fig. 7).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.head.copies import copy_warnings, take_of
from stages.head.pitch import semitones
from stages.head.search import (
    Database,
    SearchResult,
    SearchSettings,
    build_database,
    search_utterance,
    sequence_reference,
)
from stages.head.segments import (
    SegmentTable,
    SegmentWeights,
    SpeakerReference,
    segment_scales,
    segment_table,
    zscore_stats,
)

TRELLIS_OUTPUTS = {
    "segments": Output.array("f", shape=("segments", 3), dtype="float64", doc="test segments (start, voiced end, end)"),
    "test_onsets": Output.array("f", shape=("test_onsets",), dtype="float64", doc="audio onsets of the test (s)"),
    "test_onset_utterance": Output.array("i", shape=("test_onsets",), dtype="int32"),
    "db_onsets": Output.array("f", shape=("db_onsets",), dtype="float64", doc="audio onsets of the database (s)"),
    "db_onset_sequence": Output.array("i", shape=("db_onsets",), dtype="int32"),
    "segment_utterance": Output.array("i", shape=("segments",), dtype="int32", doc="index into meta labels"),
    "subsentence_start": Output.array("b", shape=("segments",)),
    "chosen": Output.array("i", shape=("segments",), dtype="int32", doc="database segment per test segment"),
    "chosen_rank": Output.array("i", shape=("segments",), dtype="int32", doc="its column in candidates"),
    "candidates": Output.array("i", shape=("segments", None), dtype="int32", doc="top K database segments"),
    "candidate_cost": Output.array("f", shape=("segments", None), dtype="float64", doc="their D (Eq. 12)"),
    "node_cost": Output.array("f", shape=("segments",), dtype="float64", doc="D of the chosen segment"),
    "transition_cost": Output.array(
        "f", shape=("segments",), dtype="float64", doc="C (Eq. 15) from the previous segment; 0 at sub-sentence starts"
    ),
    "transition_smoothness": Output.array("f", shape=("segments",), dtype="float64", doc="w1 H part"),
    "transition_repeat": Output.array("f", shape=("segments",), dtype="float64", doc="w2 R part"),
    "db_segments": Output.array("f", shape=("db_segments", 3), dtype="float64", doc="database segment times"),
    "db_segment_sequence": Output.array(
        "i", shape=("db_segments",), dtype="int32", doc="database (headdb) sequence of each segment"
    ),
    "db_segment_position": Output.array("i", shape=("db_segments",), dtype="int32"),
    "phrase_distance": Output.array(
        "f", shape=("utterances", "db_sequences"), dtype="float64", doc="phrase-stage distance, NaN where excluded"
    ),
    "phrase_selected": Output.array("b", shape=("utterances", "db_sequences"), doc="phrases searched"),
}


def _plot_trellis(view, inputs=None, utterance: int = 0, max_segments: int = 40):
    """Paper Fig. 7: the K candidates per test segment (colour: D) and the chosen path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mask = np.flatnonzero(view["segment_utterance"] == utterance)[:max_segments]
    cost = view["candidate_cost"][mask]
    rank = view["chosen_rank"][mask]
    chosen = view["chosen"][mask]
    seq = view["db_segment_sequence"][chosen]
    pos = view["db_segment_position"][chosen]
    n, k = cost.shape if cost.ndim == 2 else (0, 0)
    fig, ax = plt.subplots(figsize=(max(8, 0.45 * n + 2), 5), constrained_layout=True)
    if n:
        _draw_candidates(fig, ax, cost)
        _draw_chosen_path(ax, view["subsentence_start"][mask], rank, seq, pos)
        _label_chosen(ax, rank, seq, pos, view.meta.get("db_labels", []))
    labels = view.meta.get("labels", [])
    _finish_trellis_axes(ax, k, labels[utterance] if labels else "the test")
    return fig


def _draw_candidates(fig, ax, cost: np.ndarray) -> None:
    """The trellis's nodes: every candidate (test segment, rank) coloured by its node cost, on faint grid lines."""
    n, k = cost.shape
    xs, ys = np.meshgrid(np.arange(n), np.arange(k), indexing="ij")
    for t in range(n - 1):
        for i in range(k):
            ax.plot([t, t + 1], [i, i], color="0.92", lw=0.5, zorder=0)
    sc = ax.scatter(xs.ravel(), ys.ravel(), c=cost.ravel(), cmap="viridis_r", s=40, zorder=2)
    fig.colorbar(sc, ax=ax, label="node cost D (Eq. 12)")


def _draw_chosen_path(ax, sub: np.ndarray, rank: np.ndarray, seq: np.ndarray, pos: np.ndarray) -> None:
    """Dashed lines at sub-sentence starts, and the chosen path: red, orange where it continues a database take."""
    n = len(rank)
    for t in range(n):
        if sub[t]:
            ax.axvline(t - 0.5, color="k", ls="--", lw=0.8)
    for a in range(n):
        if a + 1 < n and not sub[a + 1]:
            consecutive = seq[a] == seq[a + 1] and pos[a] + 1 == pos[a + 1]
            ax.plot(
                [a, a + 1],
                [rank[a], rank[a + 1]],
                color="crimson" if not consecutive else "orange",
                lw=2.5 if consecutive else 1.8,
                zorder=3,
            )
    ax.scatter(np.arange(n), rank, facecolors="none", edgecolors="crimson", s=120, lw=1.5, zorder=4)


def _label_chosen(ax, rank: np.ndarray, seq: np.ndarray, pos: np.ndarray, db_labels: list) -> None:
    """Each chosen node labelled with its database take and segment (take:segment)."""
    for t in range(len(rank)):
        name = db_labels[seq[t]] if seq[t] < len(db_labels) else str(seq[t])
        ax.annotate(
            f"{name}:{pos[t]}",
            (t, rank[t]),
            textcoords="offset points",
            xytext=(0, 9),
            fontsize=6,
            ha="center",
            rotation=60,
        )


def _finish_trellis_axes(ax, k: int, name: str) -> None:
    """Axis labels, ticks and the title of the trellis figure of the test take ``name``."""
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("test segment")
    ax.set_ylabel("candidate rank (0 = best D)")
    ax.set_ylim(k - 0.5 if k else 1, -2.2)  # rank 0 on top, room for the database labels above it
    ax.set_yticks(range(k))
    ax.set_title(
        f"trellis of {name}: chosen path in red, orange where "
        f"database-consecutive;\nlabels: database take:segment; dashed lines: sub-sentence starts",
        fontsize=10,
    )


class TrellisParams(Stage.Params):
    top_m: int = Field(20, ge=1, description="phrases searched (database sequences, mirrors included)")
    k: int = Field(
        3, ge=1, description="candidates per test segment (the paper gives no value; 3 tuned on the shared clips)"
    )
    b: float = Field(0.05, ge=0, le=1, description="weight of G_d (Eq. 12)")
    c: float = Field(0.3, ge=0, le=1, validate_default=True, description="weight of P_d; L_d gets 1 - b - c")
    e: float = Field(0.0, ge=0, description="weight of the loudness-contour distance E_d (beyond the paper; 0: off)")
    o: float = Field(0.0, ge=0, description="weight of the onset-rate distance O_d (beyond the paper; 0: off)")
    w1: float = Field(1.0, ge=0, description="weight of H (Eq. 15)")
    w2: float = Field(1.0, ge=0, description="weight of R (Eq. 15)")
    unit: Literal["semitones", "zscore", "hz"] = Field(
        "semitones",
        description="pitch unit of P_d and G_d: semitones relative to the speaker's median, those divided by the "
        "speaker's spread (z-scores per speaker), or Hz",
    )
    test_speaker: Literal["auto", "own", "database"] = Field(
        "auto",
        description="reference of the test's pitch: that speaker's median in the database (the test's speaker "
        "label, or the database's only speaker), or its own speaker's median (from the test takes); auto: the "
        "database's where it knows the speaker, else its own, with a warning; database: an error where it does not",
    )
    contour_length: int | None = Field(None, ge=2, description="None: the database's mean voiced length in frames")
    boundary_window: float = Field(0.1, gt=0, description="seconds either side for P, V, A at segment boundaries")
    warp_boundaries: bool = Field(
        True,
        description="H as the blend joins: V, A of each candidate scaled by its resampling to the test segment's "
        "length (False: on the recordings' own clocks)",
    )
    holdout: Literal["none", "take", "speaker"] = Field(
        "none",
        description="leave out of the database, for each test take: nothing; the take itself (its source file, "
        "mirror included); or every take of its speaker",
    )
    exclude_labels: list[str] = Field([], description="database recordings (labels) to leave out")
    same_performance: list[list[str]] = Field(
        [],
        description="groups of take labels that record one performance (two cameras, a re-encoded or cropped copy): "
        "with holdout 'take', a test take also leaves out the other takes of its group (their pieces and mirrors "
        "included), since their motion and voice are its own",
    )
    speaker_motion: Literal["any", "same"] = Field(
        "any",
        description="database motion a test take may use: any speaker's (the paper), or only its own speaker's "
        "when the database holds some after the holdout (beyond the paper; any speaker's otherwise)",
    )

    @field_validator("c")
    @classmethod
    def _weights_sum(cls, value, info):
        b = info.data.get("b")
        if b is not None and b + value > 1 + 1e-12:
            raise ValueError(f"b + c must be at most 1 (got b={b}, c={value}); L_d gets 1 - b - c")
        return value


class Trellis(Stage):
    """Two-stage pitch matching and Viterbi path search (Sec. 5.2-5.3) from test pitch to database segments."""

    cheap = True

    Params = TrellisParams
    inputs = {
        "database": Input.artifact("angles", "sequence", doc="headdb artifact (motion)"),
        "database_pitch": Input.artifact("segments", "f0", "phrase_features", doc="pitch of the headdb artifact"),
        "test_pitch": Input.artifact("segments", "f0", "phrase_features", doc="pitch of the test audio"),
    }
    outputs = TRELLIS_OUTPUTS
    figures = {"trellis": _plot_trellis}

    def run(self, params, inputs):
        db, length = build_database(
            inputs["database"],
            inputs["database_pitch"],
            unit=params.unit,
            length=params.contour_length,
            window=params.boundary_window,
        )
        result = search(db, inputs["test_pitch"], params, length, inputs["database"].meta)
        result.arrays.update(onsets_of("test", inputs["test_pitch"]) | onsets_of("db", inputs["database_pitch"]))
        if params.holdout == "take":
            result.warnings += copy_warnings(inputs["database"], params.same_performance)
        return result


def onsets_of(prefix: str, pitch) -> dict[str, np.ndarray]:
    """A pitch artifact's audio onsets and their utterance, carried through for the blend's timing (empty when the
    artifact predates onsets)."""
    has = "onsets" in pitch and "onset_utterance" in pitch
    times = np.asarray(pitch["onsets"], dtype=np.float64) if has else np.zeros(0)
    owner = np.asarray(pitch["onset_utterance"], dtype=np.int32) if has else np.zeros(0, np.int32)
    return {f"{prefix}_onsets": times, f"{prefix}_onset_{'utterance' if prefix == 'test' else 'sequence'}": owner}


def reference_for_test(test_view, db: Database, test_speaker: str) -> tuple[SpeakerReference, np.ndarray]:
    """Per test utterance: the reference of its pitch unit, and the shift (semitones) that re-expresses its level
    phrase features (computed relative to its own speaker's median) relative to that reference."""
    own = sequence_reference(test_view, "inputs.test_pitch", required=False)
    if test_speaker == "own":
        return own, np.zeros(len(own.median))
    speakers = list(test_view.meta.get("speakers") or [None] * len(own.median))
    found = [db.speaker_reference(s) for s in speakers]
    missing = [s for s, f in zip(speakers, found) if f is None]
    if missing and test_speaker == "database":
        named = "an unlabelled test take" if missing[0] is None else f"test speaker '{missing[0]}'"
        raise UserError(
            f"{named} is not in the database, so its pitch has no database reference; set test_speaker: own or "
            "auto (or label the test take with a database speaker)",
            field="params.test_speaker",
        )
    found = [f if f is not None else (m, v) for f, m, v in zip(found, own.median, own.spread)]  # auto: its own
    reference = SpeakerReference(np.array([f[0] for f in found]), np.array([f[1] for f in found]))
    return reference, semitones(own.median, reference.median)


def unknown_speakers_warning(test_view, db: Database, test_speaker: str) -> list[str]:
    """The warning of ``test_speaker: auto`` when a test take's speaker is not in the database."""
    if test_speaker != "auto":  # own: no take needs the database; database: such a take is an error
        return []
    labels = list(test_view.meta.get("labels") or [])
    speakers = list(test_view.meta.get("speakers") or [None] * len(labels))
    strangers = [label for label, s in zip(labels, speakers) if db.speaker_reference(s) is None]
    if not strangers:
        return []
    return [
        f"the database does not know the speaker of {strangers} (unlabelled, or a speaker it holds no takes of): "
        "their pitch is measured against their own median (test_speaker: own for them)"
    ]


def allowed_sequences(db: Database, params, test_source: str, test_speaker: str | None, label: str) -> np.ndarray:
    """Database sequences one test utterance may use: not in exclude_labels, nor held out (``params.holdout``)."""
    allowed = np.array(
        [
            lab not in params.exclude_labels and rec not in params.exclude_labels
            for lab, rec in zip(db.labels, db.recordings)
        ]
    )
    if params.holdout == "take":
        allowed &= np.array([src != test_source for src in db.sources])
        linked = linked_takes(params.same_performance, take_of(label))
        allowed &= np.array([take_of(lab) not in linked for lab in db.labels])
    elif params.holdout == "speaker":
        if test_speaker is None:
            raise UserError(
                f"holdout: speaker needs the test take's speaker, and '{label}' has no speaker label",
                field="params.holdout",
            )
        allowed &= np.array([spk != test_speaker for spk in db.speakers])
    if params.speaker_motion == "same" and test_speaker is not None:
        own = allowed & np.array([spk == test_speaker for spk in db.speakers])
        allowed = own if own.any() else allowed
    return allowed


def linked_takes(groups: list[list[str]], take: str) -> set[str]:
    """The other takes recorded in one performance with ``take`` (``same_performance``)."""
    return {other for group in groups if take in group for other in group if other != take}


def test_phrase_features(test_view, shift: np.ndarray) -> np.ndarray:
    """The test's phrase features with their pitch-level features moved onto the matching reference."""
    features = np.asarray(test_view["phrase_features"], dtype=np.float64).copy()
    names = list(test_view.meta.get("feature_names") or [])
    level = [names.index(f) for f in test_view.meta.get("level_features", []) if f in names]
    features[:, level] += shift[:, None]
    return features


def search(db: Database, test_view, params, length: int, db_meta: dict) -> Result:
    """The search for every test utterance, packed as the trellis artifact."""
    test_labels = list(test_view.meta.get("labels") or [])
    _check_named_takes(db, params, test_labels)
    test_sources = list(test_view.meta.get("sources") or test_labels)
    test_speakers = list(test_view.meta.get("speakers") or [None] * len(test_labels))
    reference, shift = reference_for_test(test_view, db, params.test_speaker)
    test = segment_table(test_view, reference, params.unit, length)
    features = test_phrase_features(test_view, shift)
    weights = SegmentWeights(params.b, params.c, params.e, params.o)
    settings = SearchSettings(params.top_m, params.k, weights, params.w1, params.w2, params.warp_boundaries)
    scales = segment_scales(db.segments)
    results, excluded = [], []
    for u, label in enumerate(test_labels):
        allowed = allowed_sequences(db, params, test_sources[u], test_speakers[u], label)
        excluded.append([db.labels[i] for i in np.flatnonzero(~allowed)])
        results.append(
            search_utterance(
                test.rows(np.flatnonzero(test.utterance == u)),
                features[u],
                db,
                allowed,
                settings,
                scales,
                zscore_stats(db.features[allowed]),
            )
        )
    meta = {
        "labels": test_labels,
        "sources": test_sources,
        "speakers": test_speakers,
        **_search_meta(test_view, db, params, length, db_meta),
        "phrases_searched": [int(r.phrase_selected.sum()) for r in results],
        "excluded": excluded,
    }
    result = pack_search(test, db, results, params, meta)
    result.warnings.extend(unknown_speakers_warning(test_view, db, params.test_speaker))
    return result


def _check_named_takes(db: Database, params, test_labels: list[str]) -> None:
    """Every take that ``exclude_labels`` and ``same_performance`` name is a database or test take."""
    unknown = [x for x in params.exclude_labels if x not in db.labels and x not in db.recordings]
    if unknown:
        raise UserError(f"exclude_labels {unknown} are not database labels", field="params.exclude_labels")
    takes = {take_of(x) for x in [*db.labels, *test_labels]}
    strangers = sorted({x for group in params.same_performance for x in group} - takes)
    if strangers:
        raise UserError(
            f"same_performance names {strangers}, which are neither database nor test takes",
            field="params.same_performance",
        )


def _search_meta(test_view, db: Database, params, length: int, db_meta: dict) -> dict:
    """The trellis artifact's meta that does not depend on the search: the test's clocks and the settings."""
    count = len(test_view.meta.get("labels") or [])
    return {
        "durations": [float(x) for x in np.asarray(test_view["utterance_duration"])],
        "fps": list(test_view.meta.get("fps") or [None] * count),
        "frames": list(test_view.meta.get("frames") or [None] * count),
        "db_labels": db.labels,
        "db_fps": float(db_meta["fps"]),
        "k": params.k,
        "contour_length": length,
        "boundary_window": float(params.boundary_window),
        "warp_boundaries": bool(params.warp_boundaries),
        "unit": params.unit,
        "test_speaker": params.test_speaker,
        "holdout": params.holdout,
        "smoothness_weights": db.weights.tolist(),
    }


def pack_search(test: SegmentTable, db: Database, results: list[SearchResult], params, meta: dict) -> Result:
    """Arrays and metrics of the trellis artifact from the per-utterance results."""
    k, n_db = params.k, len(db.labels)

    def cat(name, empty):
        return np.concatenate([getattr(r, name) for r in results]) if results else empty

    smooth, repeat = cat("smoothness", np.zeros(0)), cat("repeat", np.zeros(0))
    seg = db.segments
    arrays = {
        "segments": test.times,
        "segment_utterance": test.utterance.astype(np.int32),
        "subsentence_start": test.subsentence_start.astype(bool),
        "chosen": cat("chosen", np.zeros(0)).astype(np.int32),
        "chosen_rank": cat("rank", np.zeros(0)).astype(np.int32),
        "candidates": cat("candidates", np.zeros((0, k))).astype(np.int32),
        "candidate_cost": cat("candidate_cost", np.zeros((0, k))).astype(np.float64),
        "node_cost": cat("node_cost", np.zeros(0)).astype(np.float64),
        "transition_cost": (smooth + repeat).astype(np.float64),
        "transition_smoothness": smooth.astype(np.float64),
        "transition_repeat": repeat.astype(np.float64),
        "db_segments": seg.times,
        "db_segment_sequence": seg.utterance.astype(np.int32),
        "db_segment_position": seg.position.astype(np.int32),
        "phrase_distance": np.stack([r.phrase_distance for r in results]) if results else np.zeros((0, n_db)),
        "phrase_selected": np.stack([r.phrase_selected for r in results]) if results else np.zeros((0, n_db), bool),
    }
    return Result(arrays, meta, search_metrics(arrays, seg, test.subsentence_start, params.w2))


def search_metrics(arrays: dict, seg: SegmentTable, subsentence_start: np.ndarray, w2: float) -> dict:
    """Costs of the chosen path, and how often it continues a database take or repeats a segment."""
    chosen = arrays["chosen"]
    n = len(chosen)
    joins = ~np.asarray(subsentence_start, dtype=bool)
    consecutive = np.zeros(n, dtype=bool)
    if n > 1:
        consecutive[1:] = (seg.utterance[chosen[1:]] == seg.utterance[chosen[:-1]]) & (
            seg.position[chosen[1:]] == seg.position[chosen[:-1]] + 1
        )
    consecutive &= joins
    repeats = arrays["transition_repeat"][joins] == 2 * w2
    return {
        "segments": n,
        "db_segments": len(seg),
        "total_cost": float(arrays["node_cost"].sum() + arrays["transition_cost"].sum()),
        "mean_node_cost": float(arrays["node_cost"].mean()) if n else 0.0,
        "mean_transition_cost": float(arrays["transition_cost"][joins].mean()) if joins.any() else 0.0,
        "consecutive_fraction": float(consecutive[joins].mean()) if joins.any() else 0.0,
        "repeat_fraction": float(repeats.mean()) if joins.any() and w2 > 0 else 0.0,
    }
