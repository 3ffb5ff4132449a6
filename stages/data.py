"""Where the embedded default data lives: ``data/`` beside the ``stages`` package (models, character, 3D face).

Stages that read one of these files by default declare it in ``Stage.resources``, so its content is in the key."""

from pathlib import Path

DATA = Path(__file__).resolve().parents[1] / "data"
PROJECT_ROOT = DATA.parent
