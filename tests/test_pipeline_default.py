"""The default pipeline.yaml on the embedded data: runs end to end, reruns nothing, exports what animators open."""

import csv

import numpy as np

import msflow


def test_default_pipeline_runs_every_stage(default_run):
    proj, result = default_run
    spec = (proj / "pipeline.yaml").read_text()
    assert result.ok
    assert set(result.executed) == set(result.states)
    for stage in (
        "track_train",
        "track_test",
        "aam",
        "bilinear",
        "edit",
        "character",
        "keyshapes",
        "keymorphs",
        "blend",
        "headdb",
        "pitch_db",
        "pitch_test",
        "trellis",
        "motion_blend",
        "export",
    ):
        assert f"  {stage}:" in spec and result.states[stage].state == "ran"


def test_the_default_run_ends_with_how_it_read_the_take(default_run):
    """pipeline.yaml's summary: what `msflow run` prints last, every entry a metric the run gave."""
    from msflow.summary import summary_entries

    proj, result = default_run
    _, problems = summary_entries(list(result.session.pipeline.summary), result.record["stages"])
    summary = result.summary
    assert problems == [] and {"edit.fraction_neutral", "blend.mean_alpha_happy", "export.duration_s"} <= set(summary)
    assert abs(sum(v for k, v in summary.items() if k.startswith("edit.fraction_")) - 1.0) < 1e-9


def test_default_pipeline_rerun_is_a_no_op(default_run):
    proj, first = default_run
    again = msflow.run(proj / "pipeline.yaml")
    assert again.executed == []
    assert {n: again.key(n) for n in again.states} == {n: first.key(n) for n in first.states}


def test_default_pipeline_publishes_animation_files(default_run):
    proj, result = default_run
    out = proj / "out"
    glb = (out / "sad_as_happy_to_disgust.glb").read_bytes()
    assert glb[:4] == b"glTF"
    rows = list(csv.reader((out / "sad_as_happy_to_disgust_live_link.csv").open()))
    assert rows[0][:2] == ["Timecode", "BlendShapeCount"] and len(rows[0]) == 2 + 61
    weights = result.load("blend.weights")
    assert len(rows) - 1 == weights.shape[0] == result.load("track_test.landmarks").shape[0]
    assert (out / "sad_head_motion.bvh").read_text().startswith("HIERARCHY")
    assert (out / "sad_as_happy_to_disgust_preview.mp4").stat().st_size > 10_000
    assert np.all((weights >= 0) & (weights <= 1))


def test_show_names_a_file_output_and_how_to_write_it(default_run):
    """Not its bytes printed as an array of numbers."""
    from conftest import run_cli

    proj, _ = default_run
    shown = run_cli(proj, "show", "export.animation")
    assert shown.returncode == 0, shown.stderr
    assert "animation          file .glb" in shown.stdout and "[103 108" not in shown.stdout, shown.stdout
    assert "a .glb file: msflow export export.animation FILE.glb writes it" in shown.stdout


def test_default_run_swings_the_mood_from_happy_to_disgust(default_run):
    """The paper's headline: the unseen take re-expressed with alpha keyframed across expressions."""
    _, result = default_run
    blend = result.artifact("blend")
    expressions, names = blend.meta["expressions"], blend.meta["target_names"]
    alpha, weights = blend["alpha"], blend["weights"]
    assert alpha[0, expressions.index("happy")] == 1.0 and alpha[-1, expressions.index("disgust")] == 1.0
    third = len(weights) // 3

    def mean(stem, rows):
        return weights[rows][:, [names.index(f"{stem}_L"), names.index(f"{stem}_R")]].mean()

    first, last = slice(0, third), slice(-third, None)
    assert mean("mouthSmile", first) > 2 * mean("mouthSmile", last)
    assert mean("browDown", last) > 2 * mean("browDown", first)


def test_the_mood_vars_set_the_swing_and_the_published_names_together(default_run):
    """A mood changed on the command line renames the files that hold it: -S blend.alpha in the README's
    examples kept publishing an all-happy take as sad_as_happy_to_disgust.*. Checked on the loaded pipeline
    (no stage runs): the keyframes and the names follow the same two variables."""
    from msflow.spec import load_pipeline

    proj, _ = default_run
    pipeline = load_pipeline(proj / "pipeline.yaml", ["vars.mood_from=neutral"])
    keyframes = pipeline.stages["blend"].params["alpha"]["keyframes"]
    assert [list(frame) for frame in keyframes.values()] == [["neutral"], ["disgust"]]
    published = {ref: path.rsplit("/", 1)[-1] for ref, path in pipeline.publish.items()}
    assert published["export.animation"] == "sad_as_neutral_to_disgust.glb"
    assert published["export.live_link"] == "sad_as_neutral_to_disgust_live_link.csv"
    assert published["export.preview"] == "sad_as_neutral_to_disgust_preview.mp4"
    default = load_pipeline(proj / "pipeline.yaml")
    assert default.publish["export.animation"].endswith("/out/sad_as_happy_to_disgust.glb")


def test_default_run_blinks_with_the_performer(default_run):
    """The default tracking gives the eyelid aperture and gaze (Face Landmarker v2 eye pass), and the blend closes
    the character's eyes where the performer blinks (the sad take, closed at frames 6-7, opening at 8)."""
    _, result = default_run
    tracks, blend = result.artifact("track_test"), result.artifact("blend")
    assert "eye_aperture" in tracks and "gaze" in tracks and "gaze" in blend
    assert blend.meta["eyes"]["blink_source"] == "tracking eye_aperture"
    names, weights = blend.meta["target_names"], blend["weights"]
    blink = weights[:, [names.index("eyeBlink_L"), names.index("eyeBlink_R")]].mean(axis=1)
    assert blink[6:8].min() > 0.5 and blink[:4].max() < 0.2 and blink[20:].max() < 0.5
    # the character's eyes open by the fraction the performer's are, blink and gaze morphs together (the eyes drop
    # as the lids cover the irises, and ICT's eyeLookDown lowers the lids too)
    from stages.retarget.blend import character_landmarks
    from stages.retarget.eyes import eye_aperture_2d

    rest, deltas = character_landmarks(result.artifact("character"))
    shapes = rest[None] + np.einsum("fm,mpc->fpc", np.asarray(weights, np.float64), deltas)
    opened = eye_aperture_2d(shapes) / eye_aperture_2d(rest[None])
    performer = np.asarray(tracks["eye_aperture"]) / np.quantile(tracks["eye_aperture"], 0.9, axis=0)
    assert opened[6:8].max() < 0.4 and np.abs(opened[6:8] - performer[6:8]).max() < 0.05
    assert opened[:4].min() > 0.9 and opened[20:].min() > 0.7
