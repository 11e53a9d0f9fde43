"""Every node's parameters (name, default, range, description) as a table over its settings
dataclass, the values of a table -> the dataclass (checked as the node checks them), and the one
reader of ROS 2 parameter files (`node: ros__parameters: ...` YAML).

No ROS here: ros/params.py declares a table's parameters on a node, and the tools that run a
node's code without ROS build the same dataclass from the same files through the same table,
so the two cannot disagree. A table is made from the dataclass's fields: every field is a
parameter (a nested dataclass field by field, under its block's prefix), so a field added to a
settings dataclass is a parameter with nothing else to edit; the table only says what each
parameter means, its range, and where its name or type differs from the field's.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Generic, TypeVar

import yaml

Config = TypeVar('Config')


class ParameterError(ValueError):
    """A parameter value a node cannot run with: the node exits at start-up (status 2) naming
    it, a tool says why it cannot run."""

    def __init__(self, name: str, problem: str, value: Any = None) -> None:
        detail = f' (got {value!r})' if value is not None else ''
        super().__init__(f"parameter '{name}' {problem}{detail}")
        self.name, self.problem, self.value = name, problem, value


@dataclasses.dataclass(frozen=True)
class Param:
    """What one field of a settings dataclass means as a parameter, and its inclusive range.

    The default is the dataclass's own, never copied. `name`: the parameter's full name where it
    is not its block's prefix + the field's name. `to_value` / `from_value`: where the field's
    type is not a parameter type, field value -> parameter value and back (ValueError for a
    value the field cannot take). `dynamic`: a parameter of more than one type (a number or
    'auto'). `elements`: a tuple field set as one parameter per element (each element's name,
    description and range)."""

    description: str = ''
    minimum: float | None = None
    maximum: float | None = None
    name: str = ''
    to_value: Callable[[Any], Any] | None = None
    from_value: Callable[[Any], Any] | None = None
    dynamic: bool = False
    elements: tuple[Param, ...] = ()


@dataclasses.dataclass(frozen=True)
class Parameter:
    """One parameter as a node declares it: its default (a bool, int, float, str or a list of
    one of them, which fixes its type), description and inclusive range; the field it sets
    (`path`, dotted through nested dataclasses; `index`: its element of a tuple field)."""

    name: str
    default: Any
    description: str
    minimum: float | None = None
    maximum: float | None = None
    dynamic: bool = False
    path: str = ''
    index: int | None = None
    param: Param = Param()


class ParameterTable(Generic[Config]):
    """The parameters of a settings dataclass, one per field in field order, with its defaults.

    `described`: the Param of a field (by dotted path, 'local_map.cell_m'), else the one in
    the field's metadata ('param'); a field without one is a parameter named after it with no
    description yet (test_parameters.py asks for one).
    `prefixes`: the prefix of a nested dataclass's parameter names (by its path; default: its
    field name and a dot, as ROS 2 parameter files nest: 'ekf.'). `internal`: fields (or whole
    nested dataclasses) that are no parameter: what the node fixes or derives itself.
    """

    def __init__(self, defaults: Config, described: Mapping[str, Param] | None = None,
                 prefixes: Mapping[str, str] | None = None,
                 internal: Iterable[str] = ()) -> None:
        self.defaults = defaults
        self._described = dict(described or {})
        self._prefixes = dict(prefixes or {})
        self._internal = frozenset(internal)
        self._paths: set[str] = set()
        self.parameters: tuple[Parameter, ...] = tuple(self._walk(defaults, '', ''))
        self._by_name = {p.name: p for p in self.parameters}
        if len(self._by_name) != len(self.parameters):
            names = [p.name for p in self.parameters]
            raise ValueError(f'parameter names used twice: '
                             f'{sorted({n for n in names if names.count(n) > 1})}')
        unknown = (set(self._described) | set(self._prefixes) | self._internal) - self._paths
        if unknown:
            raise ValueError(f'{type(defaults).__name__} has no fields {sorted(unknown)}')

    def _walk(self, obj: Any, path_prefix: str, name_prefix: str) -> Iterator[Parameter]:
        for f in dataclasses.fields(obj):
            path = path_prefix + f.name
            self._paths.add(path)
            if path in self._internal:
                continue
            value = getattr(obj, f.name)
            spec = self._described.get(path) or f.metadata.get('param')
            if spec is None and dataclasses.is_dataclass(value):
                yield from self._walk(value, path + '.',
                                      name_prefix + self._prefixes.get(path, f.name + '.'))
                continue
            spec = spec or Param()
            if spec.elements:
                for i, element in enumerate(spec.elements):
                    yield Parameter(element.name, value[i], element.description,
                                    element.minimum, element.maximum, path=path, index=i,
                                    param=element)
                continue
            default = spec.to_value(value) if spec.to_value else _as_parameter(value)
            yield Parameter(spec.name or name_prefix + f.name, default, spec.description,
                            spec.minimum, spec.maximum, spec.dynamic, path, param=spec)

    def with_defaults(self, defaults: Config) -> ParameterTable[Config]:
        """The same table over other defaults (another instance, or a subclass's: what a field
        added to the dataclass makes of the parameters)."""
        return ParameterTable(defaults, self._described, self._prefixes, self._internal)

    def __getitem__(self, name: str) -> Parameter:
        return self._by_name[name]

    def names(self) -> list[str]:
        return [p.name for p in self.parameters]

    def build(self, values: Mapping[str, Any]) -> Config:
        """The dataclass with each parameter in `values` (by name; others keep their defaults)
        converted into its field, unchecked: ParameterError only for a value its conversion
        refuses. A nested dataclass that refuses its values at construction is kept with them,
        for its problems() to name."""
        updates: dict[str, Any] = {}
        for p in self.parameters:
            if p.name not in values:
                continue
            value = values[p.name]
            if p.index is not None:
                current = list(updates.get(p.path, _field(self.defaults, p.path)))
                current[p.index] = _number(value, p.default)
                updates[p.path] = tuple(current)
                continue
            try:
                updates[p.path] = p.param.from_value(value) if p.param.from_value else \
                    _as_field(value, _field(self.defaults, p.path), p.default)
            except ValueError as error:
                raise ParameterError(p.name, str(error), value) from None
        return _rebuild(self.defaults, updates, '')

    def config(self, values: Mapping[str, Any]) -> Config:
        """The dataclass from parameter values (by name, as a node declares them or a parameter
        file gives them; absent ones: the defaults; unknown names are not this node's and are
        left alone), checked as the node checks them at start-up: ParameterError naming the
        first parameter of the wrong type or out of its range, refused by its conversion, or
        refused by the dataclass's problems()."""
        for p in self.parameters:
            if p.name in values:
                _check(p, values[p.name])
        config = self.build(values)
        self.raise_problems(config)
        return config

    def check(self, config: Config) -> None:
        """ParameterError for the first parameter whose value in `config` (a dataclass of this
        table's type) has the wrong type or is out of its range, or that its problems()
        refuses."""
        for p in self.parameters:
            _check(p, self.value(config, p))
        self.raise_problems(config)

    def raise_problems(self, config: Config) -> None:
        """ParameterError naming the parameter of the first of config.problems()."""
        for field, problem, value in config.problems():
            raise ParameterError(self.name_of(field), problem, value)

    def value(self, config: Config, parameter: Parameter) -> Any:
        """The parameter's value in `config`."""
        value = _field(config, parameter.path)
        if parameter.index is not None:
            return value[parameter.index]
        return parameter.param.to_value(value) if parameter.param.to_value else \
            _as_parameter(value)

    def values(self, config: Config) -> dict[str, Any]:
        """Every parameter's value in `config`, by name."""
        return {p.name: self.value(config, p) for p in self.parameters}

    def name_of(self, field: str) -> str:
        """The parameter(s) of a field path that problems() names: its own, a tuple field's
        elements' ('laser_x_m/laser_y_m/laser_yaw_rad'), a field a nested dataclass reports
        as its own (an input's 'variance_per_m' set in its noise model) by the one parameter of
        that block ending so; else the label as problems() gave it ('use_*')."""
        exact = [p.name for p in self.parameters if p.path == field]
        if exact:
            return '/'.join(exact)
        block, _, leaf = field.rpartition('.')
        inside = [p.name for p in self.parameters if p.path.startswith(f'{block}.' if block
                                                                      else '')
                  and p.path.rpartition('.')[2] == leaf]
        return inside[0] if len(inside) == 1 else field


