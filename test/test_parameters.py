"""Every node's parameters come from one table over its settings dataclass
(sensing_nodes/parameters.py): what the tables hold (a description each, defaults their own
checks accept), how a table turns values into the dataclass and names what it refuses, that a
field added to a settings dataclass is a parameter with nothing else to edit, that the
parameter files shipped and documented set only parameters the nodes declare, that the node
pages document each parameter with its default, and that no node module declares a literal
default of its own."""

from __future__ import annotations

import ast
import dataclasses
import math
import re
from pathlib import Path

import pytest
import yaml

from sensing_nodes.core.config.gyro_integrator import GYRO_INTEGRATOR_PARAMETERS
from sensing_nodes.core.config.icp_matcher import ICP_MATCHER_PARAMETERS, IcpMatcherParameters
from sensing_nodes.core.config.line_extractor import LINE_EXTRACTOR_PARAMETERS
from sensing_nodes.core.config.sensor_sim import NODE_SETTINGS_PARAMETERS
from sensing_nodes.core.config.wheel_odometry import WHEEL_ODOMETRY_PARAMETERS
from sensing_nodes.core.fusion.config import FUSION_PARAMETERS, session_config
from sensing_nodes.core.scan_matching import ScanMatcherSettings
from sensing_nodes.core.sim.simulator import SIM_PARAMETERS
from sensing_nodes.parameters import (
    Param,
    ParameterError,
    ParameterTable,
    flatten,
    load_parameters,
)
from sensing_nodes.paths import config_file

ROOT = Path(__file__).resolve().parents[1]
# Each node's tables (complementary_fusion: one per method, sensor_sim: the simulation's numbers
# and the node's own settings).
TABLES = {
    'wheel_odometry': [WHEEL_ODOMETRY_PARAMETERS],
    'gyro_integrator': [GYRO_INTEGRATOR_PARAMETERS],
    'line_extractor': [LINE_EXTRACTOR_PARAMETERS],
    'icp_matcher': [ICP_MATCHER_PARAMETERS],
    'complementary_fusion': [FUSION_PARAMETERS['ekf'], FUSION_PARAMETERS['complementary']],
    'sensor_sim': [NODE_SETTINGS_PARAMETERS, SIM_PARAMETERS],
}


def _names(node: str) -> set[str]:
    return {name for table in TABLES[node] for name in table.names()}


@pytest.mark.parametrize('node', TABLES)
def test_every_parameter_is_described_and_its_defaults_pass_its_checks(node):
    for table in TABLES[node]:
        assert [p.name for p in table.parameters if not p.description] == [], \
            f'{node}: give these a Param(description) in its table'
        table.check(table.defaults)


# --- the mechanism on a worked example -----------------------------------------------------

@dataclasses.dataclass(frozen=True)
class _Inner:
    cell_m: float = 0.1
    count: int = 3

    def problems(self):
        return [('cell_m', 'must be > 0', self.cell_m)] if not self.cell_m > 0 else []


@dataclasses.dataclass(frozen=True)
class _Outer:
    mode: str = 'a'
    pose: tuple[float, float] = (0.5, 0.0)
    inner: _Inner = _Inner()
    block: _Inner = _Inner(count=7)
    hidden: int = 9

    def problems(self):
        out = [(f'inner.{f}', p, v) for f, p, v in self.inner.problems()]
        return out + ([('mode', "must be 'a' or 'b'", self.mode)]
                      if self.mode not in 'ab' else [])


_TABLE = ParameterTable(_Outer(), described={
    'mode': Param('the mode'),
    'pose': Param(elements=(Param('x', name='pose_x_m'), Param('y', -1.0, 1.0, name='pose_y_m'))),
    'inner.count': Param('count', 1, 10, name='points_per_cell'),
}, prefixes={'inner': 'map_'}, internal={'hidden'})


def test_a_table_names_nested_prefixed_renamed_and_split_fields():
    assert [(p.name, p.default) for p in _TABLE.parameters] == [
        ('mode', 'a'), ('pose_x_m', 0.5), ('pose_y_m', 0.0), ('map_cell_m', 0.1),
        ('points_per_cell', 3), ('block.cell_m', 0.1), ('block.count', 7)]
    config = _TABLE.config({'pose_y_m': 1, 'map_cell_m': 2, 'block.count': 4, 'other': 'x'})
    assert config == _Outer(pose=(0.5, 1.0), inner=_Inner(cell_m=2.0), block=_Inner(count=4))
    assert isinstance(config.inner.cell_m, float)     # an int given for a float: a float
    assert _TABLE.values(config)['pose_y_m'] == 1.0


