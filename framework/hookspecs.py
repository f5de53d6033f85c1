"""Every hook a btforge plugin can implement.

A plugin is a module (or object) that pluggy registers; it is found through the ``btforge.plugins`` entry-point
group (built-in families register the same way, see ``pyproject.toml``).  Implement any of the hooks below with
``@btforge.hookimpl``; all hooks are optional and are called once, when the registry loads, so a plugin can be
listed and validated (``btforge stages``, ``btforge validate``) without running any of its stages.

Every plugin states the plugin API it was written for, as a module (or object) attribute
``BTFORGE_PLUGIN_API = 1``; a plugin written for another version, or one that states none, is refused with a
message naming it.  A hook implementation whose name is not one of the hooks below (a typo) is refused too.

Example::

    from btforge import hookimpl, declare_stage, Param

    BTFORGE_PLUGIN_API = 1

    @declare_stage("mine.scale", inputs={"stack": "SampleStack"}, outputs={"stack": "SampleStack"},
           params=[Param("factor", "float", 2.0, "multiplier")])
    def scale(ctx, stack, *, factor):
        '''Multiply every sample by a constant.'''
        ...

    @hookimpl
    def btforge_stages():
        return [scale]
"""
from __future__ import annotations

import pluggy

hookspec = pluggy.HookspecMarker("btforge")
hookimpl = pluggy.HookimplMarker("btforge")

PLUGIN_API_VERSION = 1  # bump when a hook's signature or a buffer contract changes incompatibly


@hookspec
def btforge_stages():
    """Return the stages this plugin provides.

    Returns
    -------
    list of btforge.stages.Stage
        Stages made with the :func:`btforge.declare_stage` decorator.  Names are dotted (``family.verb``, the
        family being the plugin's package name) and must be unique across all installed plugins, old names of
        renamed stages (``deprecated_names``) included; a clash is reported naming both plugins.
    """


@hookspec
def btforge_buffer_types():
    """Return the buffer types this plugin defines.

    Returns
    -------
    list of type
        Subclasses of :class:`btforge.buffers.Buffer`.  Ports name types by their ``type_name``; a port accepts
        any subclass of the named type, so a stage taking ``ReflectanceModel`` takes every representation.
    """


@hookspec
def btforge_info_readers():
    """Return readers that describe files for ``btforge info``.

    Returns
    -------
    dict of str to callable
        Maps a lower-case file extension (``".exr"``) to a function ``path -> dict`` that reads only what it
        needs to describe the file (header, counts, sizes) and raises ``BtforgeInputError`` on bad files.  An
        extension two plugins read is refused, naming both.
    """


@hookspec
def btforge_bench_commands():
    """Return the benchmarks this plugin contributes to ``btforge bench``.

    Returns
    -------
    dict of str to callable
        Maps a bench name to ``bench(args: list[str]) -> int``: it parses its own arguments with argparse
        (``prog="btforge bench NAME"``), prints its figures, and returns an exit code.  The first line of its
        docstring is the one-line help ``btforge bench`` lists.  Names must be unique across plugins.
    """


@hookspec
def btforge_cli_commands():
    """Return command-line subcommands this plugin adds to ``btforge``.

    Returns
    -------
    dict of str to (callable, callable)
        Maps a command name (``"calibrate"``) to ``(add_arguments, run)``: ``add_arguments(parser)`` adds the
        command's arguments to its ``argparse`` sub-parser, and ``run(args) -> int`` runs it and returns the exit
        code.  The first line of ``run``'s docstring is the command's help.  ``run`` raises
        ``BtforgeInputError`` for bad input, which the CLI prints without a traceback (exit code 2).  A name
        that a built-in command or another plugin already uses is refused, naming both.
    """
