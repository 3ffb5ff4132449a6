"""msflow: a small cached dataflow framework (pipeline spec, DAG, content-hashed zarr artifacts, executors, CLI).

Stage authors import ``Stage, Input, Output, Result, UserError`` from here; users call ``msflow.run``. Exports
load on first use so that ``msflow status`` and a no-op ``msflow run`` import as little as possible.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from msflow.errors import StageFailed, UserError
from msflow.version import __version__

if TYPE_CHECKING:
    from msflow.api import RunResult

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


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'msflow' has no attribute '{name}'")


def run(path: Any, overrides: Sequence[str] = (), **options: Any) -> RunResult:
    """Run a pipeline: compute what is missing, reuse everything else, publish, and record the run.

    Parameters
    ----------
    path : str or Path
        The pipeline file.
    overrides : sequence of str
        ``stage.param=value`` overrides (YAML values), as ``msflow run -S``.
    jobs : int
        Stages run at once (``-j``: one in this process, for stages that allow it, the others in worker
        processes started when needed), also given to each stage as ``Stage.jobs``.
    until : str, optional
        Run only this stage and what it needs.
    force : sequence of str
        Stages to recompute even when cached.
    executor, scheduler, connect_timeout
        ``"local"`` (msflow's own process and worker processes) or ``"dask"``; a Dask scheduler address and how
        long to wait for it.
    reporter
        Receives every stage state change (the CLI's progress display).
    raise_on_failure : bool
        Raise after the run when a stage failed (otherwise inspect ``RunResult.states``).
    publish_dir : str or Path, optional
        Where the ``publish:`` entries go (relative to it); by default they are relative to the pipeline file and
        must stay inside the project folder.

    Returns
    -------
    RunResult
        Stage states, the run record, and access to every artifact.

    Raises
    ------
    UserError
        A mistake in the pipeline or its data (nothing is computed for pipeline mistakes).
    StageFailed
        A stage crashed (only when ``raise_on_failure``).

    Examples
    --------
    >>> import tempfile, msflow
    >>> from msflow.testing import example_project
    >>> project = example_project(tempfile.mkdtemp())
    >>> result = msflow.run(project / "pipeline.yaml")
    >>> result.executed
    ['ramp', 'scale']
    >>> result.load("scale.y")
    array([0., 3., 6., 9.])
    >>> msflow.run(project / "pipeline.yaml").executed  # everything is cached
    []
    >>> msflow.run(project / "pipeline.yaml", ["scale.factor=4"]).executed
    ['scale']
    """
    from msflow.api import run as run_pipeline

    return run_pipeline(path, overrides=overrides, **options)


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
