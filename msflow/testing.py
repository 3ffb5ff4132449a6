"""Run one stage class outside a pipeline: for unit tests of stages and for notebooks.

    from msflow.testing import run_stage, artifact
    out = run_stage(Scale, {"factor": 3}, {"x": np.arange(4.0)})
    out.arrays["y"]; out.meta; out.view()  # view() feeds the next stage's Input.artifact

``example_project(folder)`` writes a small runnable project (two stages and a pipeline file) for examples.

The same validation as the runner applies (params, inputs, output schema, strict JSON metadata); with
``store=path`` the result also round-trips through a real zarr artifact, so serialisation problems show up.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from msflow.artifact import ArtifactView, settle_output
from msflow.stage import Files, Stage


def artifact(
    arrays: Mapping[str, Any], meta: dict[str, Any] | None = None, metrics: dict[str, Any] | None = None
) -> ArtifactView:
    """An in-memory artifact with the interface stages see for ``Input.artifact`` inputs."""
    import numpy as np

    return ArtifactView({k: np.asarray(v) for k, v in arrays.items()}, meta or {}, metrics or {})


@dataclass
class StageRun:
    """What ``run_stage`` returns: the outputs as numpy, meta, metrics and warnings."""

    arrays: dict[str, Any]
    meta: dict[str, Any]
    metrics: dict[str, Any]
    warnings: list[str] = field(default_factory=list)

    def view(self) -> ArtifactView:
        return ArtifactView(self.arrays, self.meta, self.metrics)


def files_input(value: Any) -> Files:
    """A path, ``{label: path}``, ``{label: {path: ..., field: value}}`` or ``Files`` as the stage receives it."""
    if isinstance(value, (str, Path)):
        value = {str(value): value}
    fields = dict(getattr(value, "fields", {}))
    paths = {}
    for label, entry in value.items():
        if isinstance(entry, Mapping):
            fields[str(label)] = {k: str(v) for k, v in entry.items() if k != "path"}
            entry = entry["path"]
        paths[str(label)] = Path(entry).resolve()
    return Files(paths, fields)


def prepare_inputs(cls: type[Stage], inputs: Mapping[str, Any]) -> dict[str, Any]:
    """Check names and kinds of directly supplied inputs the way the runner would."""
    unknown = set(inputs) - set(cls.inputs)
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown inputs {sorted(unknown)}; declared: {sorted(cls.inputs)}")
    prepared: dict[str, Any] = {}
    for name, spec in cls.inputs.items():
        value = inputs.get(name)
        if value is None:
            if not spec.optional:
                raise ValueError(f"{cls.__name__}: missing required input '{name}'")
            prepared[name] = None
            continue
        if spec.kind == "files":
            prepared[name] = files_input(value)
        elif spec.kind == "artifact":
            if isinstance(value, StageRun):
                value = value.view()
            if not isinstance(value, ArtifactView):
                raise TypeError(f"{cls.__name__}: input '{name}' wants an artifact (msflow.testing.artifact)")
            missing = [r for r in spec.requires if r not in value]
            if missing:
                raise ValueError(f"{cls.__name__}: input '{name}' lacks outputs {missing}")
            prepared[name] = value
        else:
            import numpy as np

            prepared[name] = np.asarray(value)
    return prepared


def run_stage(
    cls: type[Stage],
    params: Mapping[str, Any] | None = None,
    inputs: Mapping[str, Any] | None = None,
    *,
    name: str | None = None,
    store: str | Path | None = None,
    jobs: int = 1,
) -> StageRun:
    """Run one stage class outside a pipeline, with the runner's validation.

    The stage runs through the function the runner's workers use (``msflow.worker.compute``), so whatever the
    runner rejects (a schema violation, non-JSON metadata, non-scalar metrics) raises here too.

    Parameters
    ----------
    cls : type of Stage
        The stage class.
    params : mapping, optional
        Raw params, validated by ``cls.Params`` (a ``pydantic.ValidationError`` when invalid).
    inputs : mapping, optional
        Input name -> value: a numpy array (``Input.array``), an artifact (``artifact(...)`` or a previous
        ``StageRun``) for ``Input.artifact``, a path or ``{label: path}`` for ``Input.files``.
    name : str, optional
        The stage name (messages); the class name by default.
    store : str or Path, optional
        A folder: the result also round-trips through a real zarr artifact there.
    jobs : int
        The stage's ``self.jobs``.

    Returns
    -------
    StageRun
        Outputs as numpy arrays (output sinks kept their blocks in memory), meta, metrics, warnings. The stage's
        warnings are also re-emitted to the caller; BLAS threading is the caller's (workers pin it to one).

    Raises
    ------
    UserError
        The stage rejected its data.
    TypeError, ValueError
        Inputs of the wrong kind, or a result the runner would reject (``msflow.errors.InvalidResult``).

    Examples
    --------
    >>> import numpy as np
    >>> from msflow import Input, Output, Result, Stage
    >>> class Scale(Stage):
    ...     class Params(Stage.Params):
    ...         factor: float = 2.0
    ...     inputs = {"x": Input.array("f")}
    ...     outputs = {"y": Output.array("f", shape=("n",))}
    ...     def run(self, params, inputs):
    ...         return Result({"y": inputs["x"] * params.factor}, metrics={"peak": float(inputs["x"].max())})
    >>> out = run_stage(Scale, {"factor": 3}, {"x": np.arange(3.0)})
    >>> out.arrays["y"], out.metrics
    (array([0., 3., 6.]), {'peak': 2.0})
    """
    from msflow.worker import compute

    stage_name = name or cls.__name__
    validated = cls.Params(**dict(params or {}))
    done = compute(cls, stage_name, validated, prepare_inputs(cls, inputs or {}), jobs=jobs, pin_blas=False)
    for caught in done.caught:  # as if the stage had run in the caller's own warning context
        warnings.warn_explicit(caught.message, caught.category, caught.filename, caught.lineno)
    arrays = {k: settle_output(v) for k, v in done.arrays.items()}
    if store is not None:
        from msflow.artifact import read_artifact, write_artifact

        path = Path(store) / f"{stage_name}.zarr"
        write_artifact(path, arrays, {"meta": done.meta, "metrics": done.metrics})
        view = read_artifact(path, through_zarr=True)  # what any zarr reader sees of it
        arrays = {k: view[k] for k in view.names}
    return StageRun(arrays, done.meta, done.metrics, done.warnings)


EXAMPLE_STAGES = """\"\"\"Two example stages: a ramp of numbers and a scaled copy.\"\"\"

