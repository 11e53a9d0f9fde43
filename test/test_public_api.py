"""The package uses rosbags and mcap through their public names only: nothing imported from
them starts with an underscore or is left out of a module's `__all__`, and no attribute with a
leading underscore is read or set on anything but the package's own objects (self, cls) in a
module that uses them. Their internals (a writer's open chunk, its buffers, its statistics)
change between releases; a bag the package writes must not depend on them."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'sensing_nodes'
LIBRARIES = ('rosbags', 'mcap')


def _library(module: str | None) -> bool:
    return (module or '').split('.')[0] in LIBRARIES


def _uses_a_library(tree: ast.AST) -> bool:
    return any((isinstance(n, ast.ImportFrom) and n.level == 0 and _library(n.module))
               or (isinstance(n, ast.Import) and any(_library(a.name) for a in n.names))
               for n in ast.walk(tree))


def private_uses(source: str) -> list[str]:
    """Where a module's source reaches past rosbags' or mcap's public names: an import of a
    private module or name (or one its module's __all__ leaves out), an attribute with a
    leading underscore on anything but self or cls (line: code)."""
    tree = ast.parse(source)
    if not _uses_a_library(tree):
        return []
    private = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and _library(node.module):
            exported = getattr(importlib.import_module(node.module), '__all__', None)
            for alias in node.names:
                if any(part.startswith('_') for part in node.module.split('.')) \
                        or alias.name.startswith('_') \
                        or (exported is not None and alias.name not in exported):
                    private.append(f'{node.lineno}: from {node.module} import {alias.name}')
        elif isinstance(node, ast.Import):
            private += [f'{node.lineno}: import {a.name}' for a in node.names
                        if _library(a.name) and any(p.startswith('_') for p in a.name.split('.'))]
        elif isinstance(node, ast.Attribute) and node.attr.startswith('_') \
                and not (node.attr.startswith('__') and node.attr.endswith('__')) \
                and not (isinstance(node.value, ast.Name) and node.value.id in ('self', 'cls')):
            private.append(f'{node.lineno}: {ast.unparse(node)}')
    return private


USERS = sorted(p for p in PACKAGE.rglob('*.py') if _uses_a_library(ast.parse(p.read_text())))


def test_the_bag_modules_are_checked():
    assert {p.relative_to(PACKAGE).as_posix() for p in USERS} >= {
        'bags/storage.py', 'bags/recovery.py', 'ros/cdr.py'}


@pytest.mark.parametrize('path', USERS, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_only_public_names_of_rosbags_and_mcap(path):
    assert private_uses(path.read_text()) == []


def test_the_rule_finds_private_state_and_private_imports():
    """What the bag writer once did (records written into a writer's open chunk) and a private
    or unexported import are found; the package's own private attributes are not."""
    assert private_uses(
        'from mcap.writer import Writer\n'
        'from mcap.writer import ChunkBuilder\n'            # not in mcap.writer.__all__
        'from rosbags.rosbag2 import _private\n'
        'def append(writer: Writer, data):\n'
        '    writer._Writer__chunk_builder.add_message(data)\n'
        'class Mine:\n'
        '    def f(self):\n'
        '        return self._own\n') == [
        '2: from mcap.writer import ChunkBuilder', '3: from rosbags.rosbag2 import _private',
        '5: writer._Writer__chunk_builder']
    assert private_uses('import os\nos._exit\n') == []      # a module without the libraries
