"""Resolving a pipeline against its stage classes: code fingerprints, interfaces, canonical params, input checks.

A stage class is imported only when its code fingerprint has no memoised interface or when a params set has not
been validated before under that fingerprint; a no-op run therefore imports no stage module (and no numpy).
"""

from __future__ import annotations

import importlib
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from msflow.errors import UserError, field_path
from msflow.fingerprint import PROJECT_ROOTS, STDLIB, CodeIndex, distribution_versions
from msflow.hashing import json_hash
from msflow.spec import FilesRef, Pipeline, StageNode, StageRef, rel_to, suggest
from msflow.syspath import holds_installed_packages

if TYPE_CHECKING:
    from msflow.stage import Stage

PYTHON = f"{sys.version_info.major}.{sys.version_info.minor}"


@dataclass
class StagePlan:
    name: str
    uses: str
    code: dict[str, Any]  # {"modules": {relpath: digest}, "dists": {name: version}, "python": "3.11"}
    code_digest: str
    interface: dict[str, Any]  # {"inputs": {...}, "outputs": {...}}
    params: dict[str, Any]  # canonical: validated, defaults filled in


def ensure_importable(root: str | Path) -> None:
    """Put the project root first on sys.path so its stage modules import (also in worker processes)."""
    root = str(root)
    PROJECT_ROOTS.add(root.rstrip("/") + "/")
    if sys.path[:1] != [root]:
        if root in sys.path:
            sys.path.remove(root)
        sys.path.insert(0, root)


_IMPORTED: dict[str, str] = {}  # module name -> stat signature of its file when this process imported it


def forget_stale_modules(root: str | Path | None = None) -> None:
    """Drop project modules from sys.modules when any project file changed since it was imported.

    A long-lived process (a notebook, a Dask worker) would otherwise run yesterday's code under today's key.
    Everything imported from the project goes at once: a changed helper module invalidates its importers too.
    """
    from msflow.hashing import stat_signature

    stale = False
    for name, sig in list(_IMPORTED.items()):
        module = sys.modules.get(name)
        path = getattr(module, "__file__", None)
        try:
            current = stat_signature(path) if path else None
        except OSError:
            current = None
        outside = root is not None and path is not None and not path.startswith(str(root).rstrip("/") + "/")
        if module is None or current != sig or outside:
            stale = True
            break
    if stale:
        for name in list(_IMPORTED):
            sys.modules.pop(name, None)
            _SEEN_MODULES.discard(name)
        _IMPORTED.clear()
        importlib.invalidate_caches()


_SEEN_MODULES: set[str] = set()


def _remember_project_modules() -> None:
    from msflow.hashing import stat_signature

    for name, module in list(sys.modules.items()):
        if name in _SEEN_MODULES:
            continue
        _SEEN_MODULES.add(name)
        path = getattr(module, "__file__", None)
        if (
            path
            and name not in _IMPORTED
            and name.split(".")[0] != "msflow"
            and any(path.startswith(root) for root in PROJECT_ROOTS)
            and not holds_installed_packages(path)
        ):
            try:
                _IMPORTED[name] = stat_signature(path)
            except OSError:
                pass


def import_stage_class(
    uses: str, *, file: str | None = None, stage: str | None = None, root: str | Path | None = None
) -> type[Stage]:
    """Import ``package.module:Class`` (re-importing edited project modules) and check it is a Stage subclass."""
    from msflow.stage import Stage

    module_name, _, cls_name = uses.partition(":")
    forget_stale_modules(root)
    try:
        module = importlib.import_module(module_name)
        _remember_project_modules()
    except ModuleNotFoundError as exc:
        missing = exc.name or module_name
        what = (
            "unknown stage module"
            if missing == module_name or module_name.startswith(missing + ".")
            else f"module '{module_name}' needs '{missing}', which is not installed;"
        )
        raise UserError(
            f"{what} '{module_name}'" if what.startswith("unknown") else f"{what} {exc}",
            file=file,
            stage=stage,
            field="uses",
        ) from None
    except SyntaxError as exc:
        raise UserError(
            f"syntax error in {exc.filename} line {exc.lineno}: {exc.msg}", file=file, stage=stage, field="uses"
        ) from None
    except Exception as exc:  # the module raised while importing
        raise UserError(
            f"importing '{module_name}' failed: {type(exc).__name__}: {exc}", file=file, stage=stage, field="uses"
        ) from None
    cls = getattr(module, cls_name, None)
    if cls is None:
        classes = sorted(
            n for n, v in vars(module).items() if isinstance(v, type) and issubclass(v, Stage) and v is not Stage
        )
        raise UserError(
            f"module '{module_name}' has no class '{cls_name}'{suggest(cls_name, classes)}; stages "
            f"there: {classes or 'none'}",
            file=file,
            stage=stage,
            field="uses",
        )
    if not (isinstance(cls, type) and issubclass(cls, Stage)):
        raise UserError(f"'{uses}' is not a msflow Stage subclass", file=file, stage=stage, field="uses")
    return cls