import numpy as np

from msflow import Input, Output, Result, Stage


class Ramp(Stage):
    \"\"\"0, 1, ..., n - 1.\"\"\"

    class Params(Stage.Params):
        n: int = 4

    outputs = {"x": Output.array("f", shape=("n",))}

    def run(self, params, inputs):
        return Result({"x": np.arange(params.n, dtype=float)}, meta={"n": params.n})


class Scale(Stage):
    \"\"\"The input times a factor.\"\"\"

    class Params(Stage.Params):
        factor: float = 2.0

    inputs = {"x": Input.array("f")}
    outputs = {"y": Output.array("f", shape=("n",))}

    def run(self, params, inputs):
        y = inputs["x"] * params.factor
        return Result({"y": y}, metrics={"total": float(y.sum())})
"""

EXAMPLE_PIPELINE = """\
version: 1
stages:
  ramp:
    uses: example_stages:Ramp
  scale:
    uses: example_stages:Scale
    inputs: {x: ramp.x}
    params: {factor: 3}
"""


def example_project(folder: str | Path) -> Path:
    """Write a two-stage example project (``example_stages.py``, ``pipeline.yaml``) into ``folder``; return it.

    For trying msflow and for the documentation's examples: ``msflow.run(example_project(d) / "pipeline.yaml")``.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "example_stages.py").write_text(EXAMPLE_STAGES, encoding="utf-8")
    (folder / "pipeline.yaml").write_text(EXAMPLE_PIPELINE, encoding="utf-8")
    return folder
