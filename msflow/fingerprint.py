"""Code fingerprints: a stage class's module and every project module it imports, transitively, hashed by AST.

Comments, docstrings and formatting do not change a fingerprint; any other edit does. "Project" covers the
pipeline's project root and packages installed in development mode (``pip install -e``). Imports of third-party
packages, and of msflow itself, contribute their distributions' versions; standard-library imports nothing (the
Python minor version is part of the key instead). Nothing is imported to compute this: modules are parsed, and parse results are memoised
by (size, mtime_ns, inode) so a no-op run only stats files.
"""

from __future__ import annotations

import ast
import os
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from msflow.errors import UserError
from msflow.hashing import bytes_hash, json_hash, stat_signature
from msflow.syspath import holds_installed_packages, in_project

IGNORED_PARTS = {"site-packages", "dist-packages", ".msflow", "node_modules", ".git", "__pycache__"}
STDLIB = frozenset(sys.stdlib_module_names) | frozenset(sys.builtin_module_names)
#: the framework is versioned, not fingerprinted: its runner, CLI and store do not change what a stage computes,
#: and a change that alters stored results bumps msflow.runner.KEY_SCHEME instead
FRAMEWORK = frozenset({"msflow"})


def strip_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if (
                body
                and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)
            ):
                node.body = body[1:] or [ast.Pass()]
    return tree


