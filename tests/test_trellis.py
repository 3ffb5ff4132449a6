"""Pitch matching and Viterbi path search (paper Sec. 5.2-5.3, Eq. 10-15)."""

import itertools

import numpy as np
import pytest
from head_synthetic import synth_database, tracking_artifact
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from msflow import UserError
from msflow.testing import artifact, run_stage
from stages.head.database import TrackedHeadDb
from stages.head.pitch import Pitch
from stages.head.search import Database, smoothness_weights, transition_costs, viterbi
from stages.head.segments import (
    SegmentScales,
    SegmentTable,
    SegmentWeights,
    SpeakerReference,
    contour_geometry,
    segment_distances,
)
from stages.head.trellis import Trellis, reference_for_test, unknown_speakers_warning


@pytest.fixture(scope="module")
def phrases():
    return synth_database(24, seed=7)


@pytest.fixture(scope="module")
def database(phrases):
    headdb = run_stage(TrackedHeadDb, {}, {"tracks": tracking_artifact(phrases)})
    return headdb, run_stage(Pitch, {}, {"source": headdb})


@pytest.fixture(scope="module")
def plain_database(phrases):
    headdb = run_stage(TrackedHeadDb, {"mirror": False}, {"tracks": tracking_artifact(phrases)})
    return headdb, run_stage(Pitch, {}, {"source": headdb})


@pytest.fixture(scope="module")
def take_pitch(phrases):
    return run_stage(Pitch, {}, {"source": tracking_artifact(phrases[:8])})


def search(db, test, **params):
    return run_stage(Trellis, params, {"database": db[0], "database_pitch": db[1], "test_pitch": test})


# ------------------------------------------------------------------------------------------- pure maths


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 5), st.integers(1, 4), st.integers(0, 10_000))
def test_viterbi_finds_the_cheapest_path(n, k, seed):
    rng = np.random.default_rng(seed)
    node = rng.uniform(0, 3, (n, k))
    trans = rng.uniform(0, 3, (max(n - 1, 0), k, k))
    path, cost = viterbi(node, trans)

    def total(p):
        return node[np.arange(n), p].sum() + sum(trans[t, p[t], p[t + 1]] for t in range(n - 1))

    best = min(total(np.array(p)) for p in itertools.product(range(k), repeat=n))
    assert cost == pytest.approx(best) and total(path) == pytest.approx(best)


def test_repeat_cost_values():
    """R = 0 for database-consecutive segments, 2 for the same segment, 1 otherwise (Eq. 14)."""
    utterance = np.array([0, 0, 0, 1, 1])
    position = np.array([0, 1, 2, 0, 1])
    kin = np.zeros((5, 3, 3))
    h, r = transition_costs(
        np.array([1]), np.array([2, 1, 3, 0, 4]), kin, kin, utterance, position, np.ones(3), 1.0, 1.0
    )
    # from take 0's segment 1: its successor (R 0), itself (R 2), segments of the other take or earlier (R 1)
    np.testing.assert_array_equal(r[0], [0.0, 2.0, 1.0, 1.0, 1.0])
    assert h.shape == (1, 5)


def test_boundary_terms_on_the_common_clock_of_the_pair():
    """H with each candidate's resampling rate: Eq. 13 itself when both play at the same rate (whatever it is, so
    slowing a pair down earns nothing), and the velocity and acceleration steps the resampling creates otherwise."""
    rng = np.random.default_rng(3)
    kin = rng.normal(size=(6, 3, 3))
    utterance, position = np.arange(6), np.zeros(6, int)
    prev, nxt = np.array([[0, 1, 2]]), np.array([[3, 4, 5]])
    weights = np.array([0.5, 0.3, 0.2])
    plain, _ = transition_costs(prev, nxt, kin, kin, utterance, position, weights, 1.0, 1.0)
    for rate in (0.5, 1.0, 1.7):
        same, _ = transition_costs(
            prev, nxt, kin, kin, utterance, position, weights, 1.0, 1.0, np.full((1, 3), rate), np.full((1, 3), rate)
        )
        np.testing.assert_allclose(same, plain, rtol=1e-12)
    # the same motion on both sides, the second played twice as fast: no position step, the velocity step V
    # (V - 2V over sqrt(1 * 2) squared: V^2 / 2) and the acceleration step (A - 4A over 2, squared: 9 A^2 / 4)
    both = np.array([[0]])
    h, _ = transition_costs(
        both, both, kin, kin, utterance, position, weights, 1.0, 1.0, np.array([[1.0]]), np.array([[2.0]])
    )
    expected = weights[1] * (kin[0, 1] ** 2).sum() / 2 + weights[2] * 9 * (kin[0, 2] ** 2).sum() / 4
    assert h[0, 0, 0] == pytest.approx(expected)


