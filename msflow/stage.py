"""The Stage contract: what a pipeline step declares (params, inputs, outputs) and what it returns.

A stage is a class::

    class Scale(Stage):
        '''Multiply an array by a factor.'''

        class Params(Stage.Params):
            factor: float = 2.0

        inputs = {"x": Input.array(kind="f")}
        outputs = {"y": Output.array(kind="f", shape=("n",))}

        def run(self, params, inputs):
            return Result({"y": inputs["x"] * params.factor}, meta={"factor": params.factor})

Inputs arrive as:
- ``Input.array``: one upstream output (``stage.output`` in pipeline.yaml), a numpy array (``lazy=True``: a
  read-only stored array that loads on slicing, with zarr's attributes);
- ``Input.artifact``: a whole upstream artifact (``stage``), an ``ArtifactView`` (``view["name"]`` loads numpy,
  ``view.lazy("name")``, ``view.meta``, ``view.metrics``);
- ``Input.files``: data files, ``Files``: an ordered ``dict`` label -> absolute ``Path`` whose ``fields``
  attribute holds each label's fields (speaker, expression, ...), parsed from file names or written in YAML.

Two implementations of one pipeline step share one ``outputs`` mapping (define it once, assign it in both),
so ``uses:`` swaps them. This module stays import-light: it is part of every stage's code fingerprint.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar, Mapping

from pydantic import BaseModel, ConfigDict

from msflow.errors import UserError

DTYPE_KINDS = {"f": "float", "i": "signed int", "u": "unsigned int", "b": "bool", "c": "complex"}


@dataclass(frozen=True)
class Output:
    """Schema of one output of a stage, checked against what ``run`` returns (a mismatch fails the stage).

    Build one with ``Output.array(...)`` or ``Output.file(suffix)``. Two implementations of one pipeline step
    share one ``outputs`` mapping, so ``uses:`` swaps them.

    Attributes
    ----------
    kind : str
        Accepted numpy dtype kinds: "f" float, "i" signed, "u" unsigned, "b" bool, "c" complex ("iu": either).
    ndim : int or None
        Number of dimensions, when fixed.
    shape : tuple or None
        Per axis: an int (fixed size), None (free) or a name: a named dimension has one size across all outputs
        of the stage (e.g. "frames").
    dtype : str or None
        One exact dtype, when ``kind`` is not enough.
    optional : bool
        The stage may leave it out of its ``Result``.
    file_suffix : str or None
        A file output (bytes: a GLB, a CSV, a video), stored as uint8; ``msflow export`` writes the file back.

    Examples
    --------
    >>> Output.array("f", shape=("frames", 68, 2)).ndim
    3
    >>> Output.file(".glb").describe()["file_suffix"]
    '.glb'
    """

    kind: str = "f"
    ndim: int | None = None
    shape: tuple[int | str | None, ...] | None = None
    dtype: str | None = None
    optional: bool = False
    file_suffix: str | None = None
    doc: str = ""

    @classmethod
    def array(
        cls,
        kind: str = "f",
        *,
        ndim: int | None = None,
        shape: tuple[int | str | None, ...] | None = None,
        dtype: str | None = None,
        optional: bool = False,
        doc: str = "",
    ) -> Output:
        if shape is not None:
            shape = tuple(shape)
            if ndim is not None and ndim != len(shape):
                raise ValueError("Output.array: ndim disagrees with shape")
            ndim = len(shape)
        return cls(kind=kind, ndim=ndim, shape=shape, dtype=dtype, optional=optional, doc=doc)

    @classmethod
    def file(cls, suffix: str, *, optional: bool = False, doc: str = "") -> Output:
        return cls(kind="u", ndim=1, dtype="uint8", optional=optional, file_suffix=suffix, doc=doc)

    def describe(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "ndim": self.ndim,
            "shape": list(self.shape) if self.shape else None,
            "dtype": self.dtype,
            "optional": self.optional,
            "file_suffix": self.file_suffix,
        }


@dataclass(frozen=True)
class Input:
    """Declaration of one input of a stage; pipeline.yaml connects it, and ``msflow status`` checks the connection
    before anything runs.

    Attributes
    ----------
    kind : str
        "array": one upstream output (``stage.output``), handed over as numpy, or as a read-only stored array
        when ``lazy`` (``msflow.stored``: slicing reads; other attributes are zarr's); "artifact": a whole
        upstream artifact (``stage``), an ``ArtifactView``; "files": data files, a ``Files`` mapping label -> Path
        with each label's fields.
    optional : bool
        The pipeline may leave it unconnected (the stage receives None).
    requires : tuple of str
        "artifact": outputs the upstream artifact must declare.
    lazy : bool
        "array": pass a lazy array (read it in blocks with ``msflow.iter_blocks``).
    array_kind, ndim
        "array": documentation of the expected dtype kind and dimensions.

    Examples
    --------
    >>> Input.array("f", lazy=True).describe()["kind"]
    'array'
    >>> Input.artifact("mesh", "pose").requires
    ('mesh', 'pose')
    """

    kind: str
    optional: bool = False
    requires: tuple[str, ...] = ()
    lazy: bool = False
    array_kind: str | None = None
    ndim: int | None = None
    doc: str = ""

    @classmethod
    def array(
        cls,
        kind: str | None = None,
        *,
        ndim: int | None = None,
        optional: bool = False,
        lazy: bool = False,
        doc: str = "",
    ) -> Input:
        return cls("array", optional=optional, lazy=lazy, array_kind=kind, ndim=ndim, doc=doc)

    @classmethod
    def artifact(cls, *requires: str, optional: bool = False, doc: str = "") -> Input:
        return cls("artifact", optional=optional, requires=tuple(requires), doc=doc)

    @classmethod
    def files(cls, *, optional: bool = False, doc: str = "") -> Input:
        return cls("files", optional=optional, doc=doc)

    def describe(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "optional": self.optional,
            "requires": list(self.requires),
            "array_kind": self.array_kind,
            "ndim": self.ndim,
        }


class Files(dict[str, Path]):
    """What an ``Input.files`` input receives: label -> absolute ``Path`` in the order written, and ``fields``:
    label -> {field: value}, the labels' fields (parsed from file names by a ``pattern``, or written beside each
    path in pipeline.yaml). Fields enter the cache key with the files' content."""

    def __init__(self, paths: Mapping[str, Any] | None = None, fields: Mapping[str, Mapping[str, str]] | None = None):
        super().__init__(paths or {})
        self.fields: dict[str, dict[str, str]] = {label: dict((fields or {}).get(label, {})) for label in self}

    def field(self, label: str, name: str, default: str | None = None) -> str | None:
        """One field of one label, or ``default``."""
        return self.fields.get(label, {}).get(name, default)


