"""The cache key of a node, in one place.

A node's key is a BLAKE2 hash of its stage's name and version, the digest of the code that computes it, its
parameters, the contents of the files it reads and the content keys of its inputs - so a changed parameter,
input, file or plugin invalidates exactly the nodes downstream of it (:func:`node_key`).

*Files.*  Hashing a large capture on every run would cost as much as reading it, so a file's digest is
remembered (under the cache's ``files/`` folder) keyed by its path, size, inode and both its modification and
status-change times: restoring an old modification time (``cp -p``, ``rsync -t``) still changes the
status-change time, which no user command can set, so an edited file is always hashed again (:func:`file_digest`).

*Code.*  A stage's code digest covers the source and ``.cl`` files of the plugin that provides it, of every
registered plugin module its module imports (read from the sources, transitively), and of the engine
(:class:`StageCode`); a zipped install without readable sources is fingerprinted by its distribution's RECORD.
"""
from __future__ import annotations

import hashlib
import importlib.metadata
import json
import os
import re
import sys
from pathlib import Path
from types import ModuleType
from typing import Any, Iterable, Mapping

from .atomic import atomic_write_text

HASH_BLOCK = 1 << 20


def _hash(text: str) -> str:
    return hashlib.blake2b(text.encode(), digest_size=20).hexdigest()



def _memo_file(path: Path, st: os.stat_result, memo: Path) -> Path:
    return memo / _hash(json.dumps([str(path), st.st_size, st.st_ino, st.st_mtime_ns, st.st_ctime_ns]))


def remember_digest(path: Path, digest: str, memo: Path) -> None:
    """Remember the digest of a file just written, so the next look at it need not read it."""
    atomic_write_text(_memo_file(path, path.stat(), memo), digest)


def file_digest(path: Path, memo: Path | None = None) -> str | None:
    """BLAKE2 digest of a file's contents (of a zarr store folder: of every file in it; of another folder: its
    sorted entry names), None if it does not exist.

    With ``memo`` (a folder), digests are remembered per (path, size, inode, mtime, ctime) and reused.
    """
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    if path.is_dir():
        if (path / "zarr.json").is_file():  # a chunked store: keyed by its contents, chunk by chunk
            files = sorted(p for p in path.rglob("*") if p.is_file())
            return _hash("\n".join(f"{p.relative_to(path)} {file_digest(p, memo)}" for p in files))
        return _hash("\n".join(sorted(os.listdir(path))))
    memo_file = None
    if memo is not None:
        memo_file = _memo_file(path, st, memo)
        try:
            return memo_file.read_text()
        except FileNotFoundError:
            pass
    digest = hashlib.blake2b(digest_size=20)
    with open(path, "rb") as handle:
        while block := handle.read(HASH_BLOCK):
            digest.update(block)
    value = digest.hexdigest()
    if memo_file is not None:
        atomic_write_text(memo_file, value)
    return value


CODE_SUFFIXES = (".py", ".cl")


def code_files(module: ModuleType) -> list[Path]:
    """The files whose contents decide what ``module``'s stages compute: every ``.py`` and ``.cl`` file of its
    package (recursively), or of a plain module its file and the ``.cl`` files beside it."""
    origin = getattr(module, "__file__", None)
    if not origin:
        return []
    origin = Path(origin).resolve()
    if hasattr(module, "__path__"):  # a package: all of it
        found = [p for folder in module.__path__ for p in Path(folder).rglob("*")
                 if p.suffix in CODE_SUFFIXES and "__pycache__" not in p.parts]
    else:
        found = [origin] + sorted(origin.parent.glob("*.cl"))
    return sorted({p.resolve() for p in found if p.is_file()})


_IMPORT = re.compile(r"^[ \t]*(?:import[ \t]+([\w., \t]+)"
                     r"|from[ \t]+(\.*)([\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n#;]*))", re.MULTILINE)


def imported_modules(path: Path, package: str) -> set[str]:
    """The modules the Python file ``path`` (of package ``package``) imports anywhere, also inside functions, with
    relative imports resolved.  Read by pattern, not parsed (a parse of every plugin file would cost a fresh
    process a tenth of a second): an import statement quoted in a docstring counts too, which only errs towards
    re-running."""
    found = set()
    for plain, dots, module, names in _IMPORT.findall(path.read_text(encoding="utf-8", errors="replace")):
        if plain:
            found.update(part.split()[0] for part in plain.split(",") if part.strip())
            continue
        if dots:
            parts = package.split(".")
            module = ".".join(parts[:len(parts) - len(dots) + 1] + ([module] if module else []))
        found.add(module)
        # `from pkg import submodule` imports the submodule too
        found.update(f"{module}.{name.split()[0]}" for name in names.strip("()").replace("\n", " ").split(",")
                     if name.strip() and name.split()[0].isidentifier())
    return found


def code_digest(files: Iterable[Path], memo: Path | None = None) -> str:
    """One digest over the contents (and names) of ``files``: changes when any of them is edited."""
    paths = sorted({Path(p).resolve() for p in files})
    return _hash(json.dumps([[p.name, file_digest(p, memo)] for p in paths]))


def node_key(stage: str, version: str, params: Mapping[str, Any], input_keys: Mapping[str, str],
             files: Iterable[Path], memo: Path | None = None, code: str = "") -> str:
    """The cache key of one node evaluation (``memo``: where file digests are remembered; ``code``: the
    :func:`code_digest` of the stage's plugin)."""
    paths = sorted({Path(p).resolve() for p in files})
    blob = json.dumps(
        {"stage": stage, "version": version, "code": code, "params": params,
         "inputs": dict(sorted(input_keys.items())),
         "files": [[str(p), file_digest(p, memo)] for p in paths]},
        sort_keys=True, default=str,
    )
    return _hash(blob)


