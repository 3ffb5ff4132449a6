"""Evaluation stages, one module per area (``face``, ``retarget``, ``head``): normal cached stages whose numbers are
stage metrics (so ``msflow show``, ``msflow sweep --format md``, ``msflow compare`` and ``msflow report`` carry them),
run by the pipelines in ``eval/``, each pointed at a folder of takes by one variable::

    msflow run eval/face.yaml -S vars.takes=path/to/takes
"""