def test_search_records_how_boundaries_were_compared(database, take_pitch):
    warped = search(database, take_pitch, holdout="take")
    plain = search(database, take_pitch, holdout="take", warp_boundaries=False)
    assert warped.meta["warp_boundaries"] and not plain.meta["warp_boundaries"]
    assert warped.meta["boundary_window"] == 0.1
    # the same node costs either way; only the transition term differs
    np.testing.assert_allclose(warped.arrays["candidate_cost"], plain.arrays["candidate_cost"])


def test_smoothness_terms_each_average_a_third():
    rng = np.random.default_rng(0)
    start = rng.normal(size=(30, 3, 3)) * np.array([1.0, 10.0, 100.0])[None, :, None]
    end = rng.normal(size=(30, 3, 3)) * np.array([1.0, 10.0, 100.0])[None, :, None] + 0.5
    w = smoothness_weights(start, end)
    for k in range(3):
        pairs = ((end[:, None, k, :] - start[None, :, k, :]) ** 2).sum(-1)
        assert w[k] * pairs.mean() == pytest.approx(1 / 3)


def table(contours, lengths, voiced=None, energy=None, onset_rate=None):
    contours = np.asarray(contours, dtype=float)
    n = len(contours)
    lengths = np.asarray(lengths, dtype=float)
    voiced = lengths * 0.6 if voiced is None else np.asarray(voiced, dtype=float)
    times = np.stack([np.zeros(n), voiced, lengths], axis=1)
    energy = np.zeros_like(contours) if energy is None else np.asarray(energy, dtype=float)
    onset_rate = np.zeros(n) if onset_rate is None else np.asarray(onset_rate, dtype=float)
    return SegmentTable(
        times,
        np.arange(n),
        np.zeros(n, int),
        np.ones(n, bool),
        contours,
        contour_geometry(contours, voiced),
        energy,
        onset_rate,
    )


UNIT_SCALES = SegmentScales(np.zeros(6), np.ones(6), 1.0, 1.0)


def test_segment_distance_terms():
    base = np.sin(np.linspace(0, 3, 20)) * 2
    test = table([base], [0.4])
    db = table([base, base + 1.5, base], [0.4, 0.4, 0.6])
    d = segment_distances(test, db, np.arange(3), SegmentWeights(0.05, 0.3), UNIT_SCALES)
    assert d.total[0, 0] == pytest.approx(0.0, abs=1e-9)
    assert d.pitch[0, 1] == pytest.approx(1.5)  # Eq. 10: RMS of a constant offset
    assert d.length[0, 2] == pytest.approx(0.5)  # Eq. 11: |0.6 - 0.4| / 0.4
    assert d.pitch[0, 2] == pytest.approx(0.0, abs=1e-9)
    # Eq. 12 weights
    expected = 0.05 * d.geometry[0, 1] + 0.3 * 1.5 + 0.65 * 0.0
    assert d.total[0, 1] == pytest.approx(expected)
    # G_d sees the offset in min and max
    assert d.geometry[0, 1] == pytest.approx(np.sqrt((1.5**2 * 2) / 6))


