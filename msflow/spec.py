"""pipeline.yaml: parsing, ``${var}`` substitution, ``-S`` overrides and validation into a resolved pipeline.

Everything the user can get wrong here raises UserError naming the file, the stage and the field. Nothing in this
module imports numpy, zarr or stage code: a no-op run goes through it on every invocation.
"""

from __future__ import annotations

import copy
import difflib
import glob as globlib
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path, PurePath
from typing import TYPE_CHECKING, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError, field_validator

from msflow.errors import UserError, display_path, strip_tags
from msflow.hashing import stat_signature
from msflow.variables import VAR_RE, untrue_names

if TYPE_CHECKING:
    from msflow.stores.base import Store

FORMAT_VERSION = 1
NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")
REF_RE = re.compile(r"^(?P<stage>[A-Za-z_][A-Za-z0-9_\-]*)(?:\.(?P<output>[A-Za-z_][A-Za-z0-9_]*))?$")
USES_RE = re.compile(
    r"^(?P<module>[A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)*):(?P<cls>[A-Za-z_][A-Za-z0-9_]*)$"
)
GLOB_CHARS = set("*?[")


# ---------------------------------------------------------------------------------------------------------- models
class StageSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")

    uses: str
    inputs: dict[str, Any] = {}
    params: dict[str, Any] = {}
    description: str | None = None

    @field_validator("uses")
    @classmethod
    def _uses_form(cls, value: str) -> str:
        if not USES_RE.match(value):
            raise ValueError(f"'{value}' is not of the form package.module:Class")
        return value


class PipelineSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")

    version: Literal[1] = 1
    store: str | None = None
    store_options: dict[str, Any] = {}
    vars: dict[str, Any] = {}
    stages: dict[str, StageSpec]
    publish: dict[str, str] = {}
    summary: list[str] = []

    @field_validator("summary", mode="before")
    @classmethod
    def _one_entry(cls, value: Any) -> Any:
        return [value] if isinstance(value, str) else value  # `summary: eval.mouth_error` is a list of one


# ---------------------------------------------------------------------------------------------------------- refs
@dataclass(frozen=True)
class StageRef:
    """An input taken from another stage: its whole artifact (output None) or one output."""

    stage: str
    output: str | None = None

    def describe(self) -> str:
        return self.stage + (f".{self.output}" if self.output else "")


@dataclass(frozen=True)
class FilesRef:
    """Data files: label -> absolute path (``form`` says how they were written), and each label's fields
    (parsed from the file name by a ``pattern``, or written beside the path)."""

    files: tuple[tuple[str, str], ...]
    form: str  # "path" | "glob" | "mapping"
    fields: tuple[tuple[str, tuple[tuple[str, str], ...]], ...] = ()
    #: glob: the folders whose listing chose the files (a file added there changes the input); None: too many
    listed: tuple[str, ...] | None = ()

    def describe(self) -> str:
        return ", ".join(p for _, p in self.files)

    def fields_by_label(self) -> dict[str, dict[str, str]]:
        return {label: dict(values) for label, values in self.fields if values}


@dataclass
class StageNode:
    name: str
    uses: str
    params: dict[str, Any]
    inputs: dict[str, StageRef | FilesRef]
    description: str | None = None

    @cached_property
    def deps(self) -> list[str]:
        """Upstream stages, sorted (computed once: the scheduler asks for them often)."""
        return sorted({r.stage for r in self.inputs.values() if isinstance(r, StageRef)})


@dataclass
class Pipeline:
    path: Path  # the pipeline file (absolute)
    root: Path  # the project root: paths in keys are relative to it
    store: str  # store location (absolute path or URL)
    stages: dict[str, StageNode]
    publish: dict[str, str] = field(default_factory=dict)
    overrides: tuple[str, ...] = ()
    store_options: dict[str, Any] = field(default_factory=dict)
    source_signature: str = ""  #: stat signature of the pipeline file when it was read
    summary: tuple[str, ...] = ()  #: ``stage.metric`` patterns printed when a run ends (msflow.summary)
    #: what the user should know before running it: published names an override made untrue (msflow.variables)
    warnings: tuple[str, ...] = ()

    def open_store(self) -> Store:
        from msflow.stores import open_store

        return open_store(self.store, self.store_options, self.path.parent / ".msflow" / "cache")

    @property
    def rel_path(self) -> str:
        return rel_to(self.path, self.root)

    def files_refs(self) -> list[FilesRef]:
        """Every data-files input of every stage."""
        return [ref for node in self.stages.values() for ref in node.inputs.values() if isinstance(ref, FilesRef)]


def rel_to(path: Path, root: Path) -> str:
    try:
        return Path(path).resolve().relative_to(root).as_posix()
    except ValueError:
        return Path(path).resolve().as_posix()


