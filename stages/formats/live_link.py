"""Live Link Face CSV and the mapping from a character's morph targets to Apple ARKit's 52 blendshapes.

The file is what Epic's Live Link Face app records: ``Timecode, BlendShapeCount``, the 52 ARKit blendshapes in
PascalCase (``ARKIT_NAMES``, the app's column order), then the head and eye angles (``ANGLE_COLUMNS``): 61 values
per row. Columns are written in that order under that header, so readers that go by position and readers that go
by name both find them.

**The ARKit mapping** (public, imported read-only by the retargeting evaluation). Each character morph gets a
*destination*: a dict ``{ARKit column: factor}``; an ARKit column is the sum of its sources' weights times their
factors, clipped to [0, 1] (ARKit weights are in [0, 1])::

    arkit[t, c] = clip( sum_m  w[t, m] * factor[m, c],  0, 1 )

Destinations are found in this order (``arkit_mapping``):

1. ``aliases``: the user's own entries (``Export`` param ``arkit_aliases``), for a character with other names;
2. ``ARKIT_TABLE``: the morphs of ICT FaceKit (the embedded character) that have no ARKit namesake;
3. namesakes: ``eyeBlink_L``, ``eyeBlinkLeft``, ``EyeBlink.L`` ... -> ``EyeBlinkLeft`` (``arkit_key``); a
   left/right half of a whole ARKit shape (ICT ``browInnerUp_L``) -> the whole column with factor 0.5 (the mean
   of the halves: the weight that, applied to both halves, reproduces their total displacement when they are
   mirror images); a whole shape of a sided ARKit pair (``mouthSmile``) -> both sides with factor 1;
4. with the character's deltas: a morph still without a destination is projected onto the character's
   ARKit-named morphs (``fit_destination``: non-negative least squares of its displacement, factors below 0.2
   dropped and the rest refitted); a projection that explains less than half of the displacement is no
   destination;
5. ``NO_ARKIT_COUNTERPART``: morphs ARKit has nothing for (pupil dilation): no destination.

A morph that moves but has no destination is *dropped* from the CSV (the GLB keeps it); an ARKit column with no
source is written as 0. ``ArkitMapping`` lists both, and the export stage turns them into stage warnings.

Timecodes: ``HH:MM:SS:FF.fff``, frames counted at the nominal (rounded) rate with the exact sub-frame remainder
after the dot, so every row's time is exact: at 29.97 fps (30000/1001) row 30 is at 1.001 s = ``00:00:01:00.030``
(not ``00:00:01:00.000``, which is 1.000 s).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

#: the 52 ARKit blendshapes in the column order of Live Link Face CSV files
ARKIT_NAMES = [
    "EyeBlinkLeft",
    "EyeLookDownLeft",
    "EyeLookInLeft",
    "EyeLookOutLeft",
    "EyeLookUpLeft",
    "EyeSquintLeft",
    "EyeWideLeft",
    "EyeBlinkRight",
    "EyeLookDownRight",
    "EyeLookInRight",
    "EyeLookOutRight",
    "EyeLookUpRight",
    "EyeSquintRight",
    "EyeWideRight",
    "JawForward",
    "JawRight",
    "JawLeft",
    "JawOpen",
    "MouthClose",
    "MouthFunnel",
    "MouthPucker",
    "MouthRight",
    "MouthLeft",
    "MouthSmileLeft",
    "MouthSmileRight",
    "MouthFrownLeft",
    "MouthFrownRight",
    "MouthDimpleLeft",
    "MouthDimpleRight",
    "MouthStretchLeft",
    "MouthStretchRight",
    "MouthRollLower",
    "MouthRollUpper",
    "MouthShrugLower",
    "MouthShrugUpper",
    "MouthPressLeft",
    "MouthPressRight",
    "MouthLowerDownLeft",
    "MouthLowerDownRight",
    "MouthUpperUpLeft",
    "MouthUpperUpRight",
    "BrowDownLeft",
    "BrowDownRight",
    "BrowInnerUp",
    "BrowOuterUpLeft",
    "BrowOuterUpRight",
    "CheekPuff",
    "CheekSquintLeft",
    "CheekSquintRight",
    "NoseSneerLeft",
    "NoseSneerRight",
    "TongueOut",
]
#: head, then left and right eye angles, after the blendshapes
ANGLE_COLUMNS = [
    "HeadYaw",
    "HeadPitch",
    "HeadRoll",
    "LeftEyeYaw",
    "LeftEyePitch",
    "LeftEyeRoll",
    "RightEyeYaw",
    "RightEyePitch",
    "RightEyeRoll",
]
LIVE_LINK_COUNT = len(ARKIT_NAMES) + len(ANGLE_COLUMNS)  # 61

#: ICT FaceKit morphs without an ARKit namesake -> {ARKit column: factor}. The factors are ``fit_destination``
#: of the morph's displacement on the ICT head (tests/test_export.py recomputes them): the raised cheek (FACS
#: AU6) is 0.92 of ARKit's cheek squint plus 0.34 of its eye squint (the lower lid rises with the cheek).
ARKIT_TABLE: dict[str, dict[str, float]] = {
    "cheekRaiser_L": {"CheekSquintLeft": 0.92, "EyeSquintLeft": 0.34},
    "cheekRaiser_R": {"CheekSquintRight": 0.92, "EyeSquintRight": 0.34},
}
#: morphs ARKit has no blendshape for: they stay in the GLB and are dropped from the CSV
NO_ARKIT_COUNTERPART = frozenset({"PupilDilate_L", "PupilDilate_R", "pupilDilate_L", "pupilDilate_R"})
#: ARKit columns no input of this pipeline can drive (the trackers see no tongue): not reported as missing
UNTRACKED_COLUMNS = frozenset({"TongueOut"})
#: a fitted destination must explain at least this share of the morph's displacement (1 - relative residual)
MIN_FIT_EXPLAINED = 0.5
#: fitted factors below this are dropped before the refit (small cross-talk terms that mostly cancel)
MIN_FIT_FACTOR = 0.2

#: characters that do not change what a morph name means: Jaw_Open, jaw-open, jaw.open and jawOpen are one morph
NAME_SEPARATORS = frozenset("_-. ")


_SIDE_WORDS = (("left", "L"), ("right", "R"), ("l", "L"), ("r", "R"))
_COLUMN_BY_KEY = {name.lower(): name for name in ARKIT_NAMES}


def split_side(name: str) -> tuple[str, str]:
    """(stem, side) of a morph name, side "L", "R" or "": a side word or letter after a separator, in any case
    (``mouthSmile_L``, ``mouthsmile.l``, ``Mouth Smile Left``), or the words left / right without one
    (``eyeBlinkLeft``, ``eyeblinkleft``; also ``mouthLeft``, whose mirror is ``mouthRight``)."""
    stem = name.strip()
    lower = stem.lower()
    for word, side in _SIDE_WORDS:
        cut = len(stem) - len(word)
        if cut > 1 and lower.endswith(word) and stem[cut - 1] in NAME_SEPARATORS:
            return stem[: cut - 1], side
    for word, side in (("left", "L"), ("right", "R")):  # a whole word needs no separator
        if lower.endswith(word) and len(stem) > len(word):
            return stem[: -len(word)], side
    return stem, ""


def arkit_key(name: str) -> str:
    """A morph name in Live Link Face spelling: ICT/ARKit ``eyeBlink_L`` or ``eyeBlinkLeft`` -> ``EyeBlinkLeft``."""
    stem, side = split_side(name)
    key = stem + {"L": "Left", "R": "Right", "": ""}[side]
    return key[:1].upper() + key[1:]


def morph_key(name: str) -> str:
    """A morph name (or fnmatch pattern) as it is compared: lower case, separators left out (``Mouth_Smile_L`` ->
    ``mouthsmilel``, as ``mouthSmile_L``). The retargeting picks morphs by it (``stages.retarget.regions``)."""
    return "".join(ch for ch in name.lower() if ch not in NAME_SEPARATORS)


def name_key(name: str) -> str:
    """A morph name as the mapping compares it: ``morph_key`` with the sides spelt ARKit's way (``mouthSmile_L``,
    ``Mouth_Smile_L``, ``mouthSmile.L`` and ``mouthSmileLeft`` are all ``mouthsmileleft``)."""
    return morph_key(arkit_key(name))


_TABLE_BY_KEY = {name_key(name): dest for name, dest in ARKIT_TABLE.items()}
_NO_COUNTERPART_KEYS = frozenset(name_key(name) for name in NO_ARKIT_COUNTERPART)


def namesake_destination(name: str) -> dict[str, float]:
    """The ARKit column(s) a morph is named after (rule 3 of the module docstring); {} when none."""
    key = name_key(name)
    if key in _COLUMN_BY_KEY:
        return {_COLUMN_BY_KEY[key]: 1.0}
    for side in ("left", "right"):
        whole = key[: -len(side)]
        if key.endswith(side) and whole in _COLUMN_BY_KEY:
            return {_COLUMN_BY_KEY[whole]: 0.5}
    sided = [_COLUMN_BY_KEY[key + side] for side in ("left", "right") if key + side in _COLUMN_BY_KEY]
    return dict.fromkeys(sided, 1.0) if len(sided) == 2 else {}


def fit_destination(delta: np.ndarray, basis: np.ndarray, columns: list[str]) -> tuple[dict[str, float], float]:
    """The ARKit columns whose morphs best rebuild a morph's displacement, and the share they explain.

    Non-negative least squares ``min_f |delta - sum_k f_k basis_k|`` over the character's ARKit-named morphs
    (``basis`` (K, V, 3), ``columns`` their K destinations), factors below MIN_FIT_FACTOR dropped and the rest
    refitted, so small cancelling cross-talk terms do not become channels. Returns ({column: factor}, explained)
    with explained = 1 - |residual| / |delta|.
    """
    from scipy.optimize import nnls

    target = np.asarray(delta, dtype=np.float64).reshape(-1)
    norm = float(np.linalg.norm(target))
    if norm == 0.0 or len(columns) == 0:
        return {}, 0.0
    matrix = np.asarray(basis, dtype=np.float64).reshape(len(columns), -1).T
    factors, _ = nnls(matrix, target)
    keep = np.flatnonzero(factors >= MIN_FIT_FACTOR)
    if not len(keep):
        return {}, 0.0
    factors, residual = nnls(matrix[:, keep], target)
    out: dict[str, float] = {}
    for k, f in zip(keep, factors):
        out[columns[k]] = out.get(columns[k], 0.0) + round(float(f), 2)
    return out, 1.0 - residual / norm


@dataclass
class ArkitMapping:
    """Where each character morph goes in the 52 ARKit columns (see the module docstring).

    ``destinations[morph]`` is ``{column: factor}`` ({} for none); ``rule[morph]`` says which rule gave it
    ("alias", "table", "namesake", "fitted", "none"); ``matrix`` is the (morphs, 52) factor matrix.
    """

    target_names: list[str]
    destinations: dict[str, dict[str, float]]
    rule: dict[str, str]
    explained: dict[str, float] = field(default_factory=dict)  # share of displacement, fitted morphs only

    @property
    def matrix(self) -> np.ndarray:
        out = np.zeros((len(self.target_names), len(ARKIT_NAMES)))
        for m, name in enumerate(self.target_names):
            for column, factor in self.destinations[name].items():
                out[m, ARKIT_NAMES.index(column)] += factor
        return out

    @property
    def sources(self) -> dict[str, list[str]]:
        """ARKit column -> the morphs feeding it (columns without a source left out)."""
        out: dict[str, list[str]] = {}
        for name in self.target_names:
            for column in self.destinations[name]:
                out.setdefault(column, []).append(name)
        return {c: out[c] for c in ARKIT_NAMES if c in out}

    @property
    def missing_columns(self) -> list[str]:
        """ARKit columns no morph feeds (written as 0)."""
        sources = self.sources
        return [c for c in ARKIT_NAMES if c not in sources]

    @property
    def unmapped(self) -> list[str]:
        """Morphs without a destination."""
        return [n for n in self.target_names if not self.destinations[n]]

    def weights(self, weights: np.ndarray) -> np.ndarray:
        """(frames, 52) ARKit weights in [0, 1] from (frames, morphs) character weights."""
        return np.clip(np.asarray(weights, dtype=np.float64) @ self.matrix, 0.0, 1.0)

    def dropped(self, weights: np.ndarray, threshold: float = 1e-3) -> list[str]:
        """Morphs that move (some |weight| above ``threshold``) but have no destination."""
        peak = np.abs(np.asarray(weights)).max(axis=0) if len(weights) else np.zeros(len(self.target_names))
        return [n for n, p in zip(self.target_names, peak) if p > threshold and not self.destinations[n]]

    def table(self) -> list[tuple[str, str, str]]:
        """Rows (morph, "Column x factor + ...", rule) for documentation."""
        rows = []
        for name in self.target_names:
            dest = " + ".join(f"{c} x {f:g}" for c, f in self.destinations[name].items()) or "(none)"
            rows.append((name, dest, self.rule[name]))
        return rows


def check_aliases(aliases: dict[str, dict[str, float]]) -> dict[str, dict[str, float]]:
    """Validate user aliases: known ARKit column names, finite factors. Raises ValueError naming the entry."""
    for morph, dest in aliases.items():
        for column, factor in dest.items():
            if column not in _COLUMN_BY_KEY.values():
                key = _COLUMN_BY_KEY.get(arkit_key(column).lower())
                hint = f" (did you mean {key!r}?)" if key else ""
                raise ValueError(f"{morph}: {column!r} is not one of the 52 ARKit columns{hint}")
            if not np.isfinite(factor):
                raise ValueError(f"{morph}: factor for {column} is not finite")
    return aliases


def arkit_mapping(
    target_names: list[str],
    deltas: np.ndarray | None = None,
    aliases: dict[str, dict[str, float]] | None = None,
) -> ArkitMapping:
    """The destination of every morph of a character (rules 1-5 of the module docstring).

    Parameters
    ----------
    target_names : the character's morph names, in its target order.
    deltas : optional (morphs, V, 3) displacements, to fit destinations of morphs rules 1-3 do not place.
    aliases : optional user entries ``{morph: {ARKit column: factor}}`` that take precedence.
    """
    aliases = check_aliases(dict(aliases or {}))
    destinations: dict[str, dict[str, float]] = {}
    rule: dict[str, str] = {}
    for name in target_names:
        for label, dest in (("alias", aliases.get(name)), ("table", _TABLE_BY_KEY.get(name_key(name)))):
            if dest is not None:
                destinations[name], rule[name] = dict(dest), label
                break
        else:
            dest = {} if name_key(name) in _NO_COUNTERPART_KEYS else namesake_destination(name)
            destinations[name], rule[name] = dest, "namesake" if dest else "none"
    mapping = ArkitMapping(list(target_names), destinations, rule)
    if deltas is not None:
        fit_missing_destinations(mapping, np.asarray(deltas))
    return mapping


def fit_missing_destinations(mapping: ArkitMapping, deltas: np.ndarray) -> None:
    """Rule 4: project each morph still without a destination onto the character's ARKit namesakes."""
    basis_ids = [m for m, n in enumerate(mapping.target_names) if mapping.rule[n] == "namesake"]
    columns, basis = [], []
    for m in basis_ids:  # a half-shape (factor 0.5) rebuilds its column with twice the weight: use its unit
        for column, factor in mapping.destinations[mapping.target_names[m]].items():
            columns.append(column)
            basis.append(deltas[m] / factor)
    for m, name in enumerate(mapping.target_names):
        if mapping.rule[name] != "none" or name_key(name) in _NO_COUNTERPART_KEYS:
            continue
        dest, explained = fit_destination(deltas[m], np.asarray(basis), columns)
        if dest and explained >= MIN_FIT_EXPLAINED:
            mapping.destinations[name], mapping.rule[name] = dest, "fitted"
            mapping.explained[name] = round(explained, 3)


