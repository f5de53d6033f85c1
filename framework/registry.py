"""Finding plugins and the stages and buffer types they provide.

Plugins are discovered through the ``btforge.plugins`` entry-point group - the built-in families are listed
there too, so a third-party plugin is loaded exactly like a built-in one.  Tests and plugin authors may also
register a module or object directly with :meth:`Registry.register`.
"""
from __future__ import annotations

import difflib
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Iterable

import pluggy

from . import buffers, hookspecs, profile
from .cachekey import StageCode
from .errors import BtforgeInputError, DeprecatedNameWarning
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
        self._collect_types()
        self._collect_stages()
        self._collect_aliases()
        self.info_readers: dict[str, Any] = self._unique_names(
            "btforge_info_readers", "info reader for", "uninstall one of the plugins, or leave the extension to one")
        self._cli_commands = self._bench_commands = None
        self._code = StageCode(self.pm.get_plugins, self._stage_sources.__getitem__,
                               lambda name: self.stages[name].fn.__module__)

    def _collect_commands(self) -> None:
        self._cli_commands = self._unique_names(
            "btforge_cli_commands", "command", "uninstall one of the plugins or rename the command")
        self._bench_commands = self._unique_names(
            "btforge_bench_commands", "bench", "rename one of the benches", check=_bench_problem)

    def _collect_types(self) -> None:
        self.types: dict[str, type[buffers.Buffer]] = {t.type_name: t for t in buffers.CORE_TYPES}
        for impl in self.pm.hook.btforge_buffer_types.get_hookimpls():
            plugin_name = self._plugin_name(impl.plugin)
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

    def _collect_stages(self) -> None:
        self.stages: dict[str, Stage] = {}
        self._stage_sources: dict[str, Any] = {}  # stage name -> the plugin object that provided it
        for impl in self.pm.hook.btforge_stages.get_hookimpls():
            plugin_name = self._plugin_name(impl.plugin)
            for st in impl.function() or ():
                if not isinstance(st, Stage):
                    raise BtforgeInputError(f"plugin '{plugin_name}'", f"btforge_stages must return Stage objects, "
                                            f"found {st!r}", "decorate the stage function with @btforge.declare_stage(...)")
                if st.name in self.stages:
                    other = self.stages[st.name].plugin
                    raise BtforgeInputError(f"stage '{st.name}'", f"is defined by both {other} and {st.plugin}",
                                            "uninstall one of the plugins or rename the stage")
                self._check_ports(st)
                self.stages[st.name] = st
                self._stage_sources[st.name] = impl.plugin

    def _check_ports(self, st: Stage) -> None:
        for port, tname in st.outputs.items():
            if tname.startswith("=") and tname[1:] not in st.inputs:
                raise BtforgeInputError(f"stage '{st.name}', output '{port}'",
                                        f"takes the type of input '{tname[1:]}', which the stage does not have")
        for port, tname in {**st.inputs, **st.outputs}.items():
            if not tname.startswith("=") and tname not in self.types:
                raise BtforgeInputError(f"stage '{st.name}', port '{port}'", f"names unknown buffer type '{tname}'",
                                        f"known types: {', '.join(sorted(self.types))}")

    def _collect_aliases(self) -> None:
        """Old names of renamed stages -> their stage's name; an old name may not be any other stage's name."""
        self.aliases: dict[str, str] = {}
        for name, st in sorted(self.stages.items()):
            for old in st.deprecated_names:
                taken = name if old in self.stages else self.aliases.get(old)
                if taken is not None:
                    raise BtforgeInputError(f"stage name '{old}'", f"is both a deprecated name of '{name}' "
                                            f"({st.plugin}) and the name of '{taken}'",
                                            "drop the deprecated name from one of the stages")
                self.aliases[old] = name

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
        if name in self.stages:
            return self.stages[name]
        new = self.aliases.get(name)
        if new is None:
            return None
        place = f"{where}: " if where else ""
        warnings.warn(f"{place}stage '{name}' is deprecated, use '{new}'", DeprecatedNameWarning, stacklevel=2)
        return self.stages[new]

    def stage(self, name: str) -> Stage:
        """The stage called ``name`` (an old name warns and gives the renamed stage); unknown: an error."""
        found = self.find_stage(name)
        if found is None:
            raise BtforgeInputError(f"stage '{name}'", "is not provided by any installed plugin",
                                    did_you_mean(name, self.stages))
        return found

    def code_digest(self, name: str, memo: Path | None = None) -> str:
        """Digest of the code behind stage ``name``: part of every node's cache key (see :mod:`btforge.cachekey`)."""
        return self._code.digest(name, memo)

    def code_files(self, name: str) -> tuple[set[Path], set[Path]]:
        """The files that decide what stage ``name`` computes, and which of them are its own plugin's."""
        return self._code.files(name)

    def stages_with_role(self, role: str) -> list[Stage]:
        """The stages that declare ``role`` (e.g. ``"fit"``), by name."""
        return [self.stages[n] for n in sorted(self.stages) if self.stages[n].role == role]

    def accepts(self, port_type: str, value_type: str) -> bool:
        """Whether a port declared as ``port_type`` accepts a buffer of ``value_type`` (unknown types: never)."""
        if port_type not in self.types or value_type not in self.types:
            return False
        return issubclass(self.types[value_type], self.types[port_type])


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
        _default = Registry()
        profile.record_phase("plugins_s", time.perf_counter() - start)
    return _default
