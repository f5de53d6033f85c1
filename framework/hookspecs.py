"""Every hook a btforge plugin can implement.

A plugin is a module (or object) that pluggy registers; it is found through the ``btforge.plugins`` entry-point
group (built-in families register the same way, see ``pyproject.toml``).  Implement any of the hooks below with
``@btforge.hookimpl``; all hooks are optional and are called once, when the registry loads, so a plugin can be
listed and validated (``btforge stages``, ``btforge validate``) without running any of its stages.

Example::

    from btforge import hookimpl, declare_stage, Param

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


@hookspec
def btforge_stages():
    """Return the stages this plugin provides.

    Returns
    -------
    list of btforge.stages.Stage
        Stages made with the :func:`btforge.declare_stage` decorator.  Names are dotted (``family.verb``) and must be
        unique across all installed plugins; a clash is reported naming both plugins.
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
        Maps a lower-case file extension (``".ptm"``) to a function ``path -> dict`` that reads only what it
        needs to describe the file (header, counts, sizes) and raises ``BtforgeInputError`` on bad files.
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