@pytest.mark.parametrize('values, name, text', [
    ({'mode': 3}, 'mode', 'must be a string'),
    ({'points_per_cell': 2.5}, 'points_per_cell', 'must be an integer'),
    ({'points_per_cell': 11}, 'points_per_cell', 'must be within [1, 10]'),
    ({'pose_y_m': math.nan}, 'pose_y_m', 'must be within [-1, 1]'),
    ({'map_cell_m': 0.0}, 'map_cell_m', 'must be > 0'),           # the nested problems()
    ({'mode': 'c'}, 'mode', "must be 'a' or 'b'"),
])
def test_a_table_refuses_a_value_naming_its_parameter(values, name, text):
    with pytest.raises(ParameterError) as error:
        _TABLE.config(values)
    assert error.value.name == name and text in str(error.value)
    assert f"parameter '{name}'" in str(error.value)


def test_a_field_added_to_a_settings_dataclass_is_a_parameter_with_nothing_else_to_edit():
    """A field added to the scan matcher's settings (here in a subclass, as if added to
    ScanMatcherSettings) is declared by icp_matcher under its name, with the field's default,
    and set from its value; the same for a field of a nested block (the local map: map_)."""
    extended = dataclasses.make_dataclass(
        'Extended', [('gate_floor_m', float, 0.25)], bases=(ScanMatcherSettings,), frozen=True)
    defaults = IcpMatcherParameters(matcher=extended(**{
        f.name: getattr(IcpMatcherParameters().matcher, f.name)
        for f in dataclasses.fields(ScanMatcherSettings)}))
    table = ICP_MATCHER_PARAMETERS.with_defaults(defaults)
    assert table['gate_floor_m'].default == 0.25
    assert set(table.names()) - set(ICP_MATCHER_PARAMETERS.names()) == {'gate_floor_m'}
    assert table.config({'gate_floor_m': 0.5}).matcher.gate_floor_m == 0.5


# --- the parameter files --------------------------------------------------------------------

def test_files_layer_sections_and_nesting_as_ros_reads_them(tmp_path):
    first, second = tmp_path / 'a.yaml', tmp_path / 'b.yaml'
    first.write_text(yaml.safe_dump({
        '/**': {'ros__parameters': {'use_sim_time': True, 'x': 1}},
        'node': {'ros__parameters': {'x': 2, 'imu': {'source': 'rate'}}},
        'other': {'ros__parameters': {'y': 5}}}))
    second.write_text(yaml.safe_dump({'/node': {'ros__parameters': {'imu': {'topic': '/i'}}}}))
    assert load_parameters('node', first, second) == {
        'use_sim_time': True, 'x': 2, 'imu.source': 'rate', 'imu.topic': '/i'}
    assert load_parameters('node') == {}
    third = tmp_path / 'c.yaml'
    third.write_text('other: {ros__parameters: {y: 1}}\n')
    assert load_parameters('node', third) == {}
    with pytest.raises(ParameterError, match='has no node: ros__parameters'):
        load_parameters('node', third, require_section=True)
    broken = tmp_path / 'd.yaml'
    broken.write_text('node: [1, 2\n')
    for path, text in ((broken, 'is not valid YAML'), (tmp_path / 'none.yaml', 'cannot be read')):
        with pytest.raises(ParameterError, match=text) as error:
            load_parameters('node', path)
        assert error.value.name == 'params_file'


def _node_sections(path: Path) -> dict[str, dict]:
    data = yaml.safe_load(path.read_text()) or {}
    return {node.lstrip('/'): flatten(section.get('ros__parameters') or {})
            for node, section in data.items() if isinstance(section, dict)
            and 'ros__parameters' in section}


SHIPPED = sorted((ROOT / 'config').glob('*.yaml')) + sorted((ROOT / 'config').glob('*/*.yaml'))