def arkit_weights(
    weights: np.ndarray,
    target_names: list[str],
    deltas: np.ndarray | None = None,
    aliases: dict[str, dict[str, float]] | None = None,
) -> tuple[np.ndarray, ArkitMapping]:
    """(frames, 52) ARKit blendshape weights in Live Link Face column order from a character's morph weights,
    and the mapping used (``arkit_mapping``)."""
    mapping = arkit_mapping(target_names, deltas, aliases)
    return mapping.weights(weights), mapping


# ------------------------------------------------------------------------------------------------ the CSV


def nominal_rate(fps: float) -> int:
    """The timecode rate of a frame rate: 30 for 29.97, 24 for 23.976, 60 for 59.94."""
    return max(int(round(fps)), 1)


def exact_rate(fps: float) -> Fraction:
    """The frame rate as a fraction: an NTSC rate (k * 1000/1001, e.g. 29.97 or a measured 29.9697) within
    1e-4 relative is taken as exactly that, any other as the nearest fraction with a denominator up to 1001."""
    k = round(fps * 1.001)
    ntsc = Fraction(k * 1000, 1001)
    if k > 0 and abs(fps - float(ntsc)) <= 1e-4 * fps:
        return ntsc
    return Fraction(fps).limit_denominator(1001)


def format_timecode(frame: np.ndarray, fps: float) -> list[str]:
    """Live Link Face timecodes ``HH:MM:SS:FF.fff`` of frames at ``fps``: the exact time i / fps in frames of
    the nominal rate (``nominal_rate``), the sub-frame remainder in thousandths after the dot.

    At an integer rate every label ends in .000; at 29.97 fps (30000/1001) frame 30 is at 1.001 s, which is
    ``00:00:01:00.030``. The rate is ``exact_rate(fps)``, so 29.97 and 30000/1001 give the same labels.
    """
    rate = exact_rate(fps)
    nominal = nominal_rate(fps)
    index = np.asarray(frame, dtype=np.int64)
    # thousandths of a nominal frame since 0, rounded to nearest: i * nominal * 1000 / rate in integers
    num, den = nominal * 1000 * rate.denominator, rate.numerator
    milli = (2 * index * num + den) // (2 * den)
    whole, sub = np.divmod(milli, 1000)
    seconds, ff = np.divmod(whole, nominal)
    minutes, ss = np.divmod(seconds, 60)
    hh, mm = np.divmod(minutes, 60)
    return [f"{h:02d}:{m:02d}:{s:02d}:{f:02d}.{u:03d}" for h, m, s, f, u in zip(hh, mm, ss, ff, sub)]