def parse_module(source: str | bytes, filename: str) -> tuple[str, list[list[Any]]]:
    """(AST digest without docstrings and positions, imports as [module, level, [names]])."""
    tree = ast.parse(source, filename=filename)
    imports: list[list[Any]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                imports.append([alias.name, 0, []])
        elif isinstance(node, ast.ImportFrom):
            imports.append([node.module or "", node.level, [a.name for a in node.names]])
    digest = bytes_hash(ast.dump(strip_docstrings(tree), annotate_fields=True, include_attributes=False).encode())
    return digest, imports


class CodeIndex:
    """Finds project modules under ``root`` and fingerprints import closures, with a JSON-able memo."""

    def __init__(self, root: Path, memo: dict[str, Any] | None = None):
        self.root = Path(root).resolve()
        self.memo = memo if memo is not None else {}
        self.memo.setdefault("files", {})
        self._closures: dict[str, dict[str, Any]] = {}

    # ------------------------------------------------------------------ locating modules
    def project_file(self, dotted: str) -> Path | None:
        """File of a source module (``pkg/__init__.py`` for packages): in the project, or in a package installed
        in development mode (``pip install -e``) whose code lives outside site-packages. None otherwise."""
        if dotted.split(".")[0] in FRAMEWORK:
            return None
        found = _module_file(self.root, dotted)
        if found is not None:
            return found
        root = self.source_root(dotted.split(".")[0])
        return _module_file(root, dotted) if root is not None else None

    def source_root(self, top: str) -> Path | None:
        """Folder holding an importable top-level package that is source code under development, not a
        distribution's installed files: edits to it must change fingerprints like edits to the project."""
        if top in STDLIB or not top:
            return None
        roots = self.memo.setdefault("roots", {})
        signature = path_signature(self.root)
        if roots.get("sig") != signature:
            roots.clear()
            roots["sig"] = signature
        if top not in roots:
            roots[top] = _find_source_root(top)
        return Path(roots[top]) if roots[top] else None

    def is_project_module(self, dotted: str) -> bool:
        return self.project_file(dotted) is not None or self._is_namespace(dotted)

    def _is_namespace(self, dotted: str) -> bool:
        path = self.root.joinpath(*dotted.split("."))
        return (
            path.is_dir()
            and dotted.split(".")[0] not in IGNORED_PARTS
            and (path / "__init__.py").exists() is False
            and any(path.glob("*.py"))
        )

    def rel(self, path: Path) -> str:
        """Path relative to the project root, or to the development package's own root: no absolute paths."""
        path = path.resolve()
        try:
            return path.relative_to(self.root).as_posix()
        except ValueError:
            top = path
            while top.parent != top and (top.parent / "__init__.py").exists():
                top = top.parent
            return path.relative_to(top.parent).as_posix()

    # ------------------------------------------------------------------ parsing with memo
    def module_info(self, path: Path) -> tuple[str, list[list[Any]]]:
        key = self.rel(path)
        sig = stat_signature(path)
        hit = self.memo["files"].get(key)
        if hit and hit[0] == sig:
            return hit[1], hit[2]
        try:
            digest, imports = parse_module(path.read_bytes(), str(path))
        except SyntaxError as exc:
            raise UserError(f"syntax error at line {exc.lineno}: {exc.msg}", file=str(path)) from None
        self.memo["files"][key] = [sig, digest, imports]
        return digest, imports

    # ------------------------------------------------------------------ closure
    def closure(self, module: str) -> dict[str, Any]:
        """{"modules": {relpath: digest}, "external": sorted top-level third-party names} for a module.

        Memoised on the stat signatures of the closure's files and of their package folders (a new module file
        changes its folder's mtime), so a no-op run validates a closure with a few stats instead of resolving
        every import again."""
        if module in self._closures:
            return self._closures[module]
        memo = self.memo.setdefault("closures", {})
        hit = memo.get(module)
        if hit and self._signature(hit["files"]) == hit["sig"]:
            self._closures[module] = hit["closure"]
            closure: dict[str, Any] = hit["closure"]
            return closure
        result, files = self._compute_closure(module)
        memo[module] = {"files": files, "sig": self._signature(files), "closure": result}
        self._closures[module] = result
        return result

    def _signature(self, files: list[str]) -> list[str]:
        """Stat signatures of closure files; relative entries are under the project root (clones stay valid)."""
        out = []
        for path in files:
            try:
                st = os.stat(path if os.path.isabs(path) else self.root / path)
                out.append(f"{st.st_size}:{st.st_mtime_ns}:{st.st_ino}")
            except OSError:
                out.append("missing")
        return out

    def _compute_closure(self, module: str) -> tuple[dict[str, Any], list[str]]:
        modules: dict[str, str] = {}
        external: set[str] = set()
        seen: set[str] = set()
        watched: set[str] = {str(self.root)}
        queue = [module]
        while queue:
            name = queue.pop()
            if name in seen:
                continue
            seen.add(name)
            # importing a.b.c executes a/__init__ and a/b/__init__ first
            parts = name.split(".")
            for i in range(1, len(parts)):
                parent = ".".join(parts[:i])
                if parent not in seen:
                    queue.append(parent)
            path = self.project_file(name)
            if path is None:
                continue
            digest, imports = self.module_info(path)
            modules[self.rel(path)] = digest
            watched.update((str(path), str(path.parent)))
            is_package = path.name == "__init__.py"
            for target, level, names in imports:
                for absolute in self._resolve(name, is_package, target, level, names):
                    top = absolute.split(".")[0]
                    if self.is_project_module(top):
                        queue.append(absolute)
                    elif top and top not in STDLIB and not top.startswith("_"):
                        external.add(top)
        result = {"modules": dict(sorted(modules.items())), "external": sorted(external)}
        return result, sorted(self._relative(w) for w in watched)

    def _relative(self, path: str) -> str:
        try:
            return Path(path).relative_to(self.root).as_posix() or "."
        except ValueError:
            return path

    def _resolve(self, current: str, is_package: bool, target: str, level: int, names: list[str]) -> list[str]:
        if level:
            package = current if is_package else current.rpartition(".")[0]
            for _ in range(level - 1):
                package = package.rpartition(".")[0]
            base = f"{package}.{target}" if target else package
        else:
            base = target
        if not base:
            return []
        out = [base]
        out.extend(f"{base}.{n}" for n in names if n != "*" and self.project_file(f"{base}.{n}") is not None)
        return out


def _module_file(base: Path, dotted: str) -> Path | None:
    parts = dotted.split(".")
    for i, part in enumerate(parts):
        pkg = base / part
        if i == len(parts) - 1:
            if (pkg / "__init__.py").is_file():
                return pkg / "__init__.py"
            if (base / f"{part}.py").is_file():
                return base / f"{part}.py"
            return None
        if not pkg.is_dir() or part in IGNORED_PARTS:
            return None
        base = pkg
    return None


def _find_source_root(top: str) -> str | None:
    import importlib.util
    import sysconfig

    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):
        return None
    if spec is None:
        return None
    locations = list(spec.submodule_search_locations or [])
    origin = spec.origin if spec.origin not in (None, "built-in", "frozen") else None
    path = Path(locations[0]) if locations else Path(origin) if origin else None
    if path is None or not origin or not origin.endswith(".py"):
        return None  # compiled extension modules and namespace packages: versioned as distributions
    installed = {sysconfig.get_paths()[k] for k in ("stdlib", "platstdlib", "purelib", "platlib")}
    resolved = path.resolve()
    if holds_installed_packages(str(resolved)) or any(
        str(resolved).startswith(str(Path(p).resolve())) for p in installed
    ):
        return None
    return str(resolved.parent if locations else resolved.parent)