def node_key_of_output(key: str, port: str) -> str:
    """The key standing for an output that is not stored, from its node's key."""
    return _hash(f"output {port} of {key}")


class StageCode:
    """Code digests of the stages of a set of registered plugins (what :meth:`Registry.code_digest` answers).

    ``plugins()`` returns the registered plugin objects; ``source_of(name)`` the plugin object that provides stage
    ``name`` and ``module_of_stage(name)`` the name of the module defining its function.
    """

    def __init__(self, plugins, source_of, module_of_stage):
        self._plugins, self._source_of, self._module_of_stage = plugins, source_of, module_of_stage
        self._digests: dict[str, str] = {}
        self._imports: dict[tuple[Path, str], set[str]] = {}  # what each source file imports

    def digest(self, name: str, memo: Path | None = None) -> str:
        """Digest of the code behind stage ``name`` (its :meth:`files`).  Part of every node's cache key, so
        editing or upgrading a plugin re-runs exactly its nodes, those of plugins importing it, and what depends on
        them; upgrading btforge re-runs everything."""
        digest = self._digests.get(name)
        if digest is None:
            files, own = self.files(name)
            digest = code_digest(files, memo)
            if not own:  # no readable source (a zipped install): the distribution's version and RECORD instead
                plugin = _module_of(self._source_of(name)) or sys.modules.get(self._module_of_stage(name))
                fingerprint = digest + _distribution_fingerprint(plugin)
                digest = hashlib.blake2b(fingerprint.encode(), digest_size=20).hexdigest()
            self._digests[name] = digest
        return digest

    def files(self, name: str) -> tuple[set[Path], set[Path]]:
        """The files that decide what stage ``name`` computes, and which of them are its own plugin's.

        Its own: the source and ``.cl`` files of the plugin package that provides it (and of the module defining
        its function, if that lies elsewhere).  Besides those, every module of a registered plugin that the
        stage's module imports, transitively and also inside functions (a plugin may use another's file reader),
        with the ``.cl`` files beside it, and the engine's own files (its buffers remap, blend and
        validate data too).
        """
        plugin = _module_of(self._source_of(name))
        defining = sys.modules.get(self._module_of_stage(name))
        own = set(code_files(plugin)) | (set(code_files(defining)) if defining is not None else set())
        files = own | set(code_files(sys.modules[__package__]))
        if defining is not None and getattr(defining, "__file__", None):
            for path in self._imported_files(Path(defining.__file__).resolve(), defining.__name__):
                files |= {path, *path.parent.glob("*.cl")}
        return files, own

    def _imported_files(self, path: Path, module_name: str) -> set[Path]:
        """The source files of registered plugins' modules that ``path`` (module ``module_name``) imports,
        transitively; found by reading the sources, so nothing is imported to find them."""
        plugins = {m.__name__: m for m in map(_module_of, self._plugins()) if m is not None}
        seen: set[Path] = set()
        todo = [(path, module_name)]
        while todo:
            path, module_name = todo.pop()
            package = module_name if path.name == "__init__.py" else module_name.rpartition(".")[0]
            for imported in self._imports_of(path, package):
                found = _plugin_module_file(imported, plugins)
                if found is not None and found not in seen:
                    seen.add(found)
                    todo.append((found, imported))
        return seen

    def _imports_of(self, path: Path, package: str) -> set[str]:
        key = (path, package)
        if key not in self._imports:
            self._imports[key] = imported_modules(path, package)
        return self._imports[key]


def _module_of(plugin: Any) -> ModuleType | None:
    """The module a plugin object comes from (a module plugin is its own)."""
    if isinstance(plugin, ModuleType):
        return plugin
    return sys.modules.get(getattr(plugin, "__module__", None) or type(plugin).__module__)


def _plugin_module_file(module_name: str, plugins: dict[str, ModuleType]) -> Path | None:
    """The source file of module ``module_name`` if it lies in a registered plugin package (None otherwise)."""
    owners = [p for p in plugins if module_name == p or module_name.startswith(p + ".")]
    if not owners:
        return None
    owner = plugins[max(owners, key=len)]
    if not hasattr(owner, "__path__"):
        return Path(owner.__file__).resolve() if module_name == owner.__name__ and owner.__file__ else None
    rest = module_name[len(owner.__name__):].lstrip(".").split(".") if module_name != owner.__name__ else []
    for folder in owner.__path__:
        base = Path(folder).joinpath(*rest)
        for candidate in (base / "__init__.py", base.with_suffix(".py")) if rest else (base / "__init__.py",):
            if candidate.is_file():
                return candidate.resolve()
    return None  # a name imported from a module (``from pkg.mod import function``), not a module


def _distribution_fingerprint(module: ModuleType | None) -> str:
    """Version and RECORD (the hashes of every installed file) of the distribution that installed ``module``."""
    top = (getattr(module, "__name__", "") or "").split(".")[0]
    parts = []
    for dist_name in sorted(importlib.metadata.packages_distributions().get(top, [])):
        dist = importlib.metadata.distribution(dist_name)
        parts.append(f"{dist_name} {dist.version}\n{dist.read_text('RECORD') or ''}")
    return "\n".join(parts)