def test_loudness_and_rhythm_terms_beyond_the_paper():
    base = np.sin(np.linspace(0, 3, 20)) * 2
    loud = np.linspace(-6, 0, 20)
    test = table([base], [0.4], energy=[loud], onset_rate=[5.0])
    db = table([base, base], [0.4, 0.4], energy=[loud, loud + 3.0], onset_rate=[5.0, 2.0])
    scales = SegmentScales(np.zeros(6), np.ones(6), 2.0, 1.5)
    paper = segment_distances(test, db, np.arange(2), SegmentWeights(0.05, 0.3), scales)
    assert paper.total[0, 0] == paper.total[0, 1] == pytest.approx(0.0, abs=1e-9)  # e = o = 0: Eq. 12 only
    richer = segment_distances(test, db, np.arange(2), SegmentWeights(0.05, 0.3, e=0.5, o=0.2), scales)
    assert richer.loudness[0, 1] == pytest.approx(3.0 / 2.0) and richer.rhythm[0, 1] == pytest.approx(3.0 / 1.5)
    assert richer.total[0, 1] == pytest.approx(0.5 * 1.5 + 0.2 * 2.0) and richer.total[0, 0] == pytest.approx(0.0)


def test_contour_geometry_of_lines_and_parabolas():
    u = np.linspace(0, 0.5, 11)
    g = contour_geometry(np.stack([3 * u, 4 * (u - 0.25) ** 2]), np.array([0.5, 0.5]))
    names = ["min", "max", "range", "min_slope", "max_slope", "curvature"]
    line, parabola = dict(zip(names, g[0])), dict(zip(names, g[1]))
    assert line["min_slope"] == pytest.approx(3) and line["max_slope"] == pytest.approx(3)
    assert line["curvature"] == pytest.approx(0, abs=1e-9) and line["range"] == pytest.approx(1.5)
    assert parabola["curvature"] == pytest.approx(8.0)


def test_test_speaker_reference():
    reference = SpeakerReference(np.array([100.0, 150.0]), np.array([2.0, 3.0]))
    db = Database(None, None, None, None, None, ["a", "b"], [], [], ["ann", "bob"], reference)
    view = artifact(
        {"speaker_median": np.array([200.0]), "speaker_spread": np.array([4.0])}, {"labels": ["t"], "speakers": ["bob"]}
    )
    own, shift_own = reference_for_test(view, db, "own")
    same, shift_same = reference_for_test(view, db, "database")
    assert own.median[0] == 200.0 and own.spread[0] == 4.0 and shift_own[0] == 0.0
    assert same.median[0] == 150.0 and same.spread[0] == 3.0 and shift_same[0] == pytest.approx(12 * np.log2(200 / 150))
    stranger = artifact({"speaker_median": np.array([200.0])}, {"labels": ["t"], "speakers": ["carl"]})
    with pytest.raises(UserError, match="test_speaker: own"):
        reference_for_test(stranger, db, "database")
    alone = Database(
        None, None, None, None, None, ["a"], [], [], ["ann"], SpeakerReference(np.array([100.0]), np.ones(1))
    )
    unlabelled = artifact({"speaker_median": np.array([200.0])}, {"labels": ["t"]})
    assert reference_for_test(unlabelled, alone, "database")[0].median[0] == 100.0
    with pytest.raises(UserError, match="an unlabelled test take is not in the database"):  # not "None"
        reference_for_test(unlabelled, db, "database")


def test_auto_takes_the_databases_reference_where_it_knows_the_speaker_else_the_takes_own():
    """A database of one's own takes, a performer it never saw (the default, ``auto``): the run goes on with the
    take's own median, saying so (before: exit 2 asking for test_speaker: own)."""
    reference = SpeakerReference(np.array([100.0, 150.0]), np.array([2.0, 3.0]))
    db = Database(None, None, None, None, None, ["a", "b"], [], [], ["ann", "bob"], reference)
    view = artifact(
        {"speaker_median": np.array([200.0, 120.0]), "speaker_spread": np.array([4.0, 5.0])},
        {"labels": ["t", "u"], "speakers": ["bob", "carl"]},
    )
    auto, shift = reference_for_test(view, db, "auto")
    assert auto.median.tolist() == [150.0, 120.0] and auto.spread.tolist() == [3.0, 5.0]
    assert shift[0] == pytest.approx(12 * np.log2(200 / 150)) and shift[1] == 0.0
    assert Trellis.Params().test_speaker == "auto"
    (warning,) = unknown_speakers_warning(view, db, "auto")
    assert "['u']" in warning and "own median" in warning
    assert unknown_speakers_warning(view, db, "own") == []


