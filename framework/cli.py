"""The ``btforge`` command line: run, validate, stages, info, devices, bench.

Bad input prints one clear message (no traceback unless ``--debug``) and exits with code 2.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import warnings
from pathlib import Path

import yaml

from .errors import BtforgeError, BtforgeInputError, BtforgeWarning


def parse_sets(items: list[str]) -> dict:
    """``--set NAME.PARAM=VALUE`` arguments as ``{'NAME.PARAM': value}``, each value read as YAML."""
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise BtforgeInputError(f"--set {item}", "expected NODE.PARAM=VALUE", "e.g. --set fit.variant=lrgb")
        try:
            out[key] = yaml.safe_load(value) if value else ""
        except yaml.YAMLError as exc:
            raise BtforgeInputError(f"--set {item}", f"the value is not valid YAML ({getattr(exc, 'problem', exc)})",
                                    "quote it for the shell, e.g. --set 'relit.lights=[[0, 0, 1]]'") from None
    return out


def _print_report(result, stream) -> None:
    rows = [("node", "stage", "status", "seconds", "peak MB", "where", "notes")]
    for r in result.report:
        notes = ", ".join(f"{k}={v}" for k, v in r.notes.items() if k != "warnings")
        rows.append((r.node, r.stage, r.status, f"{r.seconds:.2f}" if r.status == "ran" else "-",
                     f"{r.peak_rss_mb:.0f}" if r.peak_rss_mb else "-", _where(r.placement), notes[:90]))
    widths = [max(len(row[i]) for row in rows) for i in range(6)]
    for row in rows:
        print("  ".join(cell.ljust(w) for cell, w in zip(row[:6], widths)) + "  " + row[6], file=stream)


def _where(placement: dict) -> str:
    """Where a node ran, for the report table: local (with its bands when streamed), a scheduler with its tasks."""
    if not placement:
        return "-"
    counts = [f"{placement[k]} {k[:-1]}{'s' * (placement[k] != 1)}" for k in ("bands", "tasks") if k in placement]
    return ", ".join([placement["where"], *counts])


def _shown(path: Path) -> str:
    """``path`` relative to the current folder when that is shorter, else absolute."""
    import os
    absolute = path.resolve()
    relative = os.path.relpath(absolute)
    return relative if len(relative) < len(str(absolute)) else str(absolute)


FOLDER_AFTER = 4  # more files than this in one folder are listed as the folder and a count


def written_lines(output_paths: list[Path], out_dir: Path, since: float) -> list[str]:
    """The files a run wrote, for the end of ``btforge run``, in the order the stages asked for them: files by
    name, an output folder (or a folder other than ``out_dir`` holding many of the files) as the folder and its
    count.  Only what was modified since ``since`` (a ``time.time()``) counts as written."""
    def fresh(p: Path) -> bool:
        return p.is_file() and p.stat().st_mtime >= since - 1

    entries: dict[Path, list[Path]] = {}   # a folder (collapsed) or a file (itself) -> its written files
    for path in output_paths:
        if path.is_dir():
            members = sorted(p for p in path.rglob("*") if fresh(p))
            if len(members) > FOLDER_AFTER:
                entries[path] = members
            else:
                entries.update({p: [p] for p in members})
        elif fresh(path):
            entries[path] = [path]
    siblings: dict[Path, int] = {}
    for path, members in entries.items():
        if members == [path]:
            siblings[path.parent] = siblings.get(path.parent, 0) + 1
    lines, folded = [], set()
    for path, members in entries.items():
        parent = path.parent
        if members == [path] and siblings[parent] > FOLDER_AFTER and parent.resolve() != out_dir.resolve():
            if parent not in folded:
                folded.add(parent)
                lines.append(f"  {_shown(parent)}/ ({siblings[parent]} files)")
        elif members == [path]:
            lines.append(f"  {_shown(path)}")
        else:
            lines.append(f"  {_shown(path)}/ ({len(members)} files)")
    return ["wrote:", *lines] if lines else []


def cmd_run(args) -> int:
    import time

    from .profile import record_phase
    importing = time.perf_counter()
    from .runner import DEFAULT_OUT, run  # NumPy and the engine load here (`import btforge` loads neither)
    record_phase("interpreter_and_imports_s", time.perf_counter() - importing)
    started = time.time()
    result = run(args.graph, only=args.only, set=parse_sets(args.set), out_dir=args.out, cache_dir=args.cache,
                 use_cache=not args.no_cache, quiet=False, report_path=args.report, scheduler=args.scheduler)
    _print_report(result, sys.stderr)
    for line in written_lines(result.output_paths, Path(args.out) if args.out else DEFAULT_OUT, started):
        print(line, file=sys.stderr)
    if args.profile:
        from .profile import format_profile
        print(format_profile(result.report_dict()), file=sys.stderr)
    return 0


def cmd_validate(args) -> int:
    from .graph import check_graph, load_graph
    from .registry import default_registry
    checked = check_graph(load_graph(args.graph, parse_sets(args.set)), default_registry(),
                          Path(args.out) if args.out else None)
    print(f"{args.graph}: ok ({len(checked.stages)} nodes, {checked.dag.number_of_edges()} edges)")
    for node, notes in checked.notes.items():  # 'auto' params the check narrowed for a consumer
        for what, why in notes.items():
            print(f"  node '{node}': {what}: {why}")
    return 0


def stage_record(st) -> dict:
    return {
        "name": st.name, "plugin": st.plugin, "version": st.version, "role": st.role, "summary": st.summary,
        "doc": st.doc, "deprecated_names": list(st.deprecated_names),
        "inputs": {p: {"type": t, "optional": p in st.optional_inputs} for p, t in st.inputs.items()},
        "outputs": dict(st.outputs),
        "params": [{"name": p.name, "type": p.type_text(), "default": None if p.required else _jsonable(p.default),
                    "required": p.required, "doc": p.doc} for p in st.params],
    }


def _jsonable(value):
    return list(value) if isinstance(value, tuple) else value


def cmd_stages(args) -> int:
    from .registry import default_registry
    reg = default_registry()
    # an unknown name is an error with a did-you-mean, not an empty listing; an old name shows the renamed stage
    wanted = {reg.stage(name).name for name in args.name or ()}
    records = [stage_record(reg.stages[n]) for n in sorted(reg.stages) if not wanted or n in wanted]
    if args.json:
        print(json.dumps(records, indent=2, default=str))
        return 0
    if args.markdown:
        print(stages_markdown(records))
        return 0
    for rec in records:
        role = f", role {rec['role']}" if rec["role"] else ""
        print(f"{rec['name']}  ({rec['plugin']}, v{rec['version']}{role})")
        if rec["deprecated_names"]:
            print(f"    deprecated name: {', '.join(rec['deprecated_names'])}")
        for line in rec["doc"].splitlines():
            print(f"    {line}")
        for port, info in rec["inputs"].items():
            print(f"    input  {port}: {info['type']}{' (optional)' if info['optional'] else ''}")
        for port, tname in rec["outputs"].items():
            print(f"    output {port}: {tname}")
        for p in rec["params"]:
            default = "required" if p["required"] else f"default {p['default']!r}"
            print(f"    param  {p['name']} ({p['type']}, {default}): {p['doc']}")
        print()
    return 0


def _numpydoc_to_markdown(doc: str) -> str:
    """NumPy-style section underlines would turn into Markdown headings: make them bold labels instead."""
    lines = doc.splitlines()
    out = []
    for i, line in enumerate(lines):
        if set(line.strip()) == {"-"} and i > 0:
            out[-1] = f"**{out[-1].strip()}**\n"
            continue
        out.append(line)
    return "\n".join(out)


def stages_markdown(records: list[dict]) -> str:
    """The stage reference as Markdown (docs/stages.md is this output)."""
    out = []
    for rec in records:
        out.append(f"#### `{rec['name']}`\n")
        if rec.get("deprecated_names"):
            old = ", ".join(f"`{n}`" for n in rec["deprecated_names"])
            out.append(f"*Deprecated name: {old} (still accepted, with a warning).*\n")
        out.append(_numpydoc_to_markdown(rec["doc"]) + "\n")
        ports = [f"input `{p}`: {i['type']}{' (optional)' if i['optional'] else ''}" for p, i in rec["inputs"].items()]
        ports += [f"output `{p}`: {t}" for p, t in rec["outputs"].items()]
        if ports:
            out.append("Ports: " + "; ".join(ports) + ".\n")
        if rec["params"]:
            out.append("| param | type | default | meaning |\n|---|---|---|---|")
            for p in rec["params"]:
                default = "required" if p["required"] else f"`{p['default']}`"
                out.append(f"| `{p['name']}` | {p['type'].replace('|', ' or ')} | {default} | {p['doc']} |")
            out.append("")
    return "\n".join(out)


def cmd_info(args) -> int:
    from .registry import default_registry
    path = Path(args.file)
    if not path.exists():
        raise BtforgeInputError(str(path), "file not found")
    readers = default_registry().info_readers
    reader = readers.get(path.suffix.lower())
    if reader is None:
        raise BtforgeInputError(str(path), f"no reader describes '{path.suffix}' files",
                                f"known: {', '.join(sorted(readers))}")
    from .errors import reading_file
    with reading_file(path, f"a '{path.suffix}' file", "the file is damaged or truncated; write it again, or check "
                      "that it is the kind of file its name says"):
        info = reader(path)
    if args.json:
        print(json.dumps(info, indent=2, default=str))
    else:
        print(path)
        for key, value in info.items():
            print(f"  {key}: {value}")
    return 0


def cmd_devices(args) -> int:
    import pyopencl as cl
    from .backend import _prepare_pocl_environment
    from .devices import BuildProbe, describe_devices, format_devices
    _prepare_pocl_environment()
    description = describe_devices(cl, args.device, BuildProbe(cl, recheck=args.recheck))
    print(json.dumps(description, indent=2) if args.json else format_devices(description))
    return 0


def cmd_bench(args) -> int:
    from . import bench
    return bench.main(args)


BUILT_IN_COMMANDS = ("run", "validate", "stages", "info", "bench")


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The command-line parser; plugins' subcommands are added unless ``argv`` names a built-in command (their
    hooks import what the commands need, which a ``btforge run`` should not pay for at start-up)."""
    parser = argparse.ArgumentParser(prog="btforge", description="Reflectance textures as a graph of stages.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    parser.add_argument("--device", help="OpenCL device: part of its platform or device name (or BTFORGE_DEVICE)")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("run", help="run a graph (only what the requested outputs need)")
    p.add_argument("graph")
    p.add_argument("--out", help="folder where output paths resolve (default: ./out)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", help="override a parameter")
    p.add_argument("--only", action="append", metavar="NODE", help="run only what this node needs (repeatable)")
    p.add_argument("--report", metavar="FILE.json", help="write the per-node report as JSON")
    p.add_argument("--cache", help="cache folder (default: $BTFORGE_CACHE_DIR/nodes or ~/.cache/btforge/nodes)")
    p.add_argument("--no-cache", action="store_true", help="neither read nor write the node cache")
    p.add_argument("--profile", action="store_true", help="print where the process spent its time: interpreter and "
                   "imports, plugins, device start, kernel builds (cached or not), each node")
    p.add_argument("--scheduler", default="local", metavar="local|dask|tcp://HOST:PORT",
                   help="where per-texel stages on stored stacks run: this process (default), a 2-worker local "
                        "dask cluster, or a running dask scheduler")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("validate", help="check a graph without running it")
    p.add_argument("graph")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE")
    p.add_argument("--out")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("stages", help="list the installed stages with their ports, params and docs")
    p.add_argument("name", nargs="*", help="only these stages")
    p.add_argument("--json", action="store_true")
    p.add_argument("--markdown", action="store_true", help="the reference as Markdown (as in docs/stages.md)")
    p.set_defaults(func=cmd_stages)

    p = sub.add_parser("info", help="describe a file (plugins provide the readers, by extension)")
    p.add_argument("file")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("devices", help="list the OpenCL devices: versions, compiler, whether each builds kernels, "
                       "and which btforge chooses and why")
    p.add_argument("--json", action="store_true")
    p.add_argument("--recheck", action="store_true", help="probe every device again instead of trusting the "
                   "verdicts kept in the cache")
    p.set_defaults(func=cmd_devices)

    from . import bench
    bench.add_parser(sub).set_defaults(func=cmd_bench)
    words = [word for word in (sys.argv[1:] if argv is None else argv) if not word.startswith("-")]
    if not words or words[0] not in BUILT_IN_COMMANDS:
        _add_plugin_commands(sub)
    return parser


def _add_plugin_commands(sub) -> None:
    """Subcommands from plugins' ``btforge_cli_commands`` hooks (``btforge NAME ...`` runs ``run(args)``)."""
    from .registry import default_registry
    for name, (add_arguments, run_command) in sorted(default_registry().cli_commands.items()):
        if name in sub.choices:
            raise BtforgeInputError(f"command '{name}'", "a plugin defines a command that btforge already has",
                                    "rename the plugin's command")
        summary = (run_command.__doc__ or "").strip().splitlines()
        p = sub.add_parser(name, help=summary[0] if summary else None)
        add_arguments(p)
        p.set_defaults(func=run_command)


def _unmap_large_blocks() -> None:
    """Serve allocations of 1 MB and more (bands of samples, temporaries) by their own mappings, returned to the
    system when freed.  glibc otherwise raises that threshold as large blocks are freed and keeps later ones on
    its heap, which fragments: a streamed SH fit of a stored BTF peaked 85 MB higher that way.

    Fixing that threshold also fixes the one for handing the heap's free top back at glibc's 128 kB default,
    where the heap shrank and grew again with every few hundred kB Python freed and allocated (3-4 thousand more
    page faults in a PTM run); the heap now keeps up to 1 MB free at its top, less than one mapped block."""
    import ctypes
    try:
        # the symbols this process has loaded (libc among them): ctypes.util.find_library would run ldconfig
        libc = ctypes.CDLL(None)
        libc.mallopt(-3, 1 << 20)  # M_MMAP_THRESHOLD
        libc.mallopt(-1, 1 << 20)  # M_TRIM_THRESHOLD
    except (OSError, AttributeError, TypeError):  # not glibc: its allocator decides
        pass


def _short_blas_spin() -> None:
    """Let NumPy's OpenBLAS threads sleep soon after their work.  They busy-wait for 2^28 processor cycles (about
    0.1 s) after starting and after each product before they sleep, so NumPy's import alone took 0.05 s of CPU:
    a core of a 2-core machine, while the process imports and decodes.  2^20 cycles (under a millisecond) still
    spans back-to-back products.  OpenBLAS reads the setting once, when NumPy loads it (so before that); a
    setting of the user's own wins."""
    os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "20")


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # the command line's own process
        _short_blas_spin()
    code = _main(argv)
    if argv is None:  # the command line's process ends here
        # Objects stay as they are until the process exits: the interpreter's collections at exit would only
        # walk every one of them (0.1 s of CPU after a PTM run); frozen, they are left out of those walks.
        import gc
        gc.disable()
        gc.freeze()
    return code


