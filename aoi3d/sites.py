"""The names that address a site: the segment of ``/sites/<site>/…`` and of the key space
``aoi3d/<run>/<site>/…``, and the label value of a site's series.

Domain, because the pool (:mod:`aoi3d.pool`) names its jobs' sites; ``services/kit/keys.py``
re-exports them for the key space. Standard library only.
"""

from __future__ import annotations

import re

DEFAULT_SITE = "site1"
"""The site of a one-site run, and the one the REST paths without ``/sites/<site>`` address."""
SITE_PATTERN = r"^[a-z0-9][a-z0-9_-]{0,31}$"
RESERVED_SITES = frozenset({"pool", "sites"})


def check_site(name: str) -> str:
    """``name`` if it can name a site (a key chunk, a URL segment, a label value), else
    ``ValueError``."""
    if not re.fullmatch(SITE_PATTERN, name) or name in RESERVED_SITES:
        raise ValueError(f"site name {name!r}: 1-32 of a-z 0-9 _ -, starting with a letter or "
                         f"digit, not one of {', '.join(sorted(RESERVED_SITES))}")
    return name


def site_names(n: int) -> list[str]:
    """The sites of an ``n``-site run: ``site1`` … ``site<n>``."""
    return [f"site{i}" for i in range(1, n + 1)]