def _field(obj: Any, path: str) -> Any:
    for part in path.split('.'):
        obj = getattr(obj, part)
    return obj


def _rebuild(obj: Any, updates: Mapping[str, Any], prefix: str) -> Any:
    """obj with the updates (dotted paths below `prefix`) set, nested dataclasses rebuilt."""
    changes = {}
    for f in dataclasses.fields(obj):
        path = prefix + f.name
        if path in updates:
            changes[f.name] = updates[path]
        elif any(p.startswith(path + '.') for p in updates):
            changes[f.name] = _rebuild(getattr(obj, f.name), updates, path + '.')
    if not changes:
        return obj
    try:
        return dataclasses.replace(obj, **changes)
    except ValueError:
        # A dataclass that checks itself at construction (core.icp.IcpOptions...): the values
        # kept unchecked, so that its problems() name what it refused.
        unchecked = copy.copy(obj)
        for name, value in changes.items():
            object.__setattr__(unchecked, name, value)
        if not getattr(unchecked, 'problems', list)():
            raise
        return unchecked


def _as_parameter(value: Any) -> Any:
    """A field's value as a parameter value: a tuple as a list."""
    return list(value) if isinstance(value, tuple) else value


def _number(value: Any, default: Any) -> Any:
    """An int given for a float parameter as a float (parameter files write 1 for 1.0)."""
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def _as_field(value: Any, field_value: Any, default: Any) -> Any:
    """A parameter value as its field's type: a list as a tuple where the field is one."""
    if isinstance(value, Sequence) and not isinstance(value, str):
        element = default[0] if default else None
        items = [_number(v, element) for v in value]
        return tuple(items) if isinstance(field_value, tuple) else items
    return _number(value, default)


