"""The doctor's verdict on one property of one input: name, subject, verdict, the number behind
it with its unit, and what to change."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

OK, WARNING, PROBLEM = 'ok', 'warning', 'problem'
# Not judged: the bag cannot show it (no stillness, no turning, no reference); `advice` says why.
SKIPPED = 'skipped'
SEVERITY = {SKIPPED: 0, OK: 1, WARNING: 2, PROBLEM: 3}


@dataclass(frozen=True)
class Check:
    """One verdict. `value` in `unit` is the number the verdict rests on (None: nothing to
    measure); `limit` the threshold it was held against; `details` further numbers (JSON)."""

    name: str
    subject: str
    verdict: str
    value: float | None
    unit: str
    advice: str
    limit: str = ''
    details: dict[str, Any] = field(default_factory=dict)
    fix: str = ''           # what the preset (params.yaml) does about it; '' nothing

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: non-finite numbers become None."""
        return {'name': self.name, 'subject': self.subject, 'verdict': self.verdict,
                'value': _finite(self.value), 'unit': self.unit, 'limit': self.limit,
                'advice': self.advice, 'fixed_by_preset': self.fix or None,
                'details': _json(self.details)}


def graded(value: float, warn: float, problem: float) -> str:
    """OK below warn, WARNING from warn, PROBLEM from problem (value and limits >= 0)."""
    if not math.isfinite(value) or value >= problem:
        return PROBLEM
    return WARNING if value >= warn else OK


def worst(checks: list[Check]) -> str:
    """The most severe verdict of the checks (SKIPPED when there are none)."""
    return max((c.verdict for c in checks), key=SEVERITY.__getitem__, default=SKIPPED)


def _finite(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _json(value):
    if isinstance(value, dict):
        return {str(k): _json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json(v) for v in value]
    if hasattr(value, 'tolist'):
        return _json(value.tolist())
    return _finite(value)
