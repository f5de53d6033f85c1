"""Finding plugins and the stages and buffer types they provide.

Plugins are discovered through the ``btforge.plugins`` entry-point group - the built-in families are listed
there too, so a third-party plugin is loaded exactly like a built-in one.  Tests and plugin authors may also
register a module or object directly with :meth:`Registry.register`.
"""
from __future__ import annotations

import difflib
import threading
import time
import warnings
from pathlib import Path
from collections.abc import Mapping
from typing import Any, Callable, Iterable, Iterator

import pluggy

from . import buffers, hookspecs, plugin_index, profile
from .cachekey import StageCode
from .errors import BtforgeInputError, DeprecatedNameWarning
from .stages import Stage

ENTRY_POINT_GROUP = "btforge.plugins"
_loading = threading.RLock()  # a lazy registry loads one plugin at a time


class Registry:
    """Stages and buffer types of every registered plugin, with checks that run at load time.

    With ``lazy=True`` (entry points only, as :func:`default_registry` makes it) and the installed plugins as
    they were when last loaded whole, a plugin is loaded when one of its stages or types is first asked for
    (:mod:`btforge.plugin_index`); anything that needs every plugin loads them all first.
    """

    def __init__(self, load_entry_points: bool = True, extra_plugins: Iterable[Any] = (), lazy: bool = False):
        self._extra = list(extra_plugins)
        self._lazy: dict[str, dict] | None = None  # while set: the index of what each unloaded plugin provides
        self.types = _Types(self)
        described = plugin_index.describe(ENTRY_POINT_GROUP, _api()) \
            if lazy and load_entry_points and not self._extra else None
        index = plugin_index.load(described[0]) if described else None
        if index is not None:
            self._lazy, self._entry_points = index["plugins"], described[2]
            self._start(load_entry_points=False)
            return
        self._start(load_entry_points)
        if described:  # loaded whole and checked: remember what each plugin provides
            plugin_index.save(described[0], self._provided(described[1]))

    def _start(self, load_entry_points: bool) -> None:
        self.pm = pluggy.PluginManager("btforge")
        self.pm.add_hookspecs(hookspecs)
        if load_entry_points:
            self.pm.load_setuptools_entrypoints(ENTRY_POINT_GROUP)
        for plugin in self._extra:
            self.pm.register(plugin)
        self._collect()

    def _everything(self) -> None:
        """Load every plugin now, as a registry that is not lazy does (in the same order)."""
        with _loading:
            if self._lazy is not None:
                self._lazy = None
                self._start(load_entry_points=True)

    def _provide(self, kind: str, name: str) -> None:
        """Make sure the plugin providing stage or type ``name`` is loaded (every plugin, if the index knows no
        plugin providing it: the full load then answers as it always does)."""
        if self._lazy is None:
            return
        with _loading:  # tasks on worker threads may ask at once
            if self._lazy is None or name in (self._type_dict if kind == "types" else self._stage_names()):
                return
            owner = next((plugin for plugin, entry in self._lazy.items() if name in entry[kind]), None)
            if owner is None or self.pm.get_plugin(owner) is not None:
                self._everything()
                return
            self.pm.register(self._entry_points[owner].load(), name=owner)  # as pluggy loads an entry point
            self._collect()
            if name not in (self._type_dict if kind == "types" else self._stage_names()):
                self._everything()  # the index was wrong after all: what a full load finds holds

    def _stage_names(self):
        return self._stages.keys() | self._aliases.keys()

    def _provided(self, plugins: dict[str, dict]) -> dict[str, dict]:
        """``plugins`` (name -> where its module lives) with the stages, old stage names and types each gave."""
        by_plugin = {name: {**entry, "stages": [], "types": []} for name, entry in plugins.items()}
        for stage_name, source in self._stage_sources.items():
            entry = by_plugin.get(self._plugin_name(source))
            if entry is not None:
                entry["stages"] += [stage_name, *self._stages[stage_name].deprecated_names]
        for impl in self.pm.hook.btforge_buffer_types.get_hookimpls():
            entry = by_plugin.get(self._plugin_name(impl.plugin))
            if entry is not None:
                entry["types"] += [t.type_name for t in impl.function() or ()]
        return by_plugin

    def _plugins_for_code(self) -> list[Any]:
        """The registered plugins, and stand-ins for those not loaded yet: code digests follow imports into every
        installed plugin, loaded or not (:mod:`btforge.cachekey`)."""
        loaded = list(self.pm.get_plugins())
        pending = [plugin_index.stand_in(entry) for name, entry in (self._lazy or {}).items()
                   if self.pm.get_plugin(name) is None]
        return loaded + pending

    @property
    def stages(self) -> dict[str, Stage]:
        """``{name: Stage}`` of every plugin (a lazy registry loads them all)."""
        self._everything()
        return self._stages

    @property
    def aliases(self) -> dict[str, str]:
        """Old names of renamed stages -> their stage's name, of every plugin."""
        self._everything()
        return self._aliases

    @property
    def info_readers(self) -> dict[str, Any]:
        """``{suffix: describe(path)}`` of every plugin, for ``btforge info``."""
        self._everything()
        return self._info_readers

    def register(self, plugin: Any, name: str | None = None) -> None:
        self._everything()
        self.pm.register(plugin, name=name)
        self._extra.append(plugin)
        self._collect()
        self._collect_commands()  # a plugin registered later is checked whole at once

    @property
    def cli_commands(self) -> dict[str, tuple[Any, Any]]:
        """``{name: (add_arguments, run)}`` of the plugins' subcommands, collected when first asked for: the hooks
        import the commands' modules (a web server, benches), which a ``btforge run`` does not need."""
        self._everything()
        if self._cli_commands is None:
            self._collect_commands()
        return self._cli_commands

    @property
    def bench_commands(self) -> dict[str, Any]:
        """``{name: bench(args) -> int}`` of the plugins' benches, collected when first asked for."""
        self._everything()
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
        self._collect_types()
        self._collect_stages()
        self._collect_aliases()
        self._info_readers: dict[str, Any] = self._unique_names(
            "btforge_info_readers", "info reader for", "uninstall one of the plugins, or leave the extension to one")
        self._cli_commands = self._bench_commands = None
        self._code = StageCode(self._plugins_for_code, self._stage_sources.__getitem__,
                               lambda name: self._stages[name].fn.__module__)

    def _collect_commands(self) -> None:
        self._cli_commands = self._unique_names(
            "btforge_cli_commands", "command", "uninstall one of the plugins or rename the command")
        self._bench_commands = self._unique_names(
            "btforge_bench_commands", "bench", "rename one of the benches", check=_bench_problem)

    def _collect_types(self) -> None:
        self._type_dict: dict[str, type[buffers.Buffer]] = {t.type_name: t for t in buffers.CORE_TYPES}
        for impl in self.pm.hook.btforge_buffer_types.get_hookimpls():
            plugin_name = self._plugin_name(impl.plugin)
            for t in impl.function() or ():
                if not (isinstance(t, type) and issubclass(t, buffers.Buffer)):
                    raise BtforgeInputError(f"plugin '{plugin_name}'", f"btforge_buffer_types must return Buffer "
                                            f"subclasses, found {t!r}", "subclass btforge.buffers.Buffer")
                known = self._type_dict.get(t.type_name)
                if known is not None and known is not t:  # a silent replacement would retype every graph
                    raise BtforgeInputError(f"buffer type '{t.type_name}'",
                                            f"is defined by both {known.__module__} and {t.__module__}",
                                            "give the plugin's type another type_name")
                self._type_dict[t.type_name] = t

    def _collect_stages(self) -> None:
        self._stages: dict[str, Stage] = {}
        self._stage_sources: dict[str, Any] = {}  # stage name -> the plugin object that provided it
        for impl in self.pm.hook.btforge_stages.get_hookimpls():
            plugin_name = self._plugin_name(impl.plugin)
            for st in impl.function() or ():
                if not isinstance(st, Stage):
                    raise BtforgeInputError(f"plugin '{plugin_name}'", f"btforge_stages must return Stage objects, "
                                            f"found {st!r}", "decorate the stage function with @btforge.declare_stage(...)")
                if st.name in self._stages:
                    other = self._stages[st.name].plugin
                    raise BtforgeInputError(f"stage '{st.name}'", f"is defined by both {other} and {st.plugin}",
                                            "uninstall one of the plugins or rename the stage")
                self._check_ports(st)
                self._stages[st.name] = st
                self._stage_sources[st.name] = impl.plugin

    def _check_ports(self, st: Stage) -> None:
        for port, tname in st.outputs.items():
            if tname.startswith("=") and tname[1:] not in st.inputs:
                raise BtforgeInputError(f"stage '{st.name}', output '{port}'",
                                        f"takes the type of input '{tname[1:]}', which the stage does not have")
        for port, tname in {**st.inputs, **st.outputs}.items():
            if not tname.startswith("=") and not self._type_known(tname):
                raise BtforgeInputError(f"stage '{st.name}', port '{port}'", f"names unknown buffer type '{tname}'",
                                        f"known types: {', '.join(sorted(self.types))}")

    def _type_known(self, name: str) -> bool:
        """Whether type ``name`` is registered, or provided by a plugin a lazy registry has not loaded yet (the
        index was made by a full load that checked every port, so it is not loaded for the check)."""
        return name in self._type_dict or any(name in entry["types"] for entry in (self._lazy or {}).values())

    def _collect_aliases(self) -> None:
        """Old names of renamed stages -> their stage's name; an old name may not be any other stage's name."""
        self._aliases: dict[str, str] = {}
        for name, st in sorted(self._stages.items()):
            for old in st.deprecated_names:
                taken = name if old in self._stages else self._aliases.get(old)
                if taken is not None:
                    raise BtforgeInputError(f"stage name '{old}'", f"is both a deprecated name of '{name}' "
                                            f"({st.plugin}) and the name of '{taken}'",
                                            "drop the deprecated name from one of the stages")
                self._aliases[old] = name

    def _unique_names(self, hook: str, kind: str, hint: str, check: Callable | None = None) -> dict[str, Any]:
        """Join the ``{name: value}`` mappings a hook returns, refusing a name two plugins give (naming both)."""
        joined: dict[str, Any] = {}
        owner: dict[str, str] = {}
        for impl in getattr(self.pm.hook, hook).get_hookimpls():
            plugin_name = self._plugin_name(impl.plugin)
            for name, value in (impl.function() or {}).items():
                if name in joined:
                    raise BtforgeInputError(f"{kind} '{name}'", f"is contributed by both plugin '{owner[name]}' and "
                                            f"plugin '{plugin_name}'", hint)
                problem = check(name, value) if check else None
                if problem:
                    raise BtforgeInputError(f"plugin '{plugin_name}', {kind} '{name}'", problem)
                joined[name], owner[name] = value, plugin_name
        return joined

    def find_stage(self, name: str, where: str = "") -> Stage | None:
        """The stage called ``name`` (or None); an old name of a renamed stage gives that stage, with a
        :class:`DeprecatedNameWarning` naming the new name (and ``where`` it was used)."""
        self._provide("stages", name)
        if name in self._stages:
            return self._stages[name]
        new = self._aliases.get(name)
        if new is None:
            return None
        place = f"{where}: " if where else ""
        warnings.warn(f"{place}stage '{name}' is deprecated, use '{new}'", DeprecatedNameWarning, stacklevel=2)
        return self._stages[new]

    def stage(self, name: str) -> Stage:
        """The stage called ``name`` (an old name warns and gives the renamed stage); unknown: an error."""
        found = self.find_stage(name)
        if found is None:
            raise BtforgeInputError(f"stage '{name}'", "is not provided by any installed plugin",
                                    did_you_mean(name, self.stages))
        return found

    def code_digest(self, name: str, memo: Path | None = None) -> str:
        """Digest of the code behind stage ``name``: part of every node's cache key (see :mod:`btforge.cachekey`)."""
        self._provide("stages", name)
        return self._code.digest(name, memo)

    def code_files(self, name: str) -> tuple[set[Path], set[Path]]:
        """The files that decide what stage ``name`` computes, and which of them are its own plugin's."""
        self._provide("stages", name)
        return self._code.files(name)

    def stages_with_role(self, role: str) -> list[Stage]:
        """The stages that declare ``role`` (e.g. ``"fit"``), by name."""
        return [self.stages[n] for n in sorted(self.stages) if self.stages[n].role == role]

    def accepts(self, port_type: str, value_type: str) -> bool:
        """Whether a port declared as ``port_type`` accepts a buffer of ``value_type`` (unknown types: never)."""
        if port_type not in self.types or value_type not in self.types:
            return False
        return issubclass(self.types[value_type], self.types[port_type])