_TYPE_NAMES = {bool: 'true or false', int: 'an integer', float: 'a number', str: 'a string'}


def _is(value: Any, kind: type) -> bool:
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, kind)


def _check(p: Parameter, value: Any) -> None:
    """ParameterError unless value has the parameter's type and is within its range."""
    if p.dynamic:
        return
    default = p.default
    if isinstance(default, list):
        kind = type(default[0]) if default else None
        if isinstance(value, str) or not isinstance(value, Sequence) or (
                kind is not None and not all(_is(v, kind) for v in value)):
            raise ParameterError(p.name, 'must be a list' + (
                f' of {_TYPE_NAMES.get(kind, kind.__name__)} values' if kind else ''), value)
        return
    kind = type(default)
    if not _is(value, kind):
        raise ParameterError(p.name, f'must be {_TYPE_NAMES.get(kind, kind.__name__)}', value)
    low, high = p.minimum, p.maximum
    if (low is not None and not value >= low) or (high is not None and not value <= high):
        if low is not None and high is not None:
            problem = f'must be within [{low:g}, {high:g}]'
        else:
            problem = f'must be >= {low:g}' if low is not None else f'must be <= {high:g}'
        raise ParameterError(p.name, problem, value)


class CheckedAtConstruction:
    """Base of a settings dataclass that refuses at construction (ValueError) the first of its
    problems(): the checks its parameters are refused by."""

    def __post_init__(self) -> None:
        for field, problem, value in self.problems():
            raise ValueError(f'{field} {problem}, got {value!r}')

    def problems(self) -> list[tuple[str, str, object]]:
        return []


def flatten(params: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """{'imu': {'source': 'rate'}} -> {'imu.source': 'rate'}: dotted names, as ROS 2 reads a
    parameter file's nesting; already dotted names pass unchanged."""
    out: dict[str, Any] = {}
    for key, value in params.items():
        if isinstance(value, Mapping):
            out.update(flatten(value, f'{prefix}{key}.'))
        else:
            out[f'{prefix}{key}'] = value
    return out


def load_parameters(node: str, *files: str | Path, require_section: bool = False
                    ) -> dict[str, Any]:
    """`node`'s parameter values in ROS 2 parameter files, with dotted names, a later file's
    over an earlier's, as the node reads several --params-file: in each file the sections
    '/**', then `node`, then '/node' (the later over the earlier). ParameterError
    ('params_file') for a file that cannot be read or is not YAML, and with `require_section`
    for a non-empty file without a section for the node."""
    merged: dict[str, Any] = {}
    for path in map(Path, files):
        try:
            data = yaml.safe_load(path.read_text())
        except OSError as error:
            raise ParameterError('params_file', f'cannot be read: {error.strerror}',
                                 str(path)) from None
        except yaml.YAMLError as error:
            raise ParameterError('params_file', f'is not valid YAML: {error}',
                                 str(path)) from None
        found = False
        for key in ('/**', node, f'/{node}'):
            section = data.get(key) if isinstance(data, dict) else None
            if isinstance(section, dict) and isinstance(section.get('ros__parameters'), dict):
                merged.update(flatten(section['ros__parameters']))
                found = True
        if require_section and data and not found:
            raise ParameterError('params_file', f'has no {node}: ros__parameters: section',
                                 str(path))
    return merged