#: project roots msflow put on sys.path (msflow.plan.ensure_importable), each ending in "/"
PROJECT_ROOTS: set[str] = set()


def environment_signature() -> str:
    """What the installed distributions depend on: ``sys_path_signature`` leaving out the project roots msflow put
    on sys.path (a project's code is fingerprinted by content and holds no installed distributions), so a process
    that runs one project after another scans its distributions once, not once per project."""
    return sys_path_signature(PROJECT_ROOTS, keep=False)


def path_signature(project_root: Path | None = None) -> str:
    """What installed packages and their locations depend on: ``sys_path_signature`` with the project root and
    folders inside it counted by name only (writing pipeline.lock or a run's outputs there changes no installed
    package, and the project's own modules are fingerprinted by content instead)."""
    roots = [str(project_root).rstrip("/") + "/"] if project_root is not None else []
    return sys_path_signature(roots, keep=True)


def sys_path_signature(project_roots: Iterable[str], *, keep: bool) -> str:
    """sys.path and the mtime of each folder on it (a package installed or removed changes its folder's mtime);
    folders of ``project_roots`` (``msflow.syspath.in_project``; a ``.venv`` inside a project is not one) are
    kept by name only (``keep``) or left out. A process that does not change sys.path signs it once."""
    entries = []
    for entry in sys.path:
        if not in_project(entry, project_roots):
            entries.append([entry, _mtime(entry)])
        elif keep:
            entries.append([entry, 0])
    return json_hash(entries)


#: ``distribution_versions(signature=WORKER_PROCESS)``: the installed distributions as this process first saw them
WORKER_PROCESS = "worker process"


def distribution_versions(
    names: list[str], memo: dict[str, Any], project_root: Path | None = None, *, signature: str | None = None
) -> dict[str, str]:
    """Map top-level import names to "dist==version"; memoised on the state of sys.path's directories.

    A name with no distribution and no importable module is recorded as absent (an optional dependency that is not
    installed is a fact about the environment, hashed like a version). ``signature=WORKER_PROCESS`` memoises for
    the process's lifetime instead: a worker keeps the packages it imported, whatever is installed later, and the
    code trees it puts on sys.path hold no distributions.
    """
    signature = signature or path_signature(project_root)
    cache = memo.get("dists")
    if not cache or cache.get("sig") != signature:
        cache = {"sig": signature, "map": {}}
        memo["dists"] = cache
    missing = [n for n in names if n not in cache["map"]]
    if missing:
        import importlib.metadata as md
        import importlib.util

        owners = _owners(signature if signature == WORKER_PROCESS else environment_signature())
        for name in missing:
            dists = sorted(set(owners.get(name, [])))
            if dists:
                cache["map"][name] = [f"{d}=={md.version(d)}" for d in dists]
            elif importlib.util.find_spec(name) is None:
                cache["map"][name] = ["absent"]
            else:
                cache["map"][name] = [f"unpackaged:{_unpackaged_digest(name)}"]
    return {n: ",".join(cache["map"][n]) for n in names}


_OWNERS: tuple[str, Mapping[str, list[str]]] | None = None


def _owners(signature: str) -> Mapping[str, list[str]]:
    """``importlib.metadata.packages_distributions()`` (a scan of every installed distribution), once per
    ``signature`` (``environment_signature``, or WORKER_PROCESS) in this process: a worker checks the distributions
    of each job it runs."""
    global _OWNERS
    if _OWNERS is None or _OWNERS[0] != signature:
        import importlib.metadata as md

        _OWNERS = (signature, md.packages_distributions())
    return _OWNERS[1]


def warm_distribution_index() -> None:
    """Scan the installed distributions now (a worker at start-up), not in its first job."""
    _owners(WORKER_PROCESS)


def _unpackaged_digest(name: str) -> str:
    """A module importable but not from any distribution (e.g. a file on PYTHONPATH): hash its source."""
    import importlib.util

    spec = importlib.util.find_spec(name)
    origin = getattr(spec, "origin", None)
    if origin and origin not in ("built-in", "frozen") and os.path.isfile(origin):
        with open(origin, "rb") as fh:
            return bytes_hash(fh.read())
    raise UserError(
        f"cannot fingerprint module '{name}': it is not in the project, not from an installed "
        "distribution and has no source file"
    )


def _mtime(path: str) -> int:
    try:
        return os.stat(path or ".").st_mtime_ns
    except OSError:
        return 0