class _Types(Mapping):
    """``{type name: Buffer subclass}`` of a registry: a lazy registry loads the plugin providing a name when it
    is first looked up, and every plugin when the types are listed."""

    def __init__(self, registry: Registry):
        self._registry = registry

    def __getitem__(self, name: str) -> type[buffers.Buffer]:
        self._registry._provide("types", name)
        return self._registry._type_dict[name]

    def __contains__(self, name: object) -> bool:
        if not isinstance(name, str):
            return False
        self._registry._provide("types", name)
        return name in self._registry._type_dict

    def __iter__(self) -> Iterator[str]:
        self._registry._everything()
        return iter(self._registry._type_dict)

    def __len__(self) -> int:
        self._registry._everything()
        return len(self._registry._type_dict)

    def __repr__(self) -> str:
        return repr(self._registry._type_dict)


def _api() -> tuple:
    """What decides which names plugins provide besides their own files: btforge's version, its plugin API, its
    hooks and its own buffer types."""
    from . import __version__
    return (__version__, hookspecs.PLUGIN_API_VERSION, sorted(h for h in dir(hookspecs) if h.startswith("btforge_")),
            sorted(t.type_name for t in buffers.CORE_TYPES))


def did_you_mean(name: str, options: Iterable[str]) -> str:
    options = sorted(options)
    near = difflib.get_close_matches(name, options, n=1, cutoff=0.5)
    if near:
        return f"did you mean '{near[0]}'?"
    return "known: " + ", ".join(options) if options else "nothing is registered"


def _bench_problem(name: str, fn: Any) -> str | None:
    return None if callable(fn) else f"expected a function bench(args) -> int, found {fn!r}"


_default: Registry | None = None


def default_registry() -> Registry:
    global _default
    if _default is None:
        start = time.perf_counter()
        _default = Registry(lazy=True)
        profile.record_phase("plugins_s", time.perf_counter() - start)
    return _default
