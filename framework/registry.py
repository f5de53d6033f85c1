"""Finding plugins and the stages and buffer types they provide.

Plugins are discovered through the ``btforge.plugins`` entry-point group - the built-in families are listed
there too, so a third-party plugin is loaded exactly like a built-in one.  Tests and plugin authors may also
register a module or object directly with :meth:`Registry.register`.
"""
from __future__ import annotations

import difflib
import importlib.metadata
from typing import Any, Iterable

import pluggy

from . import buffers, hookspecs
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

    def _collect(self) -> None:
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
        self.cli_commands: dict[str, tuple[Any, Any]] = {}
        for impl in self.pm.hook.btforge_cli_commands.get_hookimpls():
            plugin_name = self.pm.get_name(impl.plugin) or repr(impl.plugin)
            for name, command in (impl.function() or {}).items():
                if name in self.cli_commands:
                    raise BtforgeInputError(f"command '{name}'", f"is defined by two plugins (one is {plugin_name})",
                                            "uninstall one of the plugins or rename the command")
                self.cli_commands[name] = command
        self.info_readers: dict[str, Any] = {}
        for result in self.pm.hook.btforge_info_readers():
            self.info_readers.update(result or {})

    def stage(self, name: str) -> Stage:
        try:
            return self.stages[name]
        except KeyError:
            raise BtforgeInputError(f"stage '{name}'", "is not provided by any installed plugin",
                                    did_you_mean(name, self.stages)) from None

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


_default: Registry | None = None


def default_registry() -> Registry:
    global _default
    if _default is None:
        _default = Registry()
    return _default
