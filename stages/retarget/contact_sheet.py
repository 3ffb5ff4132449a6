"""The keymorph contact sheet (the paper's Figs 3-4): per expression, each keyshape's face crop from tracking with
its landmarks beside the character rendered with its keymorph; and the keymorph stages' figures.
"""

from __future__ import annotations

import numpy as np

from msflow import UserError
from stages.retarget.face_measures import IBUG68_CONTOURS


def draw_landmarks(image: np.ndarray, points: np.ndarray, color=(40, 200, 40)) -> np.ndarray:
    """RGB copy of a grayscale or RGB image with the iBUG-68 contours and points drawn."""
    import cv2

    out = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB) if image.ndim == 2 else image.copy()
    shift = 4  # sub-pixel drawing
    pts = np.round(np.asarray(points, np.float64) * (1 << shift)).astype(np.int32)
    for contour in IBUG68_CONTOURS:
        cv2.polylines(out, [pts[list(contour)].reshape(-1, 1, 2)], False, color, 1, cv2.LINE_AA, shift)
    for p in pts:
        cv2.circle(out, (int(p[0]), int(p[1])), 1 << shift, color, -1, cv2.LINE_AA, shift)
    return out


def landmark_tile(points: np.ndarray, size: int) -> np.ndarray:
    """A white tile with a landmark drawing, for when no tracking crops are available."""
    pts = np.asarray(points, np.float64)
    lo, hi = pts.min(0), pts.max(0)
    scale = 0.8 * size / max(float((hi - lo).max()), 1e-9)
    pts = (pts - (lo + hi) / 2) * scale + size / 2
    return draw_landmarks(np.full((size, size), 255, np.uint8), pts, color=(30, 30, 30))


def face_crop_tile(crop: np.ndarray, landmarks: np.ndarray, size: int) -> np.ndarray:
    """The tracking crop with its landmarks, square-cropped around the face and resized to ``size``."""
    import cv2

    crop = np.asarray(crop)
    h, w = crop.shape[:2]
    pts = np.asarray(landmarks, np.float64)
    centre = (pts.min(0) + pts.max(0)) / 2
    half = 0.62 * float((pts.max(0) - pts.min(0)).max())
    x0, y0 = int(round(centre[0] - half)), int(round(centre[1] - half))
    side = max(int(round(2 * half)), 1)
    padded = cv2.copyMakeBorder(crop, side, side, side, side, cv2.BORDER_CONSTANT, value=0)
    window = padded[y0 + side : y0 + 2 * side, x0 + side : x0 + 2 * side]
    tile = cv2.resize(window, (size, size), interpolation=cv2.INTER_AREA)
    return draw_landmarks(tile, (pts - [x0, y0]) * (size / side))


def render_keymorph_tiles(character, weights: np.ndarray, size: int, supersample: int = 2) -> list[np.ndarray]:
    """The character's face from the front (stages.geometry.render, "face" framing) posed by each row of ``weights``."""
    from stages.geometry.render import CharacterRenderer, View

    # frame the landmarks tightly (brows to chin), like the tracking crops beside them
    points = np.asarray(character["neutral"], np.float64)[np.asarray(character["landmark_ids"])]
    lo, hi = points.min(axis=0), points.max(axis=0)
    pad = 0.12 * (hi - lo)
    view = View.fit(np.array([lo - pad, hi + pad * [1, 2, 0]]), margin=1.0)
    renderer = CharacterRenderer.from_artifact(character, size=size, view=view, supersample=supersample)
    return [np.ascontiguousarray(renderer(w)[..., :3]) for w in np.asarray(weights, np.float32)]


