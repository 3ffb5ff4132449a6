"""CREMA-D 1001 through the face branch to the ICT character: keyshapes, keymorphs (KeymorphFit), blend.

    OPENBLAS_NUM_THREADS=1 python bench/eval_retarget.py [out_dir]   (from the project root; default bench/out/retarget)

Tracking (FaceMesh) -> aam (AamPca) -> bilinear (BilinearFit) -> edit (ExpressionEdit) on the test take (SAD),
then Keyshapes -> KeymorphFit (GltfCharacter ict-facekit.glb) -> Blend with alpha = happy / angry / neutral /
from_analysis. Prints the numbers of the issue-5 report and writes PNGs.
"""

import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from msflow.testing import run_stage

OUT = Path(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).resolve().parent / "out" / "retarget")
OUT.mkdir(parents=True, exist_ok=True)

shutil.rmtree(OUT / "store", ignore_errors=True)
D = "data/crema-d/1001_DFA_{}_XX.flv"


def timed(label, fn):
    t = time.time()
    out = fn()
    print(f"[{label}] {time.time() - t:.1f}s", flush=True)
    return out


def save_figure(fig, path):
    if isinstance(fig, (bytes, bytearray)):
        Path(path).write_bytes(fig)
    else:
        fig.savefig(path, dpi=110)


def main():
    from stages.face.aam import AamPca
    from stages.face.bilinear import BilinearFit
    from stages.face.edit import ExpressionEdit
    from stages.retarget.blend import Blend
    from stages.retarget.character import GltfCharacter
    from stages.retarget.keymorphs import KeymorphFit
    from stages.retarget.keyshapes import Keyshapes
    from stages.tracking import FaceMesh

    train = timed(
        "track_train",
        lambda: run_stage(
            FaceMesh, {}, {"videos": {"neutral": D.format("NEU"), "happy": D.format("HAP"), "angry": D.format("ANG")}}
        ),
    )
    test = timed("track_test", lambda: run_stage(FaceMesh, {}, {"videos": {"sad": D.format("SAD")}}))
    aam = timed("aam", lambda: run_stage(AamPca, {}, {"tracks": train.view()}))
    bilinear = timed("bilinear", lambda: run_stage(BilinearFit, {}, {"aam": aam.view(), "tracks": train.view()}))
    edit = timed(
        "edit",
        lambda: run_stage(
            ExpressionEdit, {"video": False}, {"model": bilinear.view(), "aam": aam.view(), "tracks": test.view()}
        ),
    )
    character = timed(
        "character", lambda: run_stage(GltfCharacter, {}, {"mesh": {"path": "data/characters/ict-facekit.glb"}})
    )
    keyshapes = timed(
        "keyshapes", lambda: run_stage(Keyshapes, {}, {"aam": aam.view(), "edit": edit.view()}, store=OUT / "store")
    )
    keymorphs = timed(
        "keymorphs",
        lambda: run_stage(
            KeymorphFit,
            {},
            {"keyshapes": keyshapes.view(), "character": character.view(), "tracks": train.view()},
            store=OUT / "store",
        ),
    )

    print("\n== keyshapes")
    print(
        "counts",
        dict(zip(keyshapes.meta["labels"], keyshapes.meta["keyshape_counts"])),
        "dropped",
        {k: len(v) for k, v in keyshapes.meta["dropped"].items()},
    )
    print("variance covered", {k: round(v, 3) for k, v in keyshapes.meta["variance_covered"].items()})
    print(json.dumps({k: round(v, 5) for k, v in keyshapes.metrics.items()}, indent=1))
    print("\n== keymorphs")
    print(json.dumps({k: round(v, 5) for k, v in keymorphs.metrics.items()}, indent=1))
    (OUT / "keymorphs.yaml").write_bytes(keymorphs.arrays["keymorphs"].tobytes())
    (OUT / "contact_sheet.png").write_bytes(keymorphs.arrays["contact_sheet"].tobytes())
    names = character.meta["target_names"]
    G = keymorphs.arrays["keymorph_weights"]
    expr = keyshapes.arrays["keyshape_expression"]
    for s, label in enumerate(keyshapes.meta["labels"]):
        mean = G[expr == s].mean(axis=0)
        top = np.argsort(-mean)[:6]
        print(f"  mean keymorph {label:8s}", {names[m]: round(float(mean[m]), 3) for m in top})

    print("\n== blend")
    smile = [names.index(n) for n in names if n.startswith("mouthSmile")]
    brow = [names.index(n) for n in names if n.startswith("browDown")]
    inputs = {
        "keyshapes": keyshapes.view(),
        "keymorphs": keymorphs.view(),
        "edit": edit.view(),
        "bilinear": bilinear.view(),
    }
    results = {}
    for alpha in ({"happy": 1.0}, {"angry": 1.0}, {"neutral": 1.0}, "from_analysis"):
        out = run_stage(Blend, {"alpha": alpha}, inputs)
        key = alpha if isinstance(alpha, str) else next(iter(alpha))
        w = out.arrays["weights"]
        results[key] = out
        print(
            f"  alpha={key:14s} clipped_fraction={out.metrics['clipped_fraction']:.4f} "
            f"clipped_amount={out.metrics['clipped_amount']:.5f} max_unclipped={out.metrics['max_weight_unclipped']:.3f}"
            f" mean mouthSmile={w[:, smile].mean():.4f} mean browDown={w[:, brow].mean():.4f}"
            + (f" mean alpha={np.round(out.arrays['alpha'].mean(0), 3).tolist()}" if key == "from_analysis" else "")
        )
    h, a = results["happy"].arrays["weights"], results["angry"].arrays["weights"]
    print(
        f"  smile happy > angry: {h[:, smile].mean() > a[:, smile].mean()}  "
        f"browDown angry > happy: {a[:, brow].mean() > h[:, brow].mean()}"
    )

    for name, fig in Keyshapes.figures.items():
        save_figure(fig(keyshapes.view(), {}), OUT / f"keyshapes_{name}.png")
    save_figure(
        KeymorphFit.figures["landmark_fit"](keymorphs.view(), {"keyshapes": keyshapes.view()}),
        OUT / "keymorphs_landmark_fit.png",
    )
    for key, out in results.items():
        for name, fig in Blend.figures.items():
            save_figure(fig(out.view(), {}), OUT / f"blend_{key}_{name}.png")
    print("figures in", OUT)


if __name__ == "__main__":
    main()