# ---------------------------------------------------------------------------------------------------------- yaml
class UniqueKeyLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # type: ignore[misc]
    """Safe loader that refuses duplicate mapping keys (PyYAML would silently keep the last)."""


def _construct_mapping(loader: Any, node: Any, deep: bool = False) -> Any:
    seen: dict[Any, Any] = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if isinstance(key, (list, dict)):
            raise yaml.constructor.ConstructorError(None, None, "a mapping key must be a scalar", key_node.start_mark)
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key '{key}' (first at line {seen[key].line + 1})", key_node.start_mark
            )
        seen[key] = key_node.start_mark
    return loader.construct_mapping_plain(node, deep=deep)


UniqueKeyLoader.construct_mapping_plain = yaml.SafeLoader.construct_mapping
UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def parse_yaml(text: str, file: str) -> Any:
    try:
        return yaml.load(text, Loader=UniqueKeyLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        context = getattr(exc, "context", None)
        detail = f"{context}: {problem}" if context and "duplicate" not in str(problem) else problem
        raise UserError(f"invalid YAML{where}: {detail}", file=file) from None
    except (ValueError, TypeError, OverflowError, RecursionError) as exc:  # e.g. bad timestamps, deep nesting
        raise UserError(f"invalid YAML: {exc}", file=file) from None


# ---------------------------------------------------------------------------------------------------------- vars
def substitute_vars(value: Any, variables: dict[str, Any], file: str, where: str) -> Any:
    """Replace ``${name}`` everywhere, mapping keys included; a string that is exactly ``${name}`` takes the
    variable's value and type (a key, its text)."""
    if isinstance(value, str):
        whole = VAR_RE.fullmatch(value)
        if whole:
            return _lookup_var(whole.group(1), variables, file, where)
        return _splice(value, variables, file, where)
    if isinstance(value, dict):
        return _substitute_mapping(value, variables, file, where)
    if isinstance(value, list):
        return [substitute_vars(v, variables, file, f"{where}[{i}]") for i, v in enumerate(value)]
    return value


def _splice(text: str, variables: dict[str, Any], file: str, where: str) -> str:
    """``text`` with each ``${name}`` replaced by the variable's value as text (a mapping or list cannot be)."""

    def repl(m: re.Match[str]) -> str:
        got = _lookup_var(m.group(1), variables, file, where)
        if isinstance(got, (dict, list)):
            raise UserError(
                f"variable '${{{m.group(1)}}}' holds a {type(got).__name__} and cannot be spliced into a string",
                file=file,
                field=where,
            )
        return str(got)

    return VAR_RE.sub(repl, text)


def _substitute_mapping(value: dict[Any, Any], variables: dict[str, Any], file: str, where: str) -> dict[Any, Any]:
    """A mapping's values and its keys (``{${mood}: 1.0}``); two keys that become one are an error, not a silent
    overwrite."""
    out: dict[Any, Any] = {}
    for key, item in value.items():
        new_key = _splice(key, variables, file, f"{where}.{key}") if isinstance(key, str) else key
        if new_key in out:
            raise UserError(f"two keys become '{new_key}' once the variables are filled in", file=file, field=where)
        out[new_key] = substitute_vars(item, variables, file, f"{where}.{new_key}")
    return out


#: ``${name:filter}``: the variable's value read as a path, reduced to a part of it
VAR_FILTERS = {"stem": lambda path: PurePath(path).stem, "name": lambda path: PurePath(path).name}


def _lookup_var(reference: str, variables: dict[str, Any], file: str, where: str) -> Any:
    name, _, filter_name = reference.partition(":")
    if name not in variables:
        hint = suggest(name, variables)
        raise UserError(
            f"unknown variable '${{{name}}}'{hint}; defined: {sorted(variables) or 'none'}"
            + (" (a variable can use the ones declared before it)" if where.startswith("vars.") else ""),
            file=file,
            field=where,
        )
    value = variables[name]
    if not filter_name:
        return value
    if filter_name not in VAR_FILTERS or not isinstance(value, str):
        problem = "a path (a string)" if filter_name in VAR_FILTERS else f"one of {sorted(VAR_FILTERS)}"
        raise UserError(f"'${{{reference}}}': the filter after ':' needs {problem}", file=file, field=where)
    return VAR_FILTERS[filter_name](value)


def suggest(name: str, options: Iterable[Any]) -> str:
    """' (did you mean ...?)' for the option closest to ``name``, or ''."""
    close = difflib.get_close_matches(str(name), [str(o) for o in options], n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def unknown_stage(name: str, stages: Iterable[str]) -> str:
    """ "unknown stage 'NAME' (did you mean ...?); stages: [...]": the nearest name when one is close, and always
    the names there are (a name like no other gets no suggestion, but still a list to pick from)."""
    return f"unknown stage '{name}'{suggest(name, stages)}; stages: {sorted(stages)}"


# ---------------------------------------------------------------------------------------------------------- overrides
def parse_override(text: str) -> tuple[list[str], Any]:
    """``stage.param=value`` (nested: ``stage.a.b=value``; ``vars.name=value``) -> (path, YAML-parsed value)."""
    if "=" not in text:
        raise UserError(f"bad override '{text}': expected stage.param=value", field="-S")
    target, _, raw = text.partition("=")
    parts = target.strip().split(".")
    if len(parts) < 2 or not all(parts):
        raise UserError(f"bad override '{text}': the target must be stage.param (got '{target}')", field="-S")
    try:
        value = yaml.load(raw, Loader=UniqueKeyLoader) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    except UnicodeEncodeError:  # bytes that are not UTF-8, most likely a file name: msflow records text as UTF-8
        raise UserError(
            f"bad override '{escaped(text)}': not UTF-8 text (rename the file it names)", field="-S"
        ) from None
    return parts, value


def apply_overrides(raw: dict[str, Any], overrides: tuple[str, ...], file: str) -> None:
    stages: dict[str, Any] = raw["stages"] if isinstance(raw.get("stages"), dict) else {}
    for text in overrides:
        try:
            parts, value = parse_override(text)
        except UserError as exc:
            raise exc.located(file=file) from None
        head, rest = parts[0], parts[1:]
        if head == "vars":
            raw.setdefault("vars", {})
            if not isinstance(raw["vars"], dict):
                raise UserError("'vars' must be a mapping", file=file, field="vars")
            if rest[0] not in raw["vars"]:  # a typo would otherwise run with the default silently
                from msflow.hints import pipelines_with_variable

                declared, path = raw["vars"], Path(file)
                raise UserError(
                    f"override '{text}': unknown variable '{rest[0]}'{suggest(rest[0], declared)}; "
                    f"the pipeline's vars: {sorted(map(str, declared)) or 'none'}"
                    + pipelines_with_variable(rest[0], find_root(path.resolve().parent), path),
                    file=file,
                    field="-S",
                )
            if value == "" and len(rest) == 1:  # `-S vars.take="$clip"` with $clip unset: never a file named ""
                raise UserError(
                    f"override '{text}': no value for variable '{rest[0]}' (an unset shell variable?); give it "
                    f"one, or leave the -S out to keep the pipeline's ({raw['vars'][rest[0]]!r})",
                    file=file,
                    field="-S",
                )
            _set_path(raw["vars"], rest, value)
            continue
        if head not in stages:
            raise UserError(
                f"override '{text}': {unknown_stage(head, stages)}",
                file=file,
                field="-S",
            )
        stage = stages[head]
        if not isinstance(stage, dict):
            continue  # reported by validation
        params = stage.setdefault("params", {})
        if not isinstance(params, dict):
            raise UserError("'params' must be a mapping", file=file, stage=head, field="params")
        _set_path(params, rest, value)


def _set_path(container: dict[str, Any], path: list[str], value: Any) -> None:
    """container[a][b]... = value for path [a, b, ...], creating (or replacing non-mapping) levels."""
    cursor = container
    for key in path[:-1]:
        if not isinstance(cursor.get(key), dict):
            cursor[key] = {}
        cursor = cursor[key]
    cursor[path[-1]] = value


# ---------------------------------------------------------------------------------------------------------- loading
def find_root(pipeline_dir: Path) -> Path:
    """The project root: the nearest ancestor holding pyproject.toml or .git, else the pipeline's folder."""
    for candidate in (pipeline_dir, *pipeline_dir.parents):
        if (candidate / "pyproject.toml").exists() or (candidate / ".git").exists():
            return candidate
    return pipeline_dir


def load_pipeline(
    path: str | Path, overrides: tuple[str, ...] | list[str] = (), publish_dir: str | Path | None = None
) -> Pipeline:
    """Read, substitute, override and validate a pipeline file; resolve data-file refs (not stage classes).
    ``publish_dir``: publish entries are relative to it (and may leave the project), not to the pipeline file."""
    path = Path(path)
    file = str(path)
    text, signature = _read_pipeline_file(path, file)
    raw = _top_level_mapping(text, file)
    overrides = tuple(overrides)
    written = copy.deepcopy(raw) if overrides else raw
    apply_overrides(raw, overrides, file)
    substituted = _substituted(raw, file)
    _reject_nul_characters(substituted, file)
    spec = _validated_spec(substituted, file)
    pipeline_dir = path.resolve().parent
    root = find_root(pipeline_dir)
    store = _store_location(spec.store, pipeline_dir)
    nodes = _stage_nodes(spec, pipeline_dir, root, file)
    _check_references(nodes, spec.publish, file)
    check_cycles(nodes, file)
    publish = publish_targets(spec.publish, root, pipeline_dir, publish_dir, file)
    _check_publish_reads_nothing(publish, spec.publish, read_paths(path.resolve(), store, nodes), file)
    _check_summary(spec.summary, nodes, file)
    warnings = untrue_names(written, raw, [parse_override(o) for o in overrides], publish) if overrides else []
    return Pipeline(
        path.resolve(),
        root,
        store,
        nodes,
        publish,
        overrides,
        spec.store_options,
        signature,
        tuple(spec.summary),
        tuple(warnings),
    )


def _nearest_above(path: Path) -> str:
    """A hint naming a file of the same name in a folder above (``msflow run`` typed in ``out/``), or ""."""
    folder = path.absolute().parent
    for above in folder.parents:
        candidate = above / path.name
        if candidate.is_file():
            shown = os.path.relpath(candidate)  # ../pipeline.yaml, as the user would type it
            return f"; the nearest is {shown} (give it as the FILE argument)"
    return ""


def _read_pipeline_file(path: Path, file: str) -> tuple[str, str]:
    """The pipeline file's text and its stat signature when it was read."""
    if not path.exists():
        from msflow.hints import same_name_in_project

        elsewhere = same_name_in_project(path.name, find_root(path.absolute().parent), path)
        raise UserError("pipeline file not found" + (_nearest_above(path) or elsewhere), file=file)
    if path.is_dir():
        raise UserError("is a directory, expected a pipeline YAML file", file=file)
    try:
        signature = stat_signature(path)
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot read: {exc}", file=file) from None
    return text, signature


def _top_level_mapping(text: str, file: str) -> dict[str, Any]:
    """Parse the pipeline YAML, which must be a non-empty mapping with string keys."""
    raw = parse_yaml(text, file)
    if raw is None:
        raise UserError("the file is empty; it needs at least 'stages:'", file=file)
    if not isinstance(raw, dict):
        raise UserError(f"the top level must be a mapping with 'stages:', got {type(raw).__name__}", file=file)
    for key in raw:
        if not isinstance(key, str):
            raise UserError(f"top-level key {key!r} is not a string", file=file)
    return raw


def _substituted(raw: dict[str, Any], file: str) -> dict[str, Any]:
    """Every top-level entry with its ``${name}`` references replaced by the values in ``vars`` (a variable's own
    value may use the variables declared before it)."""
    variables = raw.get("vars", {})
    if not isinstance(variables, dict):
        raise UserError("'vars' must be a mapping of name: value", file=file, field="vars")
    resolved: dict[str, Any] = {}
    for name, value in variables.items():  # in file order: a variable may use those declared before it
        resolved[str(name)] = substitute_vars(value, resolved, file, f"vars.{name}")
    return {k: (resolved if k == "vars" else substitute_vars(v, resolved, file, k)) for k, v in raw.items()}


def _reject_nul_characters(value: Any, file: str, where: str = "") -> None:
    """A UserError for a string holding a NUL character (a YAML ``"\\0"``): no path can hold one, and the
    operating system would refuse it with a ValueError deep inside a file lookup."""
    if isinstance(value, str) and "\0" in value:
        raise UserError(f"a NUL character in {value!r}: no file name can hold one", file=file, field=where or None)
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, item in items:
        _reject_nul_characters(key, file, where)  # a label or stage name becomes part of a file name too
        _reject_nul_characters(item, file, f"{where}.{key}" if where else str(key))


def _validated_spec(substituted: dict[str, Any], file: str) -> PipelineSpec:
    """The pipeline's schema check, with at least one stage."""
    try:
        spec = PipelineSpec.model_validate(substituted)
    except ValidationError as exc:
        raise _user_error_from_validation(exc, file) from None
    if not spec.stages:
        raise UserError("'stages' is empty: a pipeline needs at least one stage", file=file, field="stages")
    return spec


def _store_location(store: str | None, pipeline_dir: Path) -> str:
    """The store as an absolute path (relative ones are to the pipeline's folder) or a URL, left as written."""
    store = store or ".msflow"
    if "://" not in store:
        store = str((pipeline_dir / store).resolve())
    return store


def _stage_nodes(spec: PipelineSpec, pipeline_dir: Path, root: Path, file: str) -> dict[str, StageNode]:
    """One node per stage, its name checked and its input references parsed (data files resolved)."""
    nodes: dict[str, StageNode] = {}
    for name, stage in spec.stages.items():
        if not NAME_RE.match(name):
            raise UserError(
                f"stage name '{name}' must start with a letter and hold only letters, digits, _ and -",
                file=file,
                stage=name,
            )
        inputs = {}
        for input_name, ref in stage.inputs.items():
            inputs[input_name] = parse_ref(ref, pipeline_dir, root, file, name, f"inputs.{input_name}")
        nodes[name] = StageNode(name, stage.uses, stage.params, inputs, stage.description)
    return nodes


def _check_references(nodes: dict[str, StageNode], publish: dict[str, str], file: str) -> None:
    """Stage inputs refer to known stages; publish targets are ``stage.output`` of known stages."""
    for name, node in nodes.items():
        for input_name, ref in node.inputs.items():
            if isinstance(ref, StageRef) and ref.stage not in nodes:
                raise UserError(
                    f"refers to unknown stage '{ref.stage}'{suggest(ref.stage, nodes)}; stages: {sorted(nodes)}",
                    file=file,
                    stage=name,
                    field=f"inputs.{input_name}",
                )
    for target in publish:
        m = REF_RE.match(target)
        if not m or not m.group("output") or m.group("stage") not in nodes:
            raise UserError(f"'{target}' is not stage.output of a known stage", file=file, field=f"publish.{target}")


def _check_summary(entries: list[str], nodes: dict[str, StageNode], file: str) -> None:
    """``summary:`` entries are ``stage.metric`` (the metric a shell-style pattern) of known stages."""
    for index, entry in enumerate(entries):
        stage, dot, metric = entry.partition(".")
        where = f"summary.{index}"  # as pydantic names list items
        if not dot or not metric or not NAME_RE.match(stage):
            raise UserError(
                f"'{entry}' is not stage.metric (the metric may be a pattern: eval.mouth_*)", file=file, field=where
            )
        if stage not in nodes:
            raise UserError(
                f"'{entry}': no stage '{stage}'{suggest(stage, nodes)}; stages: {sorted(nodes)}", file=file, field=where
            )


def publish_targets(
    entries: dict[str, str], root: Path, pipeline_dir: Path, publish_dir: str | Path | None, file: str
) -> dict[str, str]:
    """Absolute destinations of ``publish:`` entries. They must stay inside the project folder (or inside
    ``publish_dir``, the explicit way to publish elsewhere: ``msflow run --publish-dir DIR``), name files, not
    folders, and name each file once."""
    base = Path(publish_dir).resolve() if publish_dir is not None else pipeline_dir
    fence = base if publish_dir is not None else root
    where = f"--publish-dir {display_path(base)}" if publish_dir is not None else "the project folder"
    targets: dict[str, str] = {}
    for ref, value in entries.items():
        dest = (base / value).resolve()
        field_name = f"publish.{ref}"
        if dest != fence and fence not in dest.parents:
            raise UserError(
                f"'{value}' is outside {where} ({display_path(fence)}); publish inside it, or choose a folder "
                "explicitly with msflow run --publish-dir DIR",
                file=file,
                field=field_name,
            )
        if dest.is_dir() or str(value).endswith(("/", "\\")):
            raise UserError(f"'{value}' is a folder; name the file to write", file=file, field=field_name)
        if dest.name.startswith("."):  # `out/${name}.glb` with name empty; a hidden file would look unwritten
            raise UserError(
                f"'{value}' names a hidden file ('{dest.name}'): was a variable in it empty?",
                file=file,
                field=field_name,
            )
        clash = next((other for other, done in targets.items() if done == str(dest)), None)
        if clash is not None:
            raise UserError(
                f"'{value}' is also published by '{clash}': each file can hold one output", file=file, field=field_name
            )
        targets[ref] = str(dest)
    return targets


@dataclass(frozen=True)
class ReadPath:
    """A file or folder a run reads or keeps its state in, which no ``publish:`` entry may write onto (or into)."""

    path: Path
    what: str  #: how an error names it: "the pipeline file itself", "an input of stage 'track' (inputs.videos)"


#: how a pipeline's lock begins (msflow.records writes it): what tells a lock from any other .lock file
LOCK_MARK = "# pipeline.lock: written by msflow"


def lock_file(pipeline_file: Path) -> Path:
    """The lock beside a pipeline file: pipeline.lock for pipeline.yaml (pipeline.yaml.lock for other suffixes)."""
    if pipeline_file.suffix in (".yaml", ".yml"):
        return pipeline_file.with_suffix(".lock")
    return pipeline_file.with_name(pipeline_file.name + ".lock")


def read_paths(pipeline_file: Path, store: str, nodes: dict[str, StageNode]) -> list[ReadPath]:
    """What a run of the pipeline reads: the pipeline file, its lock, the store (and the .msflow folder beside
    the file, where the no-op fast path keeps its state), and every data file or folder of the stages' inputs."""
    found = [
        ReadPath(pipeline_file, "the pipeline file itself"),
        ReadPath(lock_file(pipeline_file), "the pipeline's lock file"),
    ]
    if "://" not in store:
        found.append(ReadPath(Path(store).resolve(), "msflow's store"))
    found.append(ReadPath(pipeline_file.parent / ".msflow", "msflow's state folder"))
    for name, node in nodes.items():
        for input_name, ref in node.inputs.items():
            if isinstance(ref, FilesRef):
                what = f"an input of stage '{name}' (inputs.{input_name})"
                found += [ReadPath(Path(p).resolve(), what) for _, p in ref.files]
    return found


def _check_publish_reads_nothing(
    targets: dict[str, str], entries: dict[str, str], reads: list[ReadPath], file: str
) -> None:
    """No publish target is (or lies inside) a file or folder the run reads, nor is another pipeline's file or
    lock: publishing runs after the stages, so it would replace the user's clip, a pipeline file or the store's
    state without a word (``-S vars.take=../out/clip_preview.mp4`` with the preview published to that very file)."""
    by_path = {r.path: r for r in reversed(reads)}  # the first one named wins, as a scan in order would find
    for ref, dest in targets.items():
        target = Path(dest)
        clash = next((by_path[p] for p in (target, *target.parents) if p in by_path), None)
        other = _msflow_file(target)
        if clash is None and other is not None:
            clash = ReadPath(target, other)
        if clash is not None:
            verb = "overwrite" if target == clash.path else "write into"
            raise UserError(
                f"'{entries[ref]}' would {verb} {display_path(clash.path)}, {clash.what}; publish to another file",
                file=file,
                field=f"publish.{ref}",
            )


def _msflow_file(path: Path) -> str | None:
    """What ``path`` is when it is an existing pipeline file (a YAML mapping with ``stages:``) or lock of another
    pipeline (``p_self.yaml`` publishing onto ``pipeline.yaml`` would turn it into a BVH), else None."""
    if path.suffix not in (".yaml", ".yml", ".lock") or not path.is_file():
        return None
    try:
        text = path.read_text(encoding="utf-8")
        if path.suffix == ".lock":
            return "another pipeline's lock file" if text.startswith(LOCK_MARK) else None
        raw = yaml.load(text, Loader=UniqueKeyLoader)
    except (OSError, ValueError, TypeError, RecursionError, yaml.YAMLError):  # not text, not YAML: no pipeline
        return None
    return "another pipeline file" if isinstance(raw, dict) and "stages" in raw else None


def parse_ref(ref: Any, base: Path, root: Path, file: str, stage: str, where: str) -> StageRef | FilesRef:
    """Turn one ``inputs:`` value into a StageRef or a FilesRef (files must exist)."""
    if isinstance(ref, str):
        m = REF_RE.match(ref)
        if m:
            return StageRef(m.group("stage"), m.group("output"))
        looks_like_path = "/" in ref or GLOB_CHARS & set(ref) or Path(ref).suffix
        hint = f"; data files are written {{path: {ref}}}" if looks_like_path else ""
        raise UserError(
            f"'{ref}' is not a stage reference (stage or stage.output){hint}", file=file, stage=stage, field=where
        )
    if isinstance(ref, dict):
        if not ref:
            raise UserError(
                "empty mapping: expected {path: file}, {glob: pattern} or {label: file, ...}",
                file=file,
                stage=stage,
                field=where,
            )
        if len({"path", "glob"} & set(ref)) == 1 and set(ref) <= FILE_FORM_KEYS:
            return _file_form(ref, base, root, file, stage, where)
        return _labelled_mapping(ref, base, file, stage, where)
    raise UserError(
        f"expected a stage reference or a file mapping, got {type(ref).__name__}", file=file, stage=stage, field=where
    )


FILE_FORM_KEYS = {"path", "glob", "pattern", "label"}
FIELD_RE = re.compile(r"\{([A-Za-z_][A-Za-z0-9_]*)\}")
FIELD_CHARS = r"[^_\-.\s/]+"


def _file_form(ref: dict[str, Any], base: Path, root: Path, file: str, stage: str, where: str) -> FilesRef:
    """``{path: file}`` or ``{glob: pattern}``, optionally with ``pattern`` (fields from file names) and
    ``label`` (a template of those fields naming each file; default: the file name without its suffix)."""
    spec = ref.get("path", ref.get("glob"))
    if not isinstance(spec, str) or not spec:
        raise UserError("the path must be a non-empty string", file=file, stage=stage, field=where)
    spec = os.path.expanduser(spec)  # as ``_existing_file`` does
    if "glob" in ref or GLOB_CHARS & set(spec):
        matches = sorted(globlib.glob(str(base / spec), recursive=True))
        matches = [_utf8_path(m, file, stage, where) for m in matches if Path(m).is_file() or Path(m).is_dir()]
        if not matches:
            raise UserError(
                f"the glob '{spec}' matches no files{_relative_hint(base, spec, bool(globlib.glob(spec, recursive=True)))}",
                file=file,
                stage=stage,
                field=where,
            )
        top = glob_top(base, spec)
        files, form = [(_label_below(Path(m), top, root), m) for m in matches], "glob"
        listed = glob_folders(base, spec)
    else:
        found = _existing_file(base, spec, file, stage, where)
        files, form = [(Path(found).name, found)], "path"
        listed = ()
    if "pattern" not in ref:
        if "label" in ref:
            raise UserError(
                "'label' needs a 'pattern' whose fields it uses", file=file, stage=stage, field=f"{where}.label"
            )
        return FilesRef(tuple(files), form, listed=listed)
    return replace(_labelled_by_pattern(files, ref, form, file, stage, where), listed=listed)


def glob_top(base: Path, pattern: str) -> Path:
    """The folder before a glob's first wildcard (``base`` when its first part has one)."""
    parts = Path(pattern).parts
    fixed = next((i for i, part in enumerate(parts) if GLOB_CHARS & set(part)), len(parts) - 1)
    return (base / Path(*parts[:fixed])) if fixed else base


def _label_below(path: Path, top: Path, root: Path) -> str:
    """A globbed file's label: its path below the glob's folder (its name for ``folder/*.mp4``), so the label,
    which the cache key holds, names the file and not where the folder is."""
    below = Path(os.path.relpath(path, top))
    return rel_to(path, root) if below.parts[:1] == ("..",) else below.as_posix()


def glob_folders(base: Path, pattern: str, limit: int = 1000) -> tuple[str, ...] | None:
    """The folders whose listings decide what a glob matches: the folder before its first wildcard and, when
    a folder part is a wildcard too, every folder below it. None when there are more than ``limit``."""
    top = glob_top(base, pattern)
    if not GLOB_CHARS & set("".join(Path(pattern).parts[:-1])):
        return (str(top.resolve()),)
    folders = []
    for dirpath, _, _ in os.walk(top):
        folders.append(str(Path(dirpath).resolve()))
        if len(folders) > limit:
            return None
    return tuple(folders)


def compile_label_pattern(pattern: str) -> re.Pattern[str]:
    """``{field}`` captures a non-empty part of a file name without separators (``_ - .``, spaces), ``*`` skips
    any text, the rest is literal: ``{speaker}_{sentence}_{expression}_*`` reads 1001_DFA_ANG_XX."""
    parts, names, pos = [], set(), 0
    for m in FIELD_RE.finditer(pattern):
        parts.append(".*?".join(re.escape(t) for t in pattern[pos : m.start()].split("*")))
        name = m.group(1)
        parts.append(f"(?P={name})" if name in names else f"(?P<{name}>{FIELD_CHARS})")
        names.add(name)
        pos = m.end()
    parts.append(".*?".join(re.escape(t) for t in pattern[pos:].split("*")))
    return re.compile("".join(parts))


def _labelled_by_pattern(
    files: list[tuple[str, str]], ref: dict[str, Any], form: str, file: str, stage: str, where: str
) -> FilesRef:
    pattern, template = ref["pattern"], ref.get("label")
    if not isinstance(pattern, str) or not FIELD_RE.search(pattern):
        raise UserError(
            f"pattern {pattern!r} has no {{field}}; e.g. '{{speaker}}_{{sentence}}_{{expression}}'",
            file=file,
            stage=stage,
            field=f"{where}.pattern",
        )
    regex = compile_label_pattern(pattern)
    if template is not None:
        unknown = set(FIELD_RE.findall(str(template))) - set(regex.groupindex)
        if not isinstance(template, str) or unknown or not FIELD_RE.search(template):
            raise UserError(
                f"label {template!r} must be a template of the pattern's fields "
                f"({', '.join(sorted(regex.groupindex))})",
                file=file,
                stage=stage,
                field=f"{where}.label",
            )
    labelled: dict[str, tuple[str, str]] = {}
    fields = []
    for _, path in files:
        name = Path(path).name
        stem = Path(name).stem
        m = regex.fullmatch(stem) or regex.fullmatch(name)
        if m is None:
            raise UserError(
                f"'{name}' does not match the label pattern '{pattern}'",
                file=file,
                stage=stage,
                field=f"{where}.pattern",
            )
        values = m.groupdict()
        label = FIELD_RE.sub(lambda g: values[g.group(1)], template) if template else stem
        if label in labelled:
            raise UserError(
                f"label '{label}' names two files: {Path(labelled[label][1]).name} and {name}; "
                "make 'label' use more fields",
                file=file,
                stage=stage,
                field=f"{where}.label",
            )
        labelled[label] = (label, path)
        fields.append((label, tuple(sorted(values.items()))))
    return FilesRef(tuple(labelled.values()), form, tuple(fields))


def _labelled_mapping(ref: dict[str, Any], base: Path, file: str, stage: str, where: str) -> FilesRef:
    """``{label: path}`` or ``{label: {path: file, field: value, ...}}``."""
    files, fields = [], []
    for label, value in ref.items():
        at = f"{where}.{label}"
        values: dict[str, str] = {}
        if isinstance(value, dict):
            values = {k: v for k, v in value.items() if k != "path"}
            bad = [
                k
                for k, v in values.items()
                if not isinstance(k, str) or not FIELD_RE.fullmatch(f"{{{k}}}") or isinstance(v, (dict, list))
            ]
            if "path" not in value or bad:
                raise UserError(
                    "a labelled file entry is a path or {path: file, field: value, ...} with scalar "
                    f"fields{f'; bad fields: {bad}' if bad else ''}",
                    file=file,
                    stage=stage,
                    field=at,
                )
            value = value["path"]
        if not isinstance(label, str) or not isinstance(value, str):
            raise UserError("a labelled file mapping needs label: path strings", file=file, stage=stage, field=at)
        files.append((label, _existing_file(base, value, file, stage, at)))
        fields.append((label, tuple(sorted((k, str(v)) for k, v in values.items()))))
    return FilesRef(tuple(files), "mapping", tuple(f for f in fields if f[1]))


def escaped(text: str) -> str:
    """``text`` with the bytes that are not UTF-8 (undecodable file-name bytes) written as escapes, printable."""
    return text.encode("utf-8", "backslashreplace").decode()


def _utf8_path(path: str, file: str, stage: str, where: str) -> str:
    """A data file's path, refused when it is not valid UTF-8 (file systems allow any bytes; labels, keys and run
    records are UTF-8 JSON), with its undecodable bytes shown escaped."""
    if escaped(path) != path:
        raise UserError(f"not a UTF-8 file name: {escaped(path)}; rename it", file=file, stage=stage, field=where)
    return path


def _existing_file(base: Path, value: str, file: str, stage: str, where: str) -> str:
    value = os.path.expanduser(value)  # ~/clip.mp4: no shell expands it after "-S vars.take=" or in YAML
    _utf8_path(value, file, stage, where)
    target = (base / value).resolve()
    if not target.exists():
        hint = _relative_hint(base, value, Path(value).exists())
        raise UserError(f"data file not found: {value}{hint}", file=file, stage=stage, field=where)
    if not (target.is_file() or target.is_dir()):
        raise UserError(f"not a file or folder: {value}", file=file, stage=stage, field=where)
    return str(target)


def _relative_hint(base: Path, value: str, found_from_cwd: bool) -> str:
    """For a relative path that names nothing: where relative paths start (the pipeline file's folder), and the
    path to write when ``value`` does name something from the working directory (``found_from_cwd``), the usual
    slip on the command line (``-S vars.take=clip.mp4`` beside a pipeline in a subfolder)."""
    if Path(value).is_absolute():
        return ""
    folder = display_path(base, ups=1)  # "." when the pipeline sits in the working directory
    hint = f" (paths are relative to the pipeline file's folder, {folder}"
    if found_from_cwd and folder != ".":
        hint += f"; from there it is '{display_path(Path(value).resolve(), base.resolve(), ups=1)}'"
    return hint + ")"


def check_cycles(nodes: dict[str, StageNode], file: str) -> None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(name: str) -> None:
        state[name] = 1
        stack.append(name)
        for dep in nodes[name].deps:
            if state.get(dep) == 1:
                cycle = stack[stack.index(dep) :] + [dep]
                raise UserError(f"dependency cycle: {' -> '.join(cycle)}", file=file, stage=dep, field="inputs")
            if dep not in state:
                visit(dep)
        stack.pop()
        state[name] = 2

    for name in nodes:
        if name not in state:
            visit(name)


def topological_order(nodes: dict[str, StageNode]) -> list[str]:
    order: list[str] = []
    done: set[str] = set()

    def visit(name: str) -> None:
        if name in done:
            return
        done.add(name)
        for dep in nodes[name].deps:
            visit(dep)
        order.append(name)

    for name in nodes:
        visit(name)
    return order


def _user_error_from_validation(exc: ValidationError, file: str) -> UserError:
    err = exc.errors()[0]
    raw = list(err.get("loc", ()))
    stage = None
    if len(raw) >= 2 and raw[0] == "stages":  # a stage's name is never a type tag, whatever it is called
        stage = str(raw[1])
        raw = raw[2:]
    loc = strip_tags(raw)
    where = ".".join(loc) or None
    msg = err.get("msg", "invalid")
    if err.get("type") == "extra_forbidden":
        allowed = sorted(StageSpec.model_fields if stage else PipelineSpec.model_fields)
        msg = f"unknown key '{loc[-1] if loc else ''}'; allowed: {', '.join(allowed)}"
    elif err.get("type") == "missing":
        msg = "required key is missing"
    elif err.get("type") == "literal_error" and loc == ["version"]:
        msg = f"unsupported format version {err.get('input')!r}; this msflow reads version {FORMAT_VERSION}"
    return UserError(msg, file=file, stage=stage, field=where)
