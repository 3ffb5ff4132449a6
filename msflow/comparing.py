"""``msflow compare``: what differs between two run records. Params and cache keys are compared exactly; metrics
within a tolerance, and printed compactly.

A metric is a float a stage computed, and the same computation summed in another order, on another CPU or with
another BLAS differs in its last bits (``0.1 + 0.2`` against ``0.3``): no change a user should chase. Two metric
values are equal when both are NaN, or when ``|a - b| <= ATOL + RTOL * max(|a|, |b|)`` (numpy.isclose's rule,
made symmetric so that ``compare A B`` and ``compare B A`` agree); infinities only equal themselves. Numbers are
printed with 6 significant digits, more when that is what tells the two values apart, with the absolute and the
relative difference. Standard library only.
"""

from __future__ import annotations

import math
from typing import Any

#: relative and absolute tolerance of metric comparisons (see the module docstring)
RTOL = 1e-9
ATOL = 1e-12
#: significant digits a number is printed with (up to the 17 a float64 needs, when two values need more to differ)
DIGITS = 6


def is_number(value: Any) -> bool:
    """An int or a float (a bool is a flag, compared exactly)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def metrics_equal(a: Any, b: Any) -> bool:
    """Whether two metric values count as the same: numbers within RTOL/ATOL, anything else exactly."""
    if not (is_number(a) and is_number(b)):
        return bool(a == b)
    x, y = float(a), float(b)
    if math.isnan(x) or math.isnan(y):
        return math.isnan(x) and math.isnan(y)
    if math.isinf(x) or math.isinf(y):
        return x == y
    return abs(x - y) <= ATOL + RTOL * max(abs(x), abs(y))


def format_pair(a: Any, b: Any) -> tuple[str, str]:
    """``a`` and ``b`` as printed: numbers with DIGITS significant digits, or as many more as it takes for two
    different numbers not to print alike (1.0000001 -> 1.0000002, never 1 -> 1)."""
    if not (is_number(a) and is_number(b)):
        return format_value(a), format_value(b)
    for digits in range(DIGITS, 18):
        shown = format_value(a, digits), format_value(b, digits)
        if shown[0] != shown[1]:
            break
    return shown


def format_value(value: Any, digits: int = DIGITS) -> str:
    """A number with ``digits`` significant digits (an int whole), anything else as Python shows it."""
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def metric_change(name: str, a: Any, b: Any) -> str:
    """``metric total: 26 -> 24 (-2, -7.69%)``."""
    shown_a, shown_b = format_pair(a, b)
    return f"  metric {name}: {shown_a} -> {shown_b}{difference(a, b)}"


def difference(a: Any, b: Any) -> str:
    """`` (+2, +7.69%)``: ``b - a`` and, when ``a`` is not zero, relative to ``a``; empty when not both finite numbers."""
    if not (is_number(a) and is_number(b)) or not (math.isfinite(a) and math.isfinite(b)):
        return ""
    delta = b - a
    relative = f", {100 * delta / abs(a):+.3g}%" if a else ""
    return f" ({delta:+.4g}{relative})"


def stage_differences(a: dict[str, Any], b: dict[str, Any], stage: str) -> tuple[list[str], int]:
    """The lines for ``stage`` in runs ``a`` and ``b`` (params, key, metrics), and how many of its metrics
    differ only within the tolerance (not listed)."""
    lines = []
    params_a = (a["config"].get(stage) or {}).get("params", {})
    params_b = (b["config"].get(stage) or {}).get("params", {})
    for name in sorted(set(params_a) | set(params_b)):
        if params_a.get(name) != params_b.get(name):  # exact: a param is what the user wrote
            lines.append(f"  param {name}: {params_a.get(name)!r} -> {params_b.get(name)!r}")
    record_a, record_b = a["stages"][stage], b["stages"][stage]
    if record_a.get("key") != record_b.get("key"):
        lines.append(f"  key {str(record_a.get('key'))[:12]} -> {str(record_b.get('key'))[:12]}")
    metrics_a, metrics_b = record_a.get("metrics") or {}, record_b.get("metrics") or {}
    within = 0
    for name in sorted(set(metrics_a) | set(metrics_b)):
        if name not in metrics_a or name not in metrics_b:
            only, value = ("A", metrics_a[name]) if name in metrics_a else ("B", metrics_b[name])
            lines.append(f"  metric {name}: {format_value(value)} (only in {only})")
        elif metrics_equal(metrics_a[name], metrics_b[name]):
            within += metrics_a[name] != metrics_b[name]
        else:
            lines.append(metric_change(name, metrics_a[name], metrics_b[name]))
    return lines, within


def compare_runs(a: dict[str, Any], b: dict[str, Any]) -> list[str]:
    """What ``msflow compare`` prints for run records ``a`` and ``b``."""
    lines = [f"A = {a['id']}", f"B = {b['id']}"]
    within = 0
    for stage in sorted(set(a["stages"]) | set(b["stages"])):
        if stage not in a["stages"] or stage not in b["stages"]:
            lines.append(f"{stage}: only in {'B' if stage not in a['stages'] else 'A'}")
            continue
        found, close = stage_differences(a, b, stage)
        within += close
        if found:
            lines += [f"{stage}:", *found]
    same = [s for s in a["stages"] if s in b["stages"] and a["stages"][s].get("key") == b["stages"][s].get("key")]
    lines.append(f"{len(same)} {'stage' if len(same) == 1 else 'stages'} identical (same key)")
    if within:
        lines.append(
            f"{within} metric {'value differs' if within == 1 else 'values differ'} only within the tolerance "
            f"(rtol {exponent(RTOL)}, atol {exponent(ATOL)}): taken as equal"
        )
    return lines


def exponent(value: float) -> str:
    """``1e-9`` (Python writes ``1e-09``)."""
    mantissa, _, power = f"{value:.0e}".partition("e")
    return f"{mantissa}e{int(power)}"
