"""Run one stage class outside a pipeline: for unit tests of stages and for notebooks.

    from msflow.testing import run_stage, artifact
    out = run_stage(Scale, {"factor": 3}, {"x": np.arange(4.0)})
    out.arrays["y"]; out.meta; out.view()  # view() feeds the next stage's Input.artifact

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


def artifact(arrays: Mapping[str, Any], meta: dict | None = None, metrics: dict | None = None) -> ArtifactView:
    """An in-memory artifact with the interface stages see for ``Input.artifact`` inputs."""
    import numpy as np

    return ArtifactView({k: np.asarray(v) for k, v in arrays.items()}, meta or {}, metrics or {})


@dataclass
class StageRun:
    """What ``run_stage`` returns: the outputs as numpy, meta, metrics and warnings."""

    arrays: dict[str, Any]
    meta: dict
    metrics: dict
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
    """Validate params and inputs, run the stage, validate its result; optionally round-trip through zarr.

    The stage runs through the same function as in the runner's workers (``msflow.worker.compute``), so a
    result the runner rejects (a schema violation, non-JSON metadata, non-scalar metrics) raises here too.
    Output sinks keep their blocks in memory; ``jobs`` is the stage's ``self.jobs``; BLAS threading is the
    caller's (workers pin it to one thread).
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
        view = read_artifact(path)
        arrays = {k: view[k] for k in view.names}
    return StageRun(arrays, done.meta, done.metrics, done.warnings)