def _main(argv: list[str] | None) -> int:
    from .profile import record_phase, seconds_since_process_start
    started = seconds_since_process_start()
    if started is not None:
        record_phase("interpreter_and_imports_s", started)
    _unmap_large_blocks()
    try:
        parser = build_parser(argv)  # loads the plugins (their commands are subcommands): a bad plugin stops here
    except BtforgeInputError as exc:
        if argv is not None and "--debug" in argv or argv is None and "--debug" in sys.argv[1:]:
            raise
        print(f"error: {exc.render()}", file=sys.stderr)
        return exc.exit_code
    args = parser.parse_args(argv)

    def show_warning(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, BtforgeWarning):
            print(f"warning: {message}", file=sys.stderr)
        elif args.debug:
            print(warnings.formatwarning(message, category, filename, lineno, line), file=sys.stderr, end="")

    warnings.showwarning = show_warning
    try:
        if args.device and args.func is not cmd_devices:  # `devices` shows what the hint selects, and why
            from .backend import select_device
            select_device(args.device)
        return args.func(args) or 0
    except BtforgeInputError as exc:
        if args.debug:
            raise
        print(f"error: {exc.render()}", file=sys.stderr)
        return exc.exit_code
    except BtforgeError as exc:
        if args.debug:
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # output piped into `head` and the like
        sys.stderr.close()
        return 0
    except Exception as exc:  # a bug, not bad input: keep the message short, the traceback behind --debug
        if args.debug:
            raise
        print(f"error: internal error ({type(exc).__name__}: {exc}); rerun with --debug for the traceback",
              file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted (outputs and cache entries are written atomically: nothing half-written was kept)",
              file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
