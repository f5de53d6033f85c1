"""Finding plugins and the stages and buffer types they provide.

Plugins are discovered through the ``btforge.plugins`` entry-point group - the built-in families are listed
there too, so a third-party plugin is loaded exactly like a built-in one.  Tests and plugin authors may also
register a module or object directly with :meth:`Registry.register`.
"""
from __future__ import annotations

import difflib
import hashlib
import importlib.metadata
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any, Iterable

import pluggy

from . import buffers, hookspecs, profile
from .cache import code_digest, code_files, imported_modules
from .errors import BtforgeInputError
from .stages import Stage

ENTRY_POINT_GROUP = "btforge.plugins"


class Registry:
    """Stages and buffer types of every registered plugin, with checks that run at load time."""

    def __init__(self, load_entry_points: bool = True, extra_plugins: Iterable[Any] = ()):
        self.pm = pluggy.PluginManager("btforge")
        self.pm.add_hookspecs(hookspecs)
        if load_entry_points:
            self.pm.load_setuptools_entrypoints(ENTRY_POINT_GROUP)
        for plugin in extra_plugins:
            self.pm.register(plugin)
        self._collect()

    def register(self, plugin: Any, name: str | None = None) -> None:
        self.pm.register(plugin, name=name)
        self._collect()
        self._collect_commands()  # a plugin registered later is checked whole at once

    @property
    def cli_commands(self) -> dict[str, tuple[Any, Any]]:
        """``{name: (add_arguments, run)}`` of the plugins' subcommands, collected when first asked for: the hooks
        import the commands' modules (a web server, benches), which a ``btforge run`` does not need."""
        if self._cli_commands is None:
            self._collect_commands()
        return self._cli_commands

    @property
    def bench_commands(self) -> dict[str, Any]:
        """``{name: bench(args) -> int}`` of the plugins' benches, collected when first asked for."""
        if self._bench_commands is None:
            self._collect_commands()
        return self._bench_commands

    def _plugin_name(self, plugin: Any) -> str:
        return self.pm.get_name(plugin) or repr(plugin)

    def _check_plugins(self) -> None:
        """Every plugin states the API it was written for and implements only hooks that exist."""
        problems = []
        for plugin in self.pm.get_plugins():
            name = self._plugin_name(plugin)
            api = getattr(plugin, "BTFORGE_PLUGIN_API", None)
            if api is None:
                problems.append(f"plugin '{name}': states no plugin API version (add "
                                f"'BTFORGE_PLUGIN_API = {hookspecs.PLUGIN_API_VERSION}' to it once it works with "
                                f"this btforge)")
            elif api != hookspecs.PLUGIN_API_VERSION:
                from . import __version__
                problems.append(f"plugin '{name}': was written for plugin API {api!r}, this btforge "
                                f"{__version__} has API {hookspecs.PLUGIN_API_VERSION} "
                                f"(install a release of the plugin made for API {hookspecs.PLUGIN_API_VERSION})")
        known = [h for h in dir(hookspecs) if h.startswith("btforge_")]
        for hook_name, caller in sorted(vars(self.pm.hook).items()):
            if caller.has_spec():
                continue
            for impl in caller.get_hookimpls():  # pluggy's check_pending, but reporting every one
                problems.append(f"plugin '{impl.plugin_name}': implements unknown hook '{hook_name}' "
                                f"({did_you_mean(hook_name, known)})")
        if problems:
            if len(problems) == 1:
                raise BtforgeInputError("", problems[0])
            raise BtforgeInputError("plugins", f"{len(problems)} problems:\n  - " + "\n  - ".join(problems))
        self.pm.check_pending()  # nothing is left for it to find; kept so pluggy's own rules still apply

    def _collect(self) -> None:
        self._check_plugins()
        self.types: dict[str, type[buffers.Buffer]] = {t.type_name: t for t in buffers.CORE_TYPES}
        for impl in self.pm.hook.btforge_buffer_types.get_hookimpls():
            plugin_name = self.pm.get_name(impl.plugin) or repr(impl.plugin)
            for t in impl.function() or ():
                if not (isinstance(t, type) and issubclass(t, buffers.Buffer)):
                    raise BtforgeInputError(f"plugin '{plugin_name}'", f"btforge_buffer_types must return Buffer "
                                            f"subclasses, found {t!r}", "subclass btforge.buffers.Buffer")
                known = self.types.get(t.type_name)
                if known is not None and known is not t:  # a silent replacement would retype every graph
                    raise BtforgeInputError(f"buffer type '{t.type_name}'",
                                            f"is defined by both {known.__module__} and {t.__module__}",
                                            "give the plugin's type another type_name")
                self.types[t.type_name] = t
        self.stages: dict[str, Stage] = {}
        self._stage_sources: dict[str, Any] = {}  # stage name -> the plugin object that provided it
        self._code_digests: dict[str, str] = {}
        self._imports: dict[tuple[Path, str], set[str]] = {}  # what each source file imports
        for impl in self.pm.hook.btforge_stages.get_hookimpls():
            plugin_name = self.pm.get_name(impl.plugin) or repr(impl.plugin)
            for st in impl.function() or ():
                if not isinstance(st, Stage):
                    raise BtforgeInputError(f"plugin '{plugin_name}'", f"btforge_stages must return Stage objects, found {st!r}",
                                            "decorate the stage function with @btforge.declare_stage(...)")
                if st.name in self.stages:
                    other = self.stages[st.name].plugin
                    raise BtforgeInputError(f"stage '{st.name}'", f"is defined by both {other} and {st.plugin}",
                                            "uninstall one of the plugins or rename the stage")
                for port, tname in st.outputs.items():
                    if tname.startswith("=") and tname[1:] not in st.inputs:
                        raise BtforgeInputError(f"stage '{st.name}', output '{port}'",
                                                f"takes the type of input '{tname[1:]}', which the stage does not have")
                for port, tname in {**st.inputs, **st.outputs}.items():
                    if tname.startswith("="):
                        continue
                    if tname not in self.types:
                        raise BtforgeInputError(f"stage '{st.name}', port '{port}'", f"names unknown buffer type '{tname}'",
                                                f"known types: {', '.join(sorted(self.types))}")
                self.stages[st.name] = st
                self._stage_sources[st.name] = impl.plugin
        self.info_readers: dict[str, Any] = {}
        for result in self.pm.hook.btforge_info_readers():
            self.info_readers.update(result or {})
        self._cli_commands = self._bench_commands = None

    def _collect_commands(self) -> None:
        commands: dict[str, tuple[Any, Any]] = {}
        for impl in self.pm.hook.btforge_cli_commands.get_hookimpls():
            plugin_name = self.pm.get_name(impl.plugin) or repr(impl.plugin)
            for name, command in (impl.function() or {}).items():
                if name in commands:
                    raise BtforgeInputError(f"command '{name}'", f"is defined by two plugins (one is {plugin_name})",
                                            "uninstall one of the plugins or rename the command")
                commands[name] = command
        self._cli_commands = commands
        self._collect_benches()

    def _collect_benches(self) -> None:
        benches: dict[str, Any] = {}
        bench_owner: dict[str, str] = {}
        for impl in self.pm.hook.btforge_bench_commands.get_hookimpls():
            plugin_name = self._plugin_name(impl.plugin)
            for bench_name, fn in (impl.function() or {}).items():
                if bench_name in benches:
                    raise BtforgeInputError(f"bench '{bench_name}'", f"is contributed by both plugin "
                                            f"'{bench_owner[bench_name]}' and plugin '{plugin_name}'",
                                            "rename one of the benches")
                if not callable(fn):
                    raise BtforgeInputError(f"plugin '{plugin_name}', bench '{bench_name}'",
                                            f"expected a function bench(args) -> int, found {fn!r}")
                benches[bench_name], bench_owner[bench_name] = fn, plugin_name
        self._bench_commands = benches

    def stage(self, name: str) -> Stage:
        try:
            return self.stages[name]
        except KeyError:
            raise BtforgeInputError(f"stage '{name}'", "is not provided by any installed plugin",
                                    did_you_mean(name, self.stages)) from None

    def code_digest(self, name: str, memo: Path | None = None) -> str:
        """Digest of the code behind stage ``name`` (its :meth:`code_files`).  Part of every node's cache key, so
        editing or upgrading a plugin re-runs exactly its nodes, those of plugins importing it, and what depends on
        them; upgrading btforge re-runs everything."""
        digest = self._code_digests.get(name)
        if digest is None:
            files, own = self.code_files(name)
            digest = code_digest(files, memo)
            if not own:  # no readable source (a zipped install): the distribution's version and RECORD instead
                plugin = _module_of(self._stage_sources[name]) or sys.modules.get(self.stages[name].fn.__module__)
                fingerprint = digest + _distribution_fingerprint(plugin)
                digest = hashlib.blake2b(fingerprint.encode(), digest_size=20).hexdigest()
            self._code_digests[name] = digest
        return digest

    def code_files(self, name: str) -> tuple[set[Path], set[Path]]:
        """The files that decide what stage ``name`` computes, and which of them are its own plugin's.

        Its own: the source and ``.cl`` files of the plugin package that provides it (and of the module defining
        its function, if that lies elsewhere).  Besides those, every module of a registered plugin that the
        stage's module imports, transitively and also inside functions (a plugin may use another's file reader),
        with the ``.cl`` files beside it, and the engine's own files (its buffers remap, blend and
        validate data too).
        """
        plugin = _module_of(self._stage_sources[name])
        defining = sys.modules.get(self.stages[name].fn.__module__)
        own = set(code_files(plugin)) | (set(code_files(defining)) if defining is not None else set())
        files = own | set(code_files(sys.modules[__package__]))
        if defining is not None and getattr(defining, "__file__", None):
            for path in self._imported_files(Path(defining.__file__).resolve(), defining.__name__):
                files |= {path, *path.parent.glob("*.cl")}
        return files, own

    def _imported_files(self, path: Path, module_name: str) -> set[Path]:
        """The source files of registered plugins' modules that ``path`` (module ``module_name``) imports,
        transitively; found by reading the sources, so nothing is imported to find them."""
        plugins = {m.__name__: m for m in map(_module_of, self.pm.get_plugins()) if m is not None}
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

    def stages_with_role(self, role: str) -> list[Stage]:
        """The stages that declare ``role`` (e.g. ``"fit"``), by name."""
        return [self.stages[n] for n in sorted(self.stages) if self.stages[n].role == role]

    def accepts(self, port_type: str, value_type: str) -> bool:
        """Whether a port declared as ``port_type`` accepts a buffer of ``value_type`` (unknown types: never)."""
        if port_type not in self.types or value_type not in self.types:
            return False
        return issubclass(self.types[value_type], self.types[port_type])


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


def did_you_mean(name: str, options: Iterable[str]) -> str:
    options = sorted(options)
    near = difflib.get_close_matches(name, options, n=1, cutoff=0.5)
    if near:
        return f"did you mean '{near[0]}'?"
    return "known: " + ", ".join(options) if options else "nothing is registered"


_default: Registry | None = None


def default_registry() -> Registry:
    global _default
    if _default is None:
        start = time.perf_counter()
        _default = Registry()
        profile.record_phase("plugins_s", time.perf_counter() - start)
    return _default
