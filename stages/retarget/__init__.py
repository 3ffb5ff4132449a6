"""Retargeting (paper Sec 4): from the edited face to a 3D character's morph targets.

- ``character``: the character's neutral mesh, morph targets and landmark vertices (glTF or OBJ);
- ``keyshapes``: the keyshape stages: keyshapes = PCA-extreme frames per expression (Sec 4.1, selected in
  ``keyshape_selection``) and the non-negative decomposition of every frame onto them (Eq 8, ``decomposition``);
- ``keymorphs``: morph weights per keyshape (Sec 4.3): the artist's file, or an automatic draft;
- ``blend``: morph weights per frame, blended across expressions by alpha_j(t) (Eq 9).
"""