@pytest.mark.parametrize('path', [p for p in SHIPPED if _node_sections(p)],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_shipped_parameter_files_set_only_parameters_the_nodes_declare(path):
    for node, values in _node_sections(path).items():
        assert set(values) - _names(node) == set(), f'{path}: {node}'
        for table in TABLES[node]:
            # Every value has its parameter's type and range, and the node starts with it.
            table.config({k: v for k, v in values.items() if k in table.names()})


def test_a_fusion_file_and_its_dotted_values_give_one_configuration():
    values = load_parameters('complementary_fusion', config_file('complementary_fusion.yaml'))
    assert session_config(values) == session_config(
        yaml.safe_load(config_file('complementary_fusion.yaml').read_text())[
            'complementary_fusion']['ros__parameters'])


# --- the node pages -------------------------------------------------------------------------

def _doc_value(token: str):
    """A default as a node page writes it ('true', '0.1745', '2*pi', "''", '[1e-3, 1e-9]')."""
    token = token.strip().strip('`').strip()
    if token in ("''", '""', ''):
        return ''
    if token.startswith('['):
        return [_doc_value(t) for t in _split(token[1:-1])]
    if token in ('true', 'false'):
        return token == 'true'
    factor = re.fullmatch(r'(\d*)\s*\*?\s*pi', token)
    if factor:
        return float(factor.group(1) or 1) * math.pi
    try:
        return float(token)
    except ValueError:
        return token


def _split(text: str) -> list[str]:
    """Comma-separated items, commas inside brackets or braces kept."""
    items, depth, current = [], 0, ''
    for char in text:
        depth += char in '[{' and 1 or char in ']}' and -1 or 0
        if char == ',' and depth == 0:
            items.append(current)
            current = ''
        else:
            current += char
    return [i.strip() for i in items + [current] if i.strip()]


def _expand(name: str) -> list[str]:
    """accel_bias_{x,y,z}_m_s2 -> its three names."""
    match = re.search(r'\{([^}]*)\}', name)
    if not match:
        return [name]
    return [name[:match.start()] + part + name[match.end():]
            for part in match.group(1).split(',')]


def _documented(page: Path) -> dict[str, list]:
    """name -> the defaults a page's parameter tables give it."""
    rows, in_table = {}, False
    for line in page.read_text().splitlines():
        if line.startswith('| parameter |'):
            in_table = True
            continue
        if not line.startswith('|'):
            in_table = False
        if not in_table or line.startswith('|---'):
            continue
        cells = [c.strip() for c in line.strip('|').split(' | ')]
        names = [n for cell in re.findall(r'`([^`]+)`', cells[0]) for n in _expand(cell)]
        defaults = [_doc_value(t) for t in _split(re.sub(r'\s*\([^)]*\)', '', cells[1]))]
        if len(defaults) == 1:
            defaults *= len(names)
        for i, name in enumerate(names):
            rows[name] = defaults[i::len(names)] if len(defaults) > len(names) else [defaults[i]]
    return rows


def _same(documented, actual) -> bool:
    if isinstance(actual, bool) or isinstance(actual, str):
        return documented == actual
    if isinstance(actual, (int, float)):
        return isinstance(documented, float) and math.isclose(documented, actual, rel_tol=1e-3,
                                                              abs_tol=1e-12)
    return isinstance(documented, list) and len(documented) == len(actual) and all(
        _same(d, a) for d, a in zip(documented, actual))


# Defaults a page describes in words.
IN_WORDS = {('sensor_sim', 'route')}


@pytest.mark.parametrize('node', TABLES)
def test_the_node_page_documents_every_parameter_with_its_default(node):
    documented = _documented(ROOT / 'docs' / 'nodes' / f'{node}.md')
    assert set(documented) ^ _names(node) == set(), \
        'in the docs but not declared, or declared but not in the docs'
    for name, defaults in documented.items():
        if (node, name) in IN_WORDS:
            continue
        actual = []
        for table in TABLES[node]:
            if name in table.names() and table[name].default not in actual:
                actual.append(table[name].default)
        # The first table's default; a page may give the other method's after it.
        assert len(defaults) <= len(actual) and all(
            _same(d, a) for d, a in zip(defaults, actual)), (name, defaults, actual)


# --- nodes declare nothing of their own ------------------------------------------------------

@pytest.mark.parametrize('path', sorted((ROOT / 'sensing_nodes' / 'nodes').glob('*.py')),
                         ids=lambda p: p.name)
def test_no_node_module_declares_a_parameter_with_a_literal_default(path):
    """A node's parameters come from its table: no declare_parameter of its own, no literal
    default handed to declare()."""
    literal = []
    for call in ast.walk(ast.parse(path.read_text())):
        if isinstance(call, ast.Call) and getattr(call.func, 'attr',
                                                  getattr(call.func, 'id', '')) in (
                'declare_parameter', 'declare', 'declare_parameters'):
            if any(isinstance(a, ast.Constant) for a in call.args) or \
                    getattr(call.func, 'attr', '') == 'declare_parameter':
                literal.append(call.lineno)
    assert literal == [], f'{path.name}: lines {literal}'