def test_an_utterance_in_the_database_finds_itself(phrases, plain_database, take_pitch):
    run = search(plain_database, take_pitch)
    db_labels = run.meta["db_labels"]
    for u, phrase in enumerate(phrases[:8]):
        rows = run.arrays["segment_utterance"] == u
        chosen = run.arrays["chosen"][rows]
        sequences = run.arrays["db_segment_sequence"][chosen]
        assert {db_labels[s] for s in sequences} == {phrase.label}
        np.testing.assert_array_equal(run.arrays["db_segment_position"][chosen], np.arange(rows.sum()))
        np.testing.assert_allclose(run.arrays["node_cost"][rows], 0.0, atol=1e-6)
        np.testing.assert_allclose(run.arrays["transition_cost"][rows], 0.0, atol=1e-6)
    assert run.metrics["consecutive_fraction"] == 1.0 and run.metrics["total_cost"] < 1e-4


def test_leave_one_out_never_uses_the_held_out_recording(phrases, database, take_pitch):
    run = search(database, take_pitch, holdout="take")
    db_labels = run.meta["db_labels"]
    for u, phrase in enumerate(phrases[:8]):
        rows = run.arrays["segment_utterance"] == u
        used = {db_labels[s] for s in run.arrays["db_segment_sequence"][run.arrays["candidates"][rows].ravel()]}
        assert phrase.label not in used and f"{phrase.label}~mirror" not in used
        assert run.meta["excluded"][u] == [phrase.label, f"{phrase.label}~mirror"]
        excluded = [db_labels.index(x) for x in run.meta["excluded"][u]]
        assert np.isnan(run.arrays["phrase_distance"][u, excluded]).all()
        assert not run.arrays["phrase_selected"][u, excluded].any()


def test_speaker_motion_same_keeps_to_the_test_speakers_own_motion(phrases):
    """speaker_motion: same searches only the test speaker's own takes (the held-out one excluded) when the database
    holds some, and every speaker's when it holds none; any (the paper) searches every speaker's."""
    ann = tracking_artifact(phrases[:12], speaker="ann")
    headdb = run_stage(
        TrackedHeadDb, {}, {"tracks": ann, "more_tracks": tracking_artifact(phrases[12:], speaker="ben")}
    )
    db = (headdb, run_stage(Pitch, {}, {"source": headdb}))
    speaker_of = {label: ("ann" if int(label.split("_")[0][1:]) < 12 else "ben") for label in headdb.meta["labels"]}

    def used_speakers(test, mode):
        run = search(
            db, run_stage(Pitch, {}, {"source": test}), holdout="take", speaker_motion=mode, test_speaker="own"
        )
        labels = run.meta["db_labels"]
        return {speaker_of[labels[s]] for s in run.arrays["db_segment_sequence"][run.arrays["candidates"].ravel()]}

    assert used_speakers(tracking_artifact(phrases[:4], speaker="ann"), "same") == {"ann"}
    assert used_speakers(tracking_artifact(phrases[12:16], speaker="ben"), "same") == {"ben"}
    assert used_speakers(tracking_artifact(phrases[:4], speaker="ann"), "any") == {"ann", "ben"}
    assert used_speakers(tracking_artifact(phrases[:4], speaker="cid"), "same") == {"ann", "ben"}


