"""Evaluation stages: normal cached stages whose numbers are stage metrics, one module per area (face, retarget,
head), run by the pipelines in ``eval/`` pointed at a folder of takes."""