def timecode_seconds(code: str, fps: float) -> float:
    """The time a ``format_timecode`` label stands for (seconds), at the nominal rate of ``fps``."""
    hh, mm, ss, rest = code.split(":")
    return int(hh) * 3600 + int(mm) * 60 + int(ss) + float(rest) / nominal_rate(fps)


def live_link_csv(
    arkit: np.ndarray, fps: float, head_angles: np.ndarray | None = None, eye_angles: np.ndarray | None = None
) -> bytes:
    """The CSV text: header, then one row per frame with 61 values.

    ``head_angles`` (frames, 3) yaw, pitch, roll and ``eye_angles`` (frames, 6) left yaw, pitch, roll, right
    yaw, pitch, roll, in the caller's units (0 where not given).
    """
    frames = arkit.shape[0]
    angles = np.zeros((frames, len(ANGLE_COLUMNS)))
    if head_angles is not None:
        angles[:, :3] = head_angles
    if eye_angles is not None:
        angles[:, 3:] = eye_angles
    values = np.concatenate([arkit, angles], axis=1)
    lines = [",".join(["Timecode", "BlendShapeCount"] + ARKIT_NAMES + ANGLE_COLUMNS)]
    codes = format_timecode(np.arange(frames), fps)
    text_values = np.char.mod("%.6f", np.round(values, 6) + 0.0)  # + 0.0 turns -0.0 into 0.0
    for code, row in zip(codes, text_values):
        lines.append(f"{code},{LIVE_LINK_COUNT}," + ",".join(row))
    return ("\n".join(lines) + "\n").encode("utf-8")