def test_same_performance_leaves_out_a_copy_of_the_held_out_take(phrases):
    """A second recording of the held-out take's performance (here an exact copy under another label) is the
    search's best match under holdout 'take'; same_performance groups the two, and the copy (mirror included) is
    left out too, and the two takes' shared sound makes the search warn until they are grouped. Pieces of a take
    and its mirror belong to the take (take_of); an unknown label is an error."""
    import dataclasses

    from stages.head.copies import take_of

    copy = dataclasses.replace(phrases[0], label="copy")
    headdb = run_stage(TrackedHeadDb, {}, {"tracks": tracking_artifact([*phrases[:8], copy])})
    db = (headdb, run_stage(Pitch, {}, {"source": headdb}))
    test = run_stage(Pitch, {}, {"source": tracking_artifact(phrases[:1])})

    def used(**params):
        run = search(db, test, holdout="take", **params)
        return {
            take_of(run.meta["db_labels"][s])
            for s in run.arrays["db_segment_sequence"][run.arrays["candidates"].ravel()]
        }

    assert "copy" in used()
    # the copy's sound gives it away: the search warns unless the two are grouped
    apart = search(db, test, holdout="take").warnings
    assert len(apart) == 1 and f"'{phrases[0].label}' and 'copy' share their sound" in apart[0]
    assert not search(db, test, holdout="take", same_performance=[[phrases[0].label, "copy"]]).warnings
    grouped = used(same_performance=[[phrases[0].label, "copy"]])
    assert "copy" not in grouped and phrases[0].label not in grouped and grouped
    assert take_of("clip#3~mirror") == take_of("clip#3") == take_of("clip~mirror") == "clip"
    with pytest.raises(UserError, match="same_performance") as err:
        search(db, test, holdout="take", same_performance=[[phrases[0].label, "nobody"]])
    assert err.value.field == "params.same_performance"


def test_phrase_stage_prefers_the_same_speaking_style(phrases, database, take_pitch):
    run = search(database, take_pitch, holdout="take", top_m=6)
    styles = [phrases[int(label.split("_")[0][1:])].style for label in run.meta["db_labels"]]
    hits = []
    for u, phrase in enumerate(phrases[:8]):
        order = np.argsort(np.nan_to_num(run.arrays["phrase_distance"][u], nan=np.inf))[:6]
        hits.append(np.mean([styles[i] == phrase.style for i in order]))
    assert np.mean(hits) > 0.6  # chance is 0.25 with four styles


def test_candidates_are_the_k_best_and_sorted(database, take_pitch):
    run = search(database, take_pitch, k=7, holdout="take")
    cost = run.arrays["candidate_cost"]
    assert cost.shape[1] == 7 and np.all(np.diff(cost, axis=1) >= 0)
    np.testing.assert_array_equal(
        run.arrays["candidates"][np.arange(len(cost)), run.arrays["chosen_rank"]], run.arrays["chosen"]
    )
    np.testing.assert_allclose(run.arrays["node_cost"], cost[np.arange(len(cost)), run.arrays["chosen_rank"]])


def test_sub_sentences_are_searched_separately(database, take_pitch):
    run = search(database, take_pitch, holdout="take")
    sub = run.arrays["subsentence_start"]
    assert sub.sum() >= 16  # two or three sentences per phrase
    np.testing.assert_array_equal(run.arrays["transition_cost"][sub], 0.0)
    joins = ~sub
    np.testing.assert_allclose(
        run.arrays["transition_cost"][joins],
        run.arrays["transition_smoothness"][joins] + run.arrays["transition_repeat"][joins],
    )
    # the search beats taking every segment's best match, in total cost per sub-sentence
    greedy = run_stage(
        Trellis,
        {"holdout": "take", "w1": 0.0, "w2": 0.0},
        {"database": database[0], "database_pitch": database[1], "test_pitch": take_pitch},
    )
    assert greedy.arrays["chosen_rank"].max() == 0
    assert run.metrics["mean_transition_cost"] < 0.8 * np.mean(
        _transition_costs_of(run, greedy.arrays["chosen"], database)
    )


def _transition_costs_of(run, chosen, database):
    """C of a given path under the run's weights (for comparing paths)."""
    from stages.head.search import build_database

    db, _ = build_database(database[0].view(), database[1].view(), unit="semitones", length=None, window=0.1)
    sub = run.arrays["subsentence_start"]
    seg = run.arrays["segments"]
    scale = (db.segments.length[chosen] / (seg[:, 2] - seg[:, 0]))[None]
    h, r = transition_costs(
        chosen[:-1][None],
        chosen[1:][None],
        db.end,
        db.start,
        db.segments.utterance,
        db.segments.position,
        db.weights,
        1.0,
        1.0,
        scale[:, :-1],
        scale[:, 1:],
    )
    steps = np.arange(len(chosen) - 1)
    total = h[0][steps, steps] + r[0][steps, steps]
    return total[~sub[1:]]


