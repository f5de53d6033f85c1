"""Every name a plugin contributes is unique across plugins: info readers, like stages and benches, are refused
on a clash rather than silently replaced."""
import types

import pytest

import btforge
from btforge import BtforgeInputError
from btforge.registry import Registry


def _reader_plugin(name: str, extension: str):
    module = types.ModuleType(name)
    module.BTFORGE_PLUGIN_API = 1
    module.btforge_info_readers = btforge.hookimpl(lambda: {extension: lambda path: {"reader": name}})
    return module


def test_two_plugins_reading_one_extension_are_refused_naming_both():
    first, second = _reader_plugin("first_reader", ".xyz"), _reader_plugin("second_reader", ".xyz")
    with pytest.raises(BtforgeInputError, match="info reader for '.xyz'.*both plugin '(first|second)_reader' and "
                                                "plugin '(first|second)_reader'"):
        Registry(load_entry_points=False, extra_plugins=[first, second])


def test_readers_of_different_extensions_are_all_kept():
    registry = Registry(load_entry_points=False, extra_plugins=[_reader_plugin("a_reader", ".aaa"),
                                                                _reader_plugin("b_reader", ".bbb")])
    assert {ext: reader(None)["reader"] for ext, reader in registry.info_readers.items()} == {
        ".aaa": "a_reader", ".bbb": "b_reader"}


def test_the_built_in_readers_do_not_clash():
    assert {".lp", ".ptm", ".wang", ".btfm"} <= set(Registry().info_readers)
