"""Evaluation stages, one module per area (``face``, ``retarget``, ``head``): normal cached stages whose numbers
are stage metrics, run by the pipelines in ``eval/``."""
