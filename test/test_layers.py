"""The package's layers (README "Layout"): imports only point down, the core never imports
rclpy or message types, and no command module imports another."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'sensing_nodes'
# Lower number = lower layer; a module may import its own layer or any lower one.
LAYERS = {'topics': 0, 'paths': 0, 'parameters': 0, 'core': 1, 'bags': 2, 'ros': 3, 'nodes': 4,
          'graph': 5, 'doctor': 6, 'tools': 7, 'bench': 7}
ROS_PACKAGES = ('rclpy', 'rosbags', 'mcap', 'sensor_msgs', 'nav_msgs', 'geometry_msgs',
                'std_msgs', 'tf2_msgs', 'diagnostic_msgs', 'visualization_msgs', 'rosgraph_msgs',
                'rcl_interfaces', 'builtin_interfaces', 'lifecycle_msgs')


def _imports(path: Path) -> list[str]:
    """Every module a file imports, at any depth (function-local imports included)."""
    names = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.append(node.module)
            names += [f'{node.module}.{alias.name}' for alias in node.names]
    return names


def _layer_of(parts: tuple[str, ...]) -> str:
    return parts[0].removesuffix('.py')


MODULES = sorted(p for p in PACKAGE.rglob('*.py'))


def test_every_module_is_in_a_layer():
    unknown = {_layer_of(p.relative_to(PACKAGE).parts) for p in MODULES} - set(LAYERS) - {
        '__init__'}
    assert not unknown


@pytest.mark.parametrize('path', MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_point_down(path):
    own = _layer_of(path.relative_to(PACKAGE).parts)
    if own == '__init__':
        return
    upward = []
    for name in _imports(path):
        parts = name.split('.')
        if parts[0] != 'sensing_nodes' or len(parts) < 2 or parts[1] not in LAYERS:
            continue
        if LAYERS[parts[1]] > LAYERS[own]:
            upward.append(name)
        if own == 'tools' and parts[1] == 'tools' and len(parts) > 2 \
                and parts[2] != path.stem:
            upward.append(f'{name} (a command imports another)')
    assert not upward, f'{path.relative_to(PACKAGE)} imports upward: {sorted(set(upward))}'


@pytest.mark.parametrize('path', sorted((PACKAGE / 'core').rglob('*.py')),
                         ids=lambda p: str(p.relative_to(PACKAGE)))
def test_core_imports_no_ros(path):
    ros = [n for n in _imports(path) if n.split('.')[0] in ROS_PACKAGES]
    assert not ros, f'{path.relative_to(PACKAGE)} imports {ros}'