def compose_contact_sheet(
    labels: list[str],
    keyshape_expression: np.ndarray,
    keyshape_index: np.ndarray,
    keyshape_frame: np.ndarray,
    keyshape_tiles: list[np.ndarray],
    keymorph_tiles: list[np.ndarray],
    size: int,
    notes: list[str] | None = None,
) -> np.ndarray:
    """Paper Figs 3-4 as one RGB image: per expression a header, a row of keyshapes, a row of keymorphs."""
    import cv2

    expression = np.asarray(keyshape_expression)
    cols = max(int(np.bincount(expression, minlength=len(labels)).max(initial=1)), 1)
    header, caption = 22, 14
    block = header + 2 * (size + caption)
    sheet = np.full((block * len(labels), cols * size, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for s, label in enumerate(labels):
        top = s * block
        sheet[top : top + header] = (225, 225, 235)
        cv2.putText(
            sheet,
            f"{label}: keyshapes (top) and keymorphs (bottom)",
            (4, top + 16),
            font,
            0.5,
            (20, 20, 20),
            1,
            cv2.LINE_AA,
        )
        for c, k in enumerate(np.flatnonzero(expression == s)):
            x = c * size
            y = top + header
            sheet[y : y + size, x : x + size] = keyshape_tiles[k]
            cv2.putText(
                sheet,
                f"#{int(keyshape_index[k])} f{int(keyshape_frame[k])}",
                (x + 3, y + size + 11),
                font,
                0.35,
                (20, 20, 20),
                1,
                cv2.LINE_AA,
            )
            y += size + caption
            sheet[y : y + size, x : x + size] = keymorph_tiles[k]
            if notes:
                cv2.putText(sheet, notes[k], (x + 3, y + size + 11), font, 0.35, (20, 20, 20), 1, cv2.LINE_AA)
    return sheet


def encode_png(image: np.ndarray) -> bytes:
    import cv2

    ok, data = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR))
    if not ok:  # pragma: no cover - OpenCV failure
        raise RuntimeError("PNG encoding failed")
    return data.tobytes()


def check_tracks(keyshapes, tracks) -> None:
    """The tracking input must be the one the keyshapes' source frames index (a UserError otherwise)."""
    frames = np.asarray(keyshapes["keyshape_frame"])
    count = len(tracks["crop_landmarks"]) if tracks is not None and "crop_landmarks" in tracks else None
    if count is not None and frames.max(initial=0) >= count:
        raise UserError(
            f"keyshape source frame {int(frames.max())} is beyond the {count} frames of the "
            "tracking input: wire the training tracking (the one the aam was built from)",
            field="inputs.tracks",
        )


def build_contact_sheet(
    keyshapes, character, tracks, weights: np.ndarray, size: int, notes: list[str] | None = None
) -> np.ndarray:
    labels = list(keyshapes.meta["labels"])
    frames = np.asarray(keyshapes["keyshape_frame"])
    if tracks is not None:
        check_tracks(keyshapes, tracks)
        crops, crop_landmarks = tracks["crops"], tracks["crop_landmarks"]
        left = [face_crop_tile(crops[f], crop_landmarks[f], size) for f in frames]
    else:
        left = [landmark_tile(shape, size) for shape in keyshapes["keyshapes"]]
    right = render_keymorph_tiles(character, weights, size)
    return compose_contact_sheet(
        labels, keyshapes["keyshape_expression"], keyshapes["keyshape_index"], frames, left, right, size, notes
    )


# ---------------------------------------------------------------------------------------------------- figures


def figure_contact_sheet(view, inputs):
    """Keyshape crops above keymorph renders, per expression (the paper's Figs 3-4): the one the stage wrote
    (``params.contact_sheet``), else rendered now from the stage's inputs (a run need not pay for it)."""
    if "contact_sheet" in view:
        return view.bytes("contact_sheet")
    if inputs and inputs.get("keyshapes") is not None and inputs.get("character") is not None:
        notes = [f"err {100 * e:.1f}%" for e in view["landmark_error"]]
        weights = np.asarray(view["keymorph_weights"], np.float64)
        sheet = build_contact_sheet(inputs["keyshapes"], inputs["character"], inputs.get("tracks"), weights, 128, notes)
        return encode_png(sheet)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4, 1))
    ax.axis("off")
    ax.text(0.5, 0.5, "no contact sheet: neither stored (params.contact_sheet) nor inputs", ha="center", va="center")
    return fig


def figure_landmark_fit(view, inputs):
    """Keyshape landmarks (black) against the landmarks the keymorph gives the character (red), per keyshape
    (the 3D fit: both in the head frame, seen from the front)."""
    from stages.retarget.keyshape_figures import plot_keyshape_grid

    keyshapes = inputs["keyshapes"]
    reference = keyshapes["keyshapes"]
    if view.meta.get("space") == "3d" and "keyshapes3d" in keyshapes:
        from stages.retarget.shapes3d import front_view

        reference = front_view(keyshapes["keyshapes3d"])
    errors = view["landmark_error"]
    return plot_keyshape_grid(
        [(reference, {"color": "k", "lw": 0.7}), (view["keymorph_landmarks"], {"color": "r", "lw": 0.7})],
        keyshapes["keyshape_expression"],
        list(keyshapes.meta["labels"]),
        "Keyshape (black) vs keymorph landmarks (red), RMS error % inter-ocular",
        lambda i, c: f"{c}: {100 * errors[i]:.1f}%",
    )
