"""msflow: a small cached dataflow framework (pipeline spec, DAG, content-hashed zarr artifacts, executors, CLI).

Stage authors import ``Stage, Input, Output, Result, UserError`` from here; users call ``msflow.run``. Exports
load on first use so that ``msflow status`` and a no-op ``msflow run`` import as little as possible.
"""

from msflow.errors import StageFailed, UserError

__version__ = "0.1.0"

_LAZY = {
    "Stage": "msflow.stage",
    "Params": "msflow.stage",
    "Input": "msflow.stage",
    "Output": "msflow.stage",
    "Result": "msflow.stage",
    "Files": "msflow.stage",
    "OutputSink": "msflow.sinks",
    "iter_blocks": "msflow.sinks",
}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'msflow' has no attribute '{name}'")


def run(path, overrides=(), **options):
    """Run a pipeline file and return a ``RunResult`` (see ``msflow.api.run``)."""
    from msflow.api import run as _run

    return _run(path, overrides=overrides, **options)


__all__ = [
    "Stage",
    "Params",
    "Input",
    "Output",
    "Result",
    "Files",
    "OutputSink",
    "iter_blocks",
    "UserError",
    "StageFailed",
    "run",
    "__version__",
]