def test_top_m_grows_until_it_holds_k_segments(database, take_pitch):
    run = search(database, take_pitch, top_m=1, k=40, holdout="take")
    assert all(m > 1 for m in run.meta["phrases_searched"])
    assert run.arrays["candidates"].shape[1] == 40


def test_hz_unit_and_own_reference_run(database, take_pitch):
    hz = search(database, take_pitch, unit="hz", holdout="take")
    own = search(database, take_pitch, test_speaker="own", holdout="take")
    assert hz.meta["unit"] == "hz" and own.meta["test_speaker"] == "own"
    assert len(hz.arrays["chosen"]) == len(own.arrays["chosen"])


def test_fewer_segments_than_k_is_an_error(database, take_pitch):
    with pytest.raises(UserError) as err:
        search(database, take_pitch, k=100_000)
    assert "fewer than k" in str(err.value) and err.value.field == "params.k"


def test_exclusions_by_label(database, take_pitch):
    run = search(database, take_pitch, exclude_labels=[database[0].meta["labels"][0]])
    assert all(database[0].meta["labels"][0] in ex for ex in run.meta["excluded"])
    with pytest.raises(UserError, match="exclude_labels"):
        search(database, take_pitch, exclude_labels=["nobody"])


def test_database_pitch_must_match_the_database(database, plain_database, take_pitch):
    with pytest.raises(UserError, match="database_pitch"):
        run_stage(Trellis, {}, {"database": database[0], "database_pitch": plain_database[1], "test_pitch": take_pitch})


@pytest.mark.parametrize(
    "params, field",
    [
        ({"b": 0.8, "c": 0.4}, "c"),
        ({"k": 0}, "k"),
        ({"top_m": 0}, "top_m"),
        ({"w1": -1}, "w1"),
        ({"holdout": "x"}, "holdout"),
    ],
)
def test_bad_settings_are_rejected_by_the_params(params, field):
    with pytest.raises(ValidationError) as err:
        Trellis.Params(**params)
    assert err.value.errors()[0]["loc"] == (field,)


def test_trellis_figure_renders(database, take_pitch):
    run = search(database, take_pitch, holdout="take")
    fig = Trellis.figures["trellis"](run.view(), {})
    assert fig.axes[0].get_xlabel() == "test segment"


def test_a_database_without_voice_is_an_error(take_pitch):
    quiet = (np.random.default_rng(0).standard_normal(32000) * 1e-4).astype(np.float32)
    silent = artifact(
        {
            "rotation": np.tile([1.0, 0, 0, 0], (60, 1)),
            "translation": np.zeros((60, 3)),
            "time": np.arange(60) / 30.0,
            "sequence": np.zeros(60, np.int32),
            "audio": quiet,
            "audio_bounds": np.array([[0, 32000]]),
        },
        {"labels": ["quiet"], "sources": ["quiet.wav"], "fps": [30.0], "audio_rate": 16000},
    )
    headdb = run_stage(TrackedHeadDb, {"speaker": "ann"}, {"tracks": silent})
    db_pitch = run_stage(Pitch, {}, {"source": headdb})
    with pytest.raises(UserError, match="no voiced speech in any take") as err:
        run_stage(Trellis, {}, {"database": headdb, "database_pitch": db_pitch, "test_pitch": take_pitch})
    assert err.value.field == "inputs.database_pitch"


def test_a_database_shorter_than_one_phrase_is_an_error(phrases, take_pitch):
    short = tracking_artifact([phrases[0]])
    headdb = run_stage(TrackedHeadDb, {"mirror": False}, {"tracks": short})
    db_pitch = run_stage(Pitch, {}, {"source": headdb})
    segments = db_pitch.metrics["segments"]
    with pytest.raises(UserError, match=f"has {segments} segments") as err:
        run_stage(
            Trellis, {"k": segments + 1}, {"database": headdb, "database_pitch": db_pitch, "test_pitch": take_pitch}
        )
    assert err.value.field == "params.k"
