"""Evaluation stages: normal cached stages whose numbers are stage metrics, so ``msflow show``, ``msflow sweep
--format md``, ``msflow compare`` and ``msflow report`` carry them. One module per part of the pipeline (``face``,
``retarget``, ``head``), each run by a pipeline in ``eval/`` pointed at a folder of takes by one variable::

    msflow run eval/face.yaml -S vars.takes=path/to/takes
"""