def canonical_params(cls: type[Stage], raw: dict[str, Any], *, file: str, stage: str) -> dict[str, Any]:
    from pydantic import ValidationError

    from msflow.stage import to_strict_json

    try:
        validated = cls.Params(**raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = field_path(err.get("loc", ()))
        if err.get("type") == "extra_forbidden":
            allowed = sorted(cls.Params.model_fields)
            msg = f"unknown parameter '{loc}'{suggest(loc, allowed)}; parameters: {', '.join(allowed) or 'none'}"
        elif err.get("type") == "missing":
            msg = "required parameter is missing"
        elif err.get("type") == "value_error" and "error" in err.get("ctx", {}):
            # the stage's own validator worded it (and quotes what it refuses, often better than the raw input)
            msg = str(err["ctx"]["error"])
        else:
            msg = f"{err.get('msg', 'invalid')} (got {err.get('input')!r})"
        raise UserError(msg, file=file, stage=stage, field=f"params.{loc}" if loc else "params") from None
    except TypeError as exc:
        raise UserError(f"invalid params: {exc}", file=file, stage=stage, field="params") from None
    try:
        canonical: dict[str, Any] = to_strict_json(validated.model_dump(mode="json"), "params")
        return canonical
    except ValueError as exc:
        raise UserError(str(exc), file=file, stage=stage, field="params") from None


def resolve(pipeline: Pipeline, memo: dict[str, Any]) -> dict[str, StagePlan]:
    """Fingerprint, interface and canonical params for every stage; checks every input against its declaration."""
    index = CodeIndex(pipeline.root, memo.setdefault("code", {}))
    interfaces: dict[str, Any] = memo.setdefault("interfaces", {})
    params_memo: dict[str, Any] = memo.setdefault("params", {})
    plans: dict[str, StagePlan] = {}
    ensure_importable(pipeline.root)
    for name, node in pipeline.stages.items():
        plans[name] = _plan_stage(pipeline, name, node, index, interfaces, params_memo)
    for name in pipeline.stages:
        check_inputs(pipeline, plans, name)
    _check_publish_outputs(pipeline, plans)
    return plans


def _plan_stage(
    pipeline: Pipeline,
    name: str,
    node: StageNode,
    index: CodeIndex,
    interfaces: dict[str, Any],
    params_memo: dict[str, Any],
) -> StagePlan:
    """One stage's plan; its class is imported only when the interface or the params are not memoised yet."""
    file = str(pipeline.path)
    code = _stage_code(pipeline, name, node, index)
    code_digest = json_hash(code)
    iface_key = json_hash([node.uses, code_digest])
    interface = interfaces.get(iface_key)
    cls: type[Stage] | None = None
    if interface is None or "in_process" not in interface:  # memoised before interfaces said it: once more
        cls = import_stage_class(node.uses, file=file, stage=name, root=pipeline.root)
        interface = _class_interface(cls, pipeline.root)
        interfaces[iface_key] = interface
    _check_resources(pipeline, name, node, interface)
    try:
        params_key: str | None = json_hash([iface_key, node.params])
    except ValueError:  # NaN or Inf (`-S stage.x=.nan`): no memo key; canonical_params names the field
        params_key = None
    params = params_memo.get(params_key) if params_key else None
    if params is None:
        cls = cls or import_stage_class(node.uses, file=file, stage=name, root=pipeline.root)
        params = canonical_params(cls, node.params, file=file, stage=name)
        if params_key:
            params_memo[params_key] = params
    return StagePlan(name, node.uses, code, code_digest, interface, params)


def _stage_code(pipeline: Pipeline, name: str, node: StageNode, index: CodeIndex) -> dict[str, Any]:
    """The code a stage runs: its project modules' digests, its third-party distributions and the Python version."""
    closure = _module_closure(pipeline, name, node, index)
    try:
        dists = distribution_versions(closure["external"], index.memo, pipeline.root)
    except UserError as exc:
        raise exc.located(file=str(pipeline.path), stage=name, field="uses") from None
    return {"modules": closure["modules"], "dists": dists, "python": PYTHON}


def _module_closure(pipeline: Pipeline, name: str, node: StageNode, index: CodeIndex) -> dict[str, Any]:
    """The project modules a stage's module imports; an installed module counts as one external distribution."""
    file = str(pipeline.path)
    module_name = node.uses.partition(":")[0]
    if index.project_file(module_name) is not None:
        try:
            return index.closure(module_name)
        except UserError as exc:
            raise exc.located(file=file, stage=name, field="uses") from None
    import importlib.util

    top = module_name.split(".")[0]
    if top in STDLIB:
        raise UserError(
            f"'{node.uses}' is not a msflow Stage subclass: '{top}' is Python's standard library",
            file=file,
            stage=name,
            field="uses",
        )
    if importlib.util.find_spec(top) is None:
        raise UserError(
            f"unknown stage module '{module_name}' (not in the project at {pipeline.root} and not installed)",
            file=file,
            stage=name,
            field="uses",
        )
    return {"modules": {}, "external": [top]}


def _class_interface(cls: type[Stage], root: Path) -> dict[str, Any]:
    """A stage class's interface, its resource paths made relative to the project root (so the memo can move)."""
    interface = cls.interface()
    interface["resources"] = {k: rel_to(Path(v), root) for k, v in interface.get("resources", {}).items()}
    return interface


def _check_resources(pipeline: Pipeline, name: str, node: StageNode, interface: dict[str, Any]) -> None:
    """Every data file the stage class declares as a resource exists (checked even when the interface is memoised)."""
    for resource, path in interface.get("resources", {}).items():
        if not (pipeline.root / path).exists():
            raise UserError(
                f"{node.uses} needs its data file '{path}' (resource '{resource}'), which is missing",
                file=str(pipeline.path),
                stage=name,
                field="uses",
            )


def _check_publish_outputs(pipeline: Pipeline, plans: dict[str, StagePlan]) -> None:
    """Every publish target names an output its stage declares."""
    for target in pipeline.publish:
        stage, _, output = target.partition(".")
        outputs = plans[stage].interface["outputs"]
        if output not in outputs:
            raise UserError(
                f"stage '{stage}' has no output '{output}'{suggest(output, outputs)}; outputs: {', '.join(outputs)}",
                file=str(pipeline.path),
                field=f"publish.{target}",
            )


def check_inputs(pipeline: Pipeline, plans: dict[str, StagePlan], name: str) -> None:
    """Check a stage's inputs against its declared ones: none unknown, none required missing, each of its kind."""
    file = str(pipeline.path)
    node = pipeline.stages[name]
    declared: dict[str, Any] = plans[name].interface["inputs"]
    _check_no_unknown_inputs(node, declared, file=file, stage=name)
    for input_name, decl in declared.items():
        where = f"inputs.{input_name}"
        ref = node.inputs.get(input_name)
        if ref is None:
            if not decl["optional"]:
                raise UserError(
                    f"missing required input '{input_name}' ({decl['kind']})", file=file, stage=name, field=where
                )
            continue
        if decl["kind"] == "files":
            if not isinstance(ref, FilesRef):
                raise UserError(
                    f"expects data files ({{path: ...}} or {{label: path}}), got stage reference '{ref.describe()}'",
                    file=file,
                    stage=name,
                    field=where,
                )
            continue
        _check_stage_input(ref, decl, plans, file=file, stage=name, where=where)


def _check_no_unknown_inputs(node: StageNode, declared: dict[str, Any], *, file: str, stage: str) -> None:
    """Every input the pipeline gives a stage is one its class declares."""
    for input_name in node.inputs:
        if input_name not in declared:
            raise UserError(
                f"unknown input '{input_name}'{suggest(input_name, declared)}; "
                f"{node.uses} takes: {', '.join(declared) or 'no inputs'}",
                file=file,
                stage=stage,
                field=f"inputs.{input_name}",
            )


def _check_stage_input(
    ref: StageRef | FilesRef, decl: dict[str, Any], plans: dict[str, StagePlan], *, file: str, stage: str, where: str
) -> None:
    """An array or artifact input is a reference to an upstream stage of the shape its kind needs."""
    if not isinstance(ref, StageRef):
        raise UserError(
            "expects a stage reference ('stage' or 'stage.output'), got data files",
            file=file,
            stage=stage,
            field=where,
        )
    upstream = plans[ref.stage].interface["outputs"]
    if ref.output is not None and ref.output not in upstream:
        raise UserError(
            f"stage '{ref.stage}' has no output '{ref.output}'{suggest(ref.output, upstream)}; "
            f"outputs: {', '.join(upstream)}",
            file=file,
            stage=stage,
            field=where,
        )
    if decl["kind"] == "array" and ref.output is None:
        raise UserError(
            f"expects one array: write '{ref.stage}.<output>' (outputs: {', '.join(upstream)})",
            file=file,
            stage=stage,
            field=where,
        )
    if decl["kind"] == "artifact":
        _check_whole_artifact(ref, decl, plans, file=file, stage=stage, where=where)


def _check_whole_artifact(
    ref: StageRef, decl: dict[str, Any], plans: dict[str, StagePlan], *, file: str, stage: str, where: str
) -> None:
    """An artifact input names a whole upstream stage that has every output the input requires."""
    if ref.output is not None:
        raise UserError(
            f"expects a whole artifact: write '{ref.stage}' instead of '{ref.describe()}'",
            file=file,
            stage=stage,
            field=where,
        )
    upstream = plans[ref.stage].interface["outputs"]
    missing = [r for r in decl["requires"] if r not in upstream]
    if missing:
        raise UserError(
            f"stage '{ref.stage}' ({plans[ref.stage].uses}) lacks outputs {missing} this input requires",
            file=file,
            stage=stage,
            field=where,
        )
