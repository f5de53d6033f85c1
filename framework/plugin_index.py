"""Which installed plugin provides which stage and buffer type, remembered between processes.

Loading every installed plugin imports every family's modules: most of the btforge code a fresh process reads
(0.05 s of CPU with their bytecode cached, about 0.13 s where Python may not cache it), while a graph of three
nodes needs two plugins.  So after all plugins have been loaded and checked once, the names each provides are
kept under the cache root (``plugins/``), keyed by everything that decides them: the entry points of the
``btforge.plugins`` group with their distributions' versions, every file of each plugin's package (name, size,
modification and status-change times), btforge's version and plugin API, and Python's.  While that key holds, a
registry made with ``lazy=True`` (:func:`~btforge.registry.default_registry`) loads a plugin when one of its
stages or buffer types is first asked for; whatever needs every plugin (listing stages, an unknown name and its
did-you-mean, a plugin's command) loads them all, so answers and errors are the ones a full load gives.  Any
change to the installed plugins changes the key, and the next registry loads everything again and remembers the
new names; a name the index places wrongly loads everything too.
"""
from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import json
import os
import sys
import types
from pathlib import Path
from typing import Any

from .atomic import atomic_write_text
from .locations import default_cache_root

FORMAT = 1
KEEP = 8  # indexes kept: a few installations may share one cache root


def entry_points(group: str) -> dict[str, Any]:
    """``{name: entry point}`` of ``group`` in the order pluggy loads them (the first of a name wins)."""
    found: dict[str, Any] = {}
    for dist in list(importlib.metadata.distributions()):
        for ep in dist.entry_points:
            if ep.group == group and ep.name not in found:
                found[ep.name] = (ep, dist)
    return found


def _package_files(spec) -> list[list]:
    """``[relative path, size, mtime, ctime]`` of every file of a module's package (of a plain module: its file);
    the status-change time changes even where a copy restores an old modification time."""
    if spec.submodule_search_locations is None:
        st = os.stat(spec.origin)
        return [[os.path.basename(spec.origin), st.st_size, st.st_mtime_ns, st.st_ctime_ns]]
    files = []
    for root in spec.submodule_search_locations:
        folders = [root]
        while folders:
            folder = folders.pop()
            for entry in sorted(os.scandir(folder), key=lambda e: e.name):
                if entry.is_dir():
                    folders += [entry.path] if entry.name != "__pycache__" else []
                    continue
                st = entry.stat()
                files.append([os.path.relpath(entry.path, root), st.st_size, st.st_mtime_ns, st.st_ctime_ns])
    return files


def describe(group: str, api: tuple) -> tuple[str, dict[str, dict], dict[str, Any]] | None:
    """``(key, {plugin name: where its module lives}, {plugin name: entry point})`` of the installed plugins, or
    None when they cannot be told apart without loading them (an entry point naming an object in a module, a
    module not found)."""
    plugins, parts = {}, [FORMAT, list(api), sys.version, sys.implementation.cache_tag]
    found = entry_points(group)
    versions: dict[int, tuple[str, str]] = {}  # one reading of each distribution's metadata (the built-in
    # families share one)
    for name, (ep, dist) in found.items():
        if ":" in ep.value:  # a plugin object inside a module: its provider is not a module to stand in for
            return None
        try:
            spec = importlib.util.find_spec(ep.value)
        except (ImportError, ValueError):
            return None
        if spec is None or spec.origin is None:
            return None
        plugins[name] = {"module": ep.value, "file": spec.origin,
                         "path": list(spec.submodule_search_locations or ()) or None}
        if id(dist) not in versions:
            versions[id(dist)] = _name_and_version(dist)
        parts.append([name, ep.value, *versions[id(dist)], spec.origin, _package_files(spec)])
    key = hashlib.blake2b(json.dumps(parts, default=str).encode(), digest_size=20).hexdigest()
    return key, plugins, {name: ep for name, (ep, _) in found.items()}


def _name_and_version(dist) -> tuple[str, str]:
    """A distribution's name and version from the header of its metadata, without parsing the long description
    that follows it (``dist.metadata`` parses all of it: 9 ms for btforge's)."""
    header = {}
    for line in (dist.read_text("METADATA") or dist.read_text("PKG-INFO") or "").splitlines():
        if not line.strip():
            break
        key, _, value = line.partition(":")
        header.setdefault(key.strip().lower(), value.strip())
    return header.get("name", ""), header.get("version", "")


def _index_file(key: str) -> Path:
    return default_cache_root() / "plugins" / f"{key}.json"


def load(key: str) -> dict[str, dict] | None:
    """The names each plugin provided when the plugins of ``key`` were last loaded whole, or None."""
    try:
        record = json.loads(_index_file(key).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and record.get("key") == key else None


def save(key: str, plugins: dict[str, dict]) -> None:
    """Remember what each plugin provides (``plugins``: name -> module, file, path, stages, types); a cache
    root that cannot be written only means the next process loads every plugin again."""
    try:
        atomic_write_text(_index_file(key), json.dumps({"key": key, "plugins": plugins}, sort_keys=True))
        kept = sorted(_index_file(key).parent.glob("*.json"), key=lambda p: p.stat().st_mtime, reverse=True)
        for stale in kept[KEEP:]:  # editing a plugin makes a new key each time: keep the newest few
            stale.unlink(missing_ok=True)
    except OSError:
        pass


def stand_in(entry: dict) -> types.ModuleType:
    """A module object naming a plugin's module and its files without importing it, for the code digests of
    the stages that import it (:class:`btforge.cachekey.StageCode` reads only these attributes)."""
    module = types.ModuleType(entry["module"])
    module.__file__ = entry["file"]
    if entry["path"] is not None:
        module.__path__ = list(entry["path"])
    return module
