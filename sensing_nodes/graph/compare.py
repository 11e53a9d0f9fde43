"""Whether a replay reproduced a bag's recorded outputs: every field of every message compared,
floats within a tolerance that tells BLAS noise from a change of behaviour, the rest exactly."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from sensing_nodes.bags.input_bag import PassResult
from sensing_nodes.topics import WALL_PERIODIC_TOPICS

# A replay on another CPU (another OpenBLAS kernel: OPENBLAS_CORETYPE) sums in another order, so
# its floats may differ from the recording's in the last bits, and a difference can grow through
# the graph's feedback (fusion, the matcher's initial guess). Floats therefore count as
# reproduced when |a - b| <= ATOL + RTOL * max(|a|, |b|); integers, strings, lengths and bag
# times must be equal. Measured (docs/reproducibility.md): between the SkylakeX, Haswell,
# Sandybridge, Nehalem and Prescott kernels the largest difference was 1.1e-14 absolute, and
# 9.7e-10 relative only on values near zero (covariance cross terms); the worst field used
# 1/1000 of this tolerance, which is still far below what a change of behaviour gives (>= 1e-6).
REPRODUCE_RTOL = 1e-9
REPRODUCE_ATOL = 1e-11


def output_messages(path: str | Path, topics: set[str]) -> dict[str, list[tuple[int, bytes]]]:
    """topic -> [(bag time ns, CDR bytes)] in bag order, for the given topics."""
    from sensing_nodes.bags.storage import BagReader

    out: dict[str, list[tuple[int, bytes]]] = {t: [] for t in topics}
    for topic, stamp, raw in BagReader(path).raw(topics):
        out[topic].append((stamp, raw))
    return out


@dataclass
class Difference:
    """The worst field of a comparison: its path, the absolute difference, and that difference
    over the tolerance at its magnitude (> 1: not reproduced; inf: not a float, or a length)."""

    where: str = ''
    absolute: float = 0.0
    excess: float = 0.0

    def worse(self, other: Difference) -> Difference:
        return other if (other.excess, other.absolute) > (self.excess, self.absolute) else self


def _float_difference(x, y, path: str, rtol: float, atol: float) -> Difference:
    """Element-wise comparison of two float arrays (NaN equals NaN, infinities equal only with
    the same sign)."""
    import numpy as np

    x, y = np.asarray(x, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()
    same = (x == y) | (np.isnan(x) & np.isnan(y))
    if same.all():
        return Difference()
    with np.errstate(invalid='ignore', over='ignore'):
        absolute = np.where(same, 0.0, np.abs(x - y))
        absolute = np.where(np.isnan(absolute), np.inf, absolute)
        excess = absolute / (atol + rtol * np.maximum(np.abs(x), np.abs(y)))
        excess = np.where(np.isnan(excess), np.inf, excess)
    i = int(np.argmax(excess))
    return Difference(f'{path}[{i}]' if x.size > 1 else path, float(absolute[i]), float(excess[i]))


def _cloud_columns(msg) -> dict[str, object] | None:
    """A PointCloud2's data as its declared fields (name -> numpy column), or None when its
    layout is not one numpy can describe."""
    import numpy as np

    kinds = {1: 'i1', 2: 'u1', 3: 'i2', 4: 'u2', 5: 'i4', 6: 'u4', 7: 'f4', 8: 'f8'}
    try:
        dtype = np.dtype({'names': [f.name for f in msg.fields],
                          'formats': [('>' if msg.is_bigendian else '<') + kinds[f.datatype]
                                      + ('' if f.count == 1 else f'({f.count},)')
                                      for f in msg.fields],
                          'offsets': [f.offset for f in msg.fields], 'itemsize': msg.point_step})
        points = np.frombuffer(bytes(msg.data), dtype=dtype, count=msg.width * msg.height)
    except (KeyError, ValueError, TypeError):
        return None
    return {name: points[name] for name in dtype.names}


def message_difference(a, b, path: str = '', rtol: float = REPRODUCE_RTOL,
                       atol: float = REPRODUCE_ATOL) -> Difference:
    """Worst difference between two decoded rclpy messages, every field compared: floats within
    the tolerance, everything else exactly (a PointCloud2's data as its declared fields)."""
    import numpy as np

    if hasattr(a, 'get_fields_and_field_types'):
        worst = Difference()
        fields = a.get_fields_and_field_types()
        columns = None
        if type(a).__name__ == 'PointCloud2' and fields.get('data') == 'sequence<uint8>':
            columns = (_cloud_columns(a), _cloud_columns(b))
        for name in fields:
            if name == 'data' and columns is not None and None not in columns:
                ca, cb = columns
                if list(ca) != list(cb) or any(ca[k].shape != cb[k].shape for k in ca):
                    worst = worst.worse(Difference(f'{path}.data (layout)', math.inf, math.inf))
                    continue
                for k in ca:
                    sub = f'{path}.data.{k}'
                    if ca[k].dtype.kind == 'f':
                        worst = worst.worse(_float_difference(ca[k], cb[k], sub, rtol, atol))
                    elif not np.array_equal(ca[k], cb[k]):
                        worst = worst.worse(Difference(sub, math.inf, math.inf))
                continue
            worst = worst.worse(message_difference(getattr(a, name), getattr(b, name),
                                                   f'{path}.{name}', rtol, atol))
        return worst
    if isinstance(a, (bytes, str, bool, int)) or a is None:
        return Difference() if type(a) is type(b) and a == b else \
            Difference(path, math.inf, math.inf)
    if isinstance(a, float):
        return _float_difference(a, b, path, rtol, atol)
    # Sequences and arrays: array.array, numpy arrays, lists of messages or strings.
    if len(a) != len(b):
        return Difference(f'{path} (length {len(a)} vs {len(b)})', math.inf, math.inf)
    if len(a) == 0:
        return Difference()
    kind = np.asarray(a).dtype.kind if not hasattr(a[0], 'get_fields_and_field_types') else 'O'
    if kind == 'f':
        return _float_difference(a, b, path, rtol, atol)
    if kind in 'iub':
        x, y = np.asarray(a), np.asarray(b)
        if np.array_equal(x, y):
            return Difference()
        i = int(np.argmax(x != y))
        return Difference(f'{path}[{i}]', math.inf, math.inf)
    worst = Difference()
    for i, (u, v) in enumerate(zip(a, b)):
        worst = worst.worse(message_difference(u, v, f'{path}[{i}]', rtol, atol))
    return worst


def compare_outputs(expected: dict[str, list[tuple[int, bytes]]],
                    actual: dict[str, list[tuple[int, bytes]]],
                    types: dict[str, str]) -> dict[str, dict]:
    """Per topic: message counts, how many are byte-identical (in canonical CDR), the worst
    difference among the others (absolute, and relative to the tolerance: 'excess' <= 1 is
    reproduced) and whether the topic is reproduced (same count, every message within it)."""
    from rclpy.serialization import deserialize_message

    from sensing_nodes.bags.storage import canonical_cdr, message_class

    report = {}
    for topic in sorted(set(expected) | set(actual)):
        a, b = expected.get(topic, []), actual.get(topic, [])
        entry = {'expected': len(a), 'actual': len(b), 'identical': 0, 'max_difference': 0.0,
                 'excess': 0.0, 'where': ''}
        cls = message_class(types[topic])
        worst = Difference()
        for (sa, ra), (sb, rb) in zip(a, b):
            if sa == sb and (ra == rb or canonical_cdr(ra, types[topic])
                             == canonical_cdr(rb, types[topic])):
                entry['identical'] += 1
                continue
            if sa != sb:
                d = Difference(f'bag time {sa} vs {sb}', math.inf, math.inf)
            else:
                d = message_difference(deserialize_message(ra, cls), deserialize_message(rb, cls))
            d.where = f'stamp {sa}: {d.where}'
            worst = worst.worse(d)
        entry.update(max_difference=worst.absolute, excess=worst.excess, where=worst.where)
        entry['reproduced'] = len(a) == len(b) and worst.excess <= 1.0
        entry['byte_identical'] = len(a) == len(b) == entry['identical']
        report[topic] = entry
    return report



def check_against(recorded: Path, results: list[PassResult]) -> bool:
    """Print, per pass and output topic, whether the replay reproduced the bag's recorded
    outputs (the topics both have, /diagnostics aside): floats within the tolerance (the bag may
    come from another CPU), the rest exactly. Passes after the first must equal the first byte
    for byte (canonical CDR): one process on one CPU is deterministic. True when all hold."""
    from sensing_nodes.bags.storage import topic_counts

    types = {t: v[0] for t, v in topic_counts(recorded).items()}
    topics = {t for r in results for t in r.outputs} & set(types) - WALL_PERIODIC_TOPICS
    expected = output_messages(recorded, topics)
    ok = True
    for k, r in enumerate(results):
        report = compare_outputs(expected, {t: r.outputs.get(t, []) for t in topics}, types)
        for topic, e in report.items():
            ok &= e['reproduced']
            print(f"  check pass {k + 1} {topic:<22} "
                  f"{'reproduced' if e['reproduced'] else 'DIFFERS'}: "
                  f"{e['identical']} of {e['expected']} byte-identical"
                  + (f", {e['actual']} replayed" if e['actual'] != e['expected'] else '')
                  + (f", largest difference {e['max_difference']:.3g} "
                     f"({e['excess']:.3g} x tolerance) at {e['where']}"
                     if e['identical'] != e['expected'] else ''))
        if k > 0:
            same = compare_outputs({t: results[0].outputs.get(t, []) for t in topics},
                                   {t: r.outputs.get(t, []) for t in topics}, types)
            for topic, e in same.items():
                ok &= e['byte_identical']
                print(f"  check pass {k + 1} {topic:<22} "
                      f"{'identical to pass 1' if e['byte_identical'] else 'DIFFERS FROM PASS 1'}"
                      + ('' if e['byte_identical'] else
                         f": {e['identical']} of {e['expected']} byte-identical, "
                         f"largest difference {e['max_difference']:.3g} at {e['where']}"))
    return ok

