"""Reading a Prometheus text exposition (a service's /metrics) in tests: one parser, three
questions.

* :func:`value`: the sample of one series, written as exposed (``name`` or
  ``name{a="1",b="2"}``); the ``site`` label the per-site services add is ignored.
* :func:`metric`: the first sample of ``name`` whose labels include ``**labels``.
* :func:`total`: the sum of the samples of ``name`` whose labels include ``**labels`` (all the
  label sets of a family when none are given)."""

from __future__ import annotations

import re
from collections.abc import Iterator

__all__ = ["REQUIRED", "MissingSeries", "metric", "samples", "total", "value"]

_LINE = re.compile(r"^([a-zA-Z_:][a-zA-Z0-9_:]*)(?:\{(.*)\})?\s+(\S+)")
_LABEL = re.compile(r'([a-zA-Z_][a-zA-Z0-9_]*)="((?:[^"\\]|\\.)*)"')
REQUIRED = object()
"""``value(..., default=REQUIRED)``: a series that must be exported."""


class MissingSeries(KeyError, AssertionError):
    """No sample matched: an assertion failure in a test, and a KeyError (so "not exported
    yet", which a live wait tolerates)."""


def _labels(text: str | None) -> dict[str, str]:
    return dict(_LABEL.findall(text or ""))


def samples(text: str) -> Iterator[tuple[str, dict[str, str], float]]:
    """Every sample of an exposition: (name, labels, value)."""
    for line in text.splitlines():
        if line.startswith("#"):
            continue
        m = _LINE.match(line)
        if m:
            yield m.group(1), _labels(m.group(2)), float(m.group(3))


def _matching(text: str, name: str, labels: dict[str, str]) -> list[float]:
    return [v for n, have, v in samples(text)
            if n == name and all(have.get(k) == want for k, want in labels.items())]


def value(text: str, series: str, default: object = None) -> float | None:
    """The value of ``series`` (``name`` or ``name{labels}``: exactly those labels, besides
    ``site``); ``default`` (None) when it is not exported, or :class:`MissingSeries` when
    ``default`` is :data:`REQUIRED`."""
    m = _LINE.match(series + " 0")
    assert m is not None, series
    name, want = m.group(1), _labels(m.group(2))
    for n, have, v in samples(text):
        if n == name and (have == want
                          or {k: x for k, x in have.items() if k != "site"} == want):
            return v
    if default is REQUIRED:
        raise MissingSeries(f"series {series} not exported")
    return default  # type: ignore[return-value]


def metric(text: str, name: str, **labels: str) -> float:
    """The first sample of ``name`` whose labels include ``labels``."""
    found = _matching(text, name, labels)
    if not found:
        raise MissingSeries(f"no sample {name}{labels}")
    return found[0]


def total(text: str, name: str, default: float | None = None, **labels: str) -> float:
    """The sum of the samples of ``name`` whose labels include ``labels``; ``default`` when
    there is none (else :class:`MissingSeries`)."""
    found = _matching(text, name, labels)
    if not found:
        if default is None:
            raise MissingSeries(f"no sample {name}{labels}")
        return default
    return sum(found)
