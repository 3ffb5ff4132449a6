"""msflow: a small cached dataflow framework (pipeline spec, DAG, content-hashed zarr artifacts, executors, CLI).

Stage authors import ``Stage, Input, Output, Result, UserError`` from here; users call ``msflow.run``.
"""
from msflow.errors import StageFailed, UserError
from msflow.stage import Input, Output, Params, Result, Stage

__version__ = "0.1.0"


def run(path, overrides=(), **options):
    """Run a pipeline file and return a ``RunResult`` (see ``msflow.api.run``)."""
    from msflow.api import run as _run

    return _run(path, overrides=overrides, **options)


__all__ = ["Stage", "Params", "Input", "Output", "Result", "UserError", "StageFailed", "run", "__version__"]
