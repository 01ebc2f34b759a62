"""Reading a /metrics exposition in tests."""

from __future__ import annotations

import re

_SITE = re.compile(r',site="[^"]*"|site="[^"]*",?')


def without_site(line: str) -> str:
    """A sample line with its ``site`` label taken out (``{}`` left out when it was the only
    one): the per-site services label every series with the site it is of."""
    return _SITE.sub("", line).replace("{}", "")