@dataclass
class Result:
    """What ``Stage.run`` returns: named arrays (or bytes for file outputs), JSON metadata, scalar metrics, and
    warnings: things the user should know about a result that is still usable (an analysis that stopped before
    converging, a channel with nothing to drive it). ``warnings.warn(..., UserWarning)`` inside ``run`` lands
    here too. The CLI prints them with the stage's name; the artifact, run record and report keep them."""

    arrays: dict[str, Any]
    meta: dict[str, Any] = field(default_factory=dict)
    metrics: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


class Params(BaseModel):
    """Base of every stage's parameters: unknown keys are an error, values are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class Stage:
    """Base class of pipeline stages: subclasses declare ``Params``, ``inputs``, ``outputs`` and define ``run``.

    ``run(params, inputs)`` receives validated params (an instance of ``Params``, a frozen pydantic model: put
    every rule pydantic can express there, so a bad ``-S`` is rejected before anything runs) and the inputs, and
    returns a ``Result``. Keep it thin: validate, call plain numpy functions, pack. Import heavy modules inside
    ``run``: a no-op run imports no stage code.

    Attributes
    ----------
    Params : type
        The parameters' pydantic model (unknown keys are errors).
    inputs : mapping of str to Input
        Declared inputs.
    outputs : mapping of str to Output
        Declared outputs.
    figures : mapping of str to callable
        Report figures: ``f(view, inputs)`` returning a matplotlib Figure, PNG or MP4 bytes.
    resources : mapping of str to path
        Data files the code reads by default (models): hashed into the cache key.
    in_process : bool
        ``-j N`` may run the stage in the run's own process (no worker started for it); false by default.
    cheap : bool
        Quick: ``-j N`` starts no worker for it (it runs in the run's own process); false by default.
    name : str
        The stage's name in the pipeline (instance attribute).
    jobs : int
        The run's worker count (``-j``), for parallelism inside ``run``; not in the key: results must not
        depend on it (instance attribute).

    Examples
    --------
    >>> import numpy as np
    >>> class Scale(Stage):
    ...     \"\"\"Multiply an array by a factor.\"\"\"
    ...     class Params(Stage.Params):
    ...         factor: float = 2.0
    ...     inputs = {"x": Input.array("f")}
    ...     outputs = {"y": Output.array("f", shape=("n",))}
    ...     def run(self, params, inputs):
    ...         return Result({"y": inputs["x"] * params.factor})
    >>> Scale("scale").run(Scale.Params(factor=3), {"x": np.ones(2)}).arrays["y"]
    array([3., 3.])
    >>> Scale.Params(factor="x")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    pydantic_core._pydantic_core.ValidationError: 1 validation error for Params
    ...
    """

    Params: ClassVar[type[Params]] = Params
    inputs: ClassVar[Mapping[str, Input]] = {}
    outputs: ClassVar[Mapping[str, Output]] = {}
    #: figures for the run report: name -> function(view: ArtifactView, inputs: dict[str, Any]) returning a matplotlib
    #: Figure, PNG bytes or MP4 bytes; rendered from artifacts at report time (import matplotlib inside).
    figures: ClassVar[Mapping[str, Callable[..., Any]]] = {}
    #: data files or folders the stage's code reads by default (models, reference meshes): name -> path. They
    #: are hashed by content into the cache key like inputs, so replacing a model file reruns the stage.
    resources: ClassVar[Mapping[str, Any]] = {}
    #: may run in a thread of the run's own process under ``-j N`` (msflow.executors.LocalExecutor), where it finds
    #: the libraries already imported and costs no worker process. Say so only of a stage whose ``run`` changes no
    #: process-wide state (working folder, signal handlers, environment) and starts no process that would outlive
    #: the run if it were killed (SIGKILL): a run cannot stop what a thread of its own started, as it stops a
    #: worker's process group.
    in_process: ClassVar[bool] = False
    #: quick (about a second or less on a take of minutes): ``-j N`` runs it in the run's own process only, after
    #: the stage that process is on, since a worker would import numpy, scipy, ... again for it (in a sweep, whose
    #: variants of it share a worker's imports, it may run in one). Implies ``in_process``.
    cheap: ClassVar[bool] = False

    def __init__(self, name: str = "", *, jobs: int = 1, chunk_target: Any = None, parts: Any = None):
        self.name = name or type(self).__name__
        #: the run's worker count (``msflow run -j N``), for parallelism inside ``run`` (threads over blocks of
        #: frames, a process pool). It is not part of the cache key: results must not depend on it.
        self.jobs = max(1, int(jobs))
        self._chunk_target = chunk_target  # where output sinks write chunks (the artifact being written)
        self._parts = parts  # where parts are kept (msflow.parts.StoreParts in a store run)
        self._sinks: dict[str, Any] = {}
        self._part_labels: set[str] = set()  # the labels whose part this instance asked for (Stage.part)

    def run(self, params: Any, inputs: dict[str, Any]) -> Result:  # pragma: no cover - abstract
        raise NotImplementedError

    def sink(self, name: str, *, dtype: Any, row_shape: tuple[int, ...] = ()) -> Any:
        """An output sink for output ``name``: a frames-first array of unknown length, filled block by block.

        ``sink.append(block)`` adds rows (``block.shape == (m, *row_shape)``); return the sink in ``Result``
        like an array. In a store run its chunks are compressed and written as they fill, so the whole array is
        never in memory; its content hash equals that of the same array returned whole.
        """
        from msflow.sinks import OutputSink

        spec = type(self).outputs.get(name)
        if spec is None:
            raise ValueError(
                f"stage '{self.name}': no declared output '{name}' to sink into; declared: {sorted(self.outputs)}"
            )
        if name in self._sinks:
            raise ValueError(f"stage '{self.name}': output '{name}' already has a sink")
        sink = OutputSink(name, dtype, tuple(row_shape), self._chunk_target)
        check_output(f"stage '{self.name}', output '{name}'", spec, sink.dtype, (0, *sink.row_shape), frames=False)
        self._sinks[name] = sink
        return sink

    def part(
        self,
        label: str,
        make: Callable[[Any], Result],
        *,
        labelled: tuple[str, ...],
        whole: tuple[str, ...] = (),
        unread_params: tuple[str, ...] = (),
    ) -> Any:
        """A piece of the result that depends on one label only, stored and reused on its own (``msflow.parts``).

        ``make(sink)`` computes it and returns a ``Result`` (arrays or sinks from ``sink(name, dtype=...,
        row_shape=...)``, strict-JSON meta; no schema). Its key hashes the stage's class, code, params (but the
        ``unread_params``) and resources, the entry under ``label`` of each ``labelled`` files input and each
        ``whole`` input: ``make`` must read nothing else (not other labels, not the label's name). A label has
        one part per run of the stage. Returns a ``msflow.parts.Part``: arrays (lazy when stored), meta, ``reused``
        (found computed by an earlier run) and the warnings its computation raised.
        """
        from msflow.parts import InMemoryParts, PartReads, check_part_reads

        reads = PartReads(tuple(labelled), tuple(whole), tuple(unread_params))
        check_part_reads(type(self).inputs, type(self).Params, reads)
        where = f"stage '{self.name}', part '{label}'"
        if label in self._part_labels:  # its key would be the first's: it would get the first's content back
            raise ValueError(f"{where} is asked for twice: a label has one part (compute all of its pieces in one)")
        self._part_labels.add(label)

        def checked(sink: Any) -> tuple[Mapping[str, Any], dict[str, Any]]:
            result = make(sink)
            if not isinstance(result, Result):
                raise TypeError(f"{where}: its function returned {type(result).__name__}, expected msflow.Result")
            return result.arrays, to_strict_json(result.meta, f"{where} meta")

        source = self._parts if self._parts is not None else InMemoryParts()
        return source.get(label, checked, reads)

    @property
    def sinks(self) -> dict[str, Any]:
        """The sinks this stage instance opened, by output name."""
        return dict(self._sinks)

    @classmethod
    def interface(cls) -> dict[str, Any]:
        """JSON description of inputs and outputs, used to check a pipeline without importing the stage."""
        return {
            "inputs": {k: v.describe() for k, v in cls.inputs.items()},
            "outputs": {k: v.describe() for k, v in cls.outputs.items()},
            "resources": {k: str(Path(v).resolve()) for k, v in cls.resources.items()},
            "figures": list(cls.figures),
            "in_process": bool(cls.in_process or cls.cheap),
            "cheap": bool(cls.cheap),
        }


def to_strict_json(value: Any, where: str) -> Any:
    """Return ``value`` as plain JSON types; numpy scalars and arrays convert, NaN/Inf and objects are errors."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"{where}: {value!r} is not allowed in strict JSON (store NaN in an array instead)")
        return float(value)
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise ValueError(f"{where}: key {k!r} is not a string")
            out[k] = to_strict_json(v, f"{where}.{k}")
        return out
    if isinstance(value, (list, tuple)):
        return [to_strict_json(v, f"{where}[{i}]") for i, v in enumerate(value)]
    tolist = getattr(value, "tolist", None)  # numpy scalars and small arrays
    if tolist is not None and type(value).__module__ == "numpy":
        return to_strict_json(tolist(), where)
    raise ValueError(f"{where}: {type(value).__name__} is not JSON (use str, int, float, bool, list, dict)")


def check_output(
    where: str,
    spec: Output,
    dtype: Any,
    shape: tuple[int, ...],
    dims: dict[str, Any] | None = None,
    name: str = "",
    frames: bool = True,
) -> None:
    """Check one output's dtype and shape against its declaration; ``dims`` collects named dimensions across
    outputs (``frames=False``: the first axis is not known yet, as for a sink just opened)."""
    import numpy as np

    dtype = np.dtype(dtype)
    if spec.file_suffix is not None and (dtype != np.uint8 or len(shape) != 1):
        raise TypeError(f"{where}: a file output is bytes (a uint8 sink with row_shape ()), got {dtype} {shape}")
    if dtype.kind not in spec.kind:
        raise TypeError(f"{where}: dtype {dtype} is not of kind {'/'.join(DTYPE_KINDS.get(k, k) for k in spec.kind)}")
    if spec.dtype is not None and dtype != np.dtype(spec.dtype):
        raise TypeError(f"{where}: dtype {dtype}, expected {spec.dtype}")
    if spec.ndim is not None and len(shape) != spec.ndim:
        raise ValueError(f"{where}: {len(shape)} dimensions {tuple(shape)}, expected {spec.ndim}")
    for axis, want in enumerate(spec.shape or ()):
        got = shape[axis]
        if axis == 0 and not frames:
            continue
        if isinstance(want, int) and got != want:
            raise ValueError(f"{where}: axis {axis} has size {got}, expected {want} (shape {tuple(shape)})")
        if isinstance(want, str) and dims is not None:
            if want in dims and dims[want][0] != got:
                raise ValueError(
                    f"{where}: dimension '{want}' is {got} here but {dims[want][0]} in output '{dims[want][1]}'"
                )
            dims.setdefault(want, (got, name))


def validate_result(stage: str, cls: type[Stage], result: Any) -> dict[str, Any]:
    """Check a run() result against the class's output schema; return the outputs as numpy arrays (or the
    output sinks returned, finished).

    Raises StageFailed-worthy ``TypeError``/``ValueError`` naming the stage and output: a schema violation is a
    bug in the stage, not in the user's data.
    """
    import numpy as np

    from msflow.sinks import OutputSink

    if not isinstance(result, Result):
        raise TypeError(f"stage '{stage}': run() returned {type(result).__name__}, expected msflow.Result")
    arrays: dict[str, Any] = {}
    unknown = set(result.arrays) - set(cls.outputs)
    if unknown:
        raise ValueError(
            f"stage '{stage}': run() returned undeclared outputs {sorted(unknown)}; declared: {sorted(cls.outputs)}"
        )
    dims: dict[str, tuple[int, str]] = {}
    for name, spec in cls.outputs.items():
        where = f"stage '{stage}', output '{name}'"
        if name not in result.arrays or result.arrays[name] is None:
            if spec.optional:
                continue
            raise ValueError(f"{where}: missing (declared and not optional)")
        value = result.arrays[name]
        if isinstance(value, OutputSink):
            if value.name != name:
                raise ValueError(f"{where}: got the sink of output '{value.name}'")
            value.finish()
            check_output(where, spec, value.dtype, value.shape, dims, name)
            arrays[name] = value
            continue
        if spec.file_suffix is not None:
            if not isinstance(value, (bytes, bytearray, memoryview)):
                raise TypeError(f"{where}: a file output must be bytes, got {type(value).__name__}")
            arrays[name] = np.frombuffer(bytes(value), dtype=np.uint8)
            continue
        arr = np.asarray(value)
        check_output(where, spec, arr.dtype, arr.shape, dims, name)
        arrays[name] = np.asarray(arr, order="C")
    return arrays


__all__ = ["Stage", "Params", "Input", "Output", "Result", "Files", "UserError", "to_strict_json", "validate_result"]
