"""A character's morphs spelt another way than ICT FaceKit's (``Mouth_Smile_L`` as some
exporters write them, Blender's ``mouthSmile.L``, ARKit's ``mouthSmileLeft``) are the same morphs everywhere a
name decides something: the ARKit mapping, the fit's regions, antagonists, correctives, exclusions and contact
morphs, and the side lookups of blinks, gaze and lip press."""

import re
from pathlib import Path

import pytest

from stages.formats.gltf import read_morph_mesh
from stages.formats.live_link import arkit_mapping
from stages.retarget.keymorphs import KeymorphFit
from stages.retarget.morph_fit import antagonist_pairs, matching_targets
from stages.retarget.region_fit import corrective_pairs, matching_any_case
from stages.retarget.regions import find_side_morph, morph_region

ICT_GLB = Path(__file__).resolve().parents[1] / "data" / "characters" / "ict-facekit.glb"


@pytest.fixture(scope="module")
def ict_names():
    return [n for n in read_morph_mesh(ICT_GLB).target_names if not n.startswith("identity")]


def title_snake(name):
    """``mouthSmile_L`` -> ``Mouth_Smile_L``."""
    base, side = (name[:-2], name[-1]) if name[-2:] in ("_L", "_R") else (name, "")
    words = re.sub(r"([a-z])([A-Z])", r"\1_\2", base).split("_")
    return "_".join(w[:1].upper() + w[1:] for w in words) + (f"_{side}" if side else "")


def blender(name):
    return f"{name[:-2]}.{name[-1]}" if name[-2:] in ("_L", "_R") else name


def arkit_sides(name):
    return name.replace("_L", "Left").replace("_R", "Right")


def lower_blender(name):
    """``mouthSmile_L`` -> ``mouthsmile.l``: the side a lower-case letter after a separator."""
    return blender(name).lower()


def spaced(name):
    """``mouthSmile_L`` -> ``Mouth Smile L``."""
    return title_snake(name).replace("_", " ")


def kebab(name):
    """``mouthSmile_L`` -> ``mouth-smile-l``."""
    return title_snake(name).replace("_", "-").lower()


@pytest.mark.parametrize("spell", [title_snake, blender, arkit_sides, lower_blender, spaced, kebab])
def test_other_spellings_are_the_same_morphs(ict_names, spell):
    other = [spell(n) for n in ict_names]
    assert other != ict_names
    ours, theirs = arkit_mapping(ict_names), arkit_mapping(other)
    assert [ours.destinations[n] for n in ict_names] == [theirs.destinations[n] for n in other]
    assert sum(1 for n in other if theirs.destinations[n]) >= 55  # every ARKit column ICT can drive
    assert [morph_region(n) for n in ict_names] == [morph_region(n) for n in other]  # gaze stays gaze
    params = KeymorphFit.Params()
    assert antagonist_pairs(ict_names, params.antagonists) == antagonist_pairs(other, params.antagonists)
    assert corrective_pairs(ict_names, params.correctives) == corrective_pairs(other, params.correctives)
    assert (matching_targets(ict_names, params.exclude) == matching_targets(other, params.exclude)).all()
    assert (
        matching_any_case(ict_names, params.contact_morphs) == matching_any_case(other, params.contact_morphs)
    ).all()
    for stem in ("eyeBlink", "eyeLookUp", "eyeLookIn", "mouthPress"):
        for side in "LR":
            assert find_side_morph(ict_names, stem, side) == find_side_morph(other, stem, side) is not None
