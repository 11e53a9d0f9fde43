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
                'value': _json(self.value), 'unit': self.unit, 'limit': self.limit,
                'advice': self.advice, 'fixed_by_preset': self.fix or None,
                'details': _json(self.details)}


def graded(value: float, warn: float, problem: float) -> str:
    """OK below warn, WARNING from warn, PROBLEM from problem (value and limits >= 0)."""
    if not math.isfinite(value) or value >= problem:
        return PROBLEM
    return WARNING if value >= warn else OK


def plural(count: int, word: str, words: str | None = None) -> str:
    """'1 gap', '2 gaps' ('1 was', '2 were' with words given)."""
    return f'{count} {word if count == 1 else (words or word + "s")}'


def number(value: float | None) -> str:
    """A figure for people: 4 significant digits, no exponent for everyday magnitudes,
    0 for what rounding noise leaves of zero, '' for nothing or non-finite."""
    if value is None or not math.isfinite(value):
        return ''
    if abs(value) < 1e-9:
        return '0'
    if 1e-3 <= abs(value) < 1e6:
        digits = max(0, 3 - int(math.floor(math.log10(abs(value)))))
        text = f'{value:.{digits}f}'
        return text.rstrip('0').rstrip('.') if '.' in text else text
    return f'{value:.3g}'


def worst(checks: list[Check]) -> str:
    """The most severe verdict of the checks (SKIPPED when there are none)."""
    return max((c.verdict for c in checks), key=SEVERITY.__getitem__, default=SKIPPED)


def _finite(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _json(value):
    """JSON-ready: numbers to 6 significant digits (no 17-digit noise), non-finite as None."""
    if isinstance(value, dict):
        return {str(k): _json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json(v) for v in value]
    if hasattr(value, 'tolist'):
        return _json(value.tolist())
    if isinstance(value, float) and math.isfinite(value):
        return float(f'{value:.6g}')
    return _finite(value)
