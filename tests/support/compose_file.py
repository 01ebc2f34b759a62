"""compose.yaml, the image and pyproject as the deployment tests read them (tests/deploy/):
Compose interpolation with defaults only, a service's environment and command, the project
table, and the series the services' code defines."""

from __future__ import annotations

import ast
import re
import shlex
import tomllib
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[2]
_INTERPOLATION = re.compile(
    r"\$\{(?P<name>[A-Za-z_][A-Za-z0-9_]*)(?:(?P<op>:?-)(?P<default>[^}]*))?\}")


def _yaml(path: Path) -> Any:
    with path.open(encoding="utf-8") as f:
        return yaml.safe_load(f)  # resolves anchors and `<<` merge keys, as Compose does


def interpolate(value: object) -> str:
    """Resolve Compose ``${VAR:-default}`` with its default (never the caller's environment).

    A variable without a default would make the deployment depend on the shell, so it is an
    error here.
    """
    text = str(value)

    def repl(m: re.Match[str]) -> str:
        if m["op"] is None:
            raise ValueError(f"${{{m['name']}}} has no default in {text!r}")
        return m["default"]

    return _INTERPOLATION.sub(repl, text).replace("$$", "$")


def environment(service: dict[str, Any]) -> dict[str, str]:
    """A service's environment (map or list form), interpolated."""
    env = service.get("environment") or {}
    if isinstance(env, list):
        env = dict(item.split("=", 1) if "=" in item else (item, "") for item in env)
    return {str(k): interpolate(v) for k, v in env.items()}


def command(service: dict[str, Any]) -> list[str]:
    cmd = service.get("command") or []
    return [interpolate(c) for c in (shlex.split(cmd) if isinstance(cmd, str) else cmd)]


def project() -> dict[str, Any]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
METRIC_TYPES = {"Counter", "Gauge", "Histogram", "Summary", "Info", "Enum"}
EXPOSED_SUFFIXES = {
    "Counter": ("_total", "_created"),
    "Gauge": ("",),
    "Histogram": ("_bucket", "_sum", "_count", "_created"),
    "Summary": ("", "_sum", "_count", "_created"),
    "Info": ("_info",),
    "Enum": ("",),
}


def defined_metrics(root: Path = ROOT / "services") -> dict[str, set[str]]:
    """Exposed series names → label names, from the prometheus_client calls in ``root``.

    prometheus_client strips ``_total`` from a counter's name and exposes ``<name>_total``;
    a histogram exposes ``_bucket``/``_sum``/``_count``.
    """
    exposed: dict[str, set[str]] = {}
    for path in sorted(root.rglob("*.py")):
        if "pb" in path.relative_to(root).parts:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.Call):
                continue
            kind = getattr(node.func, "id", None) or getattr(node.func, "attr", None)
            # a custom collector's families (CounterMetricFamily …) expose the same names
            kind = kind.removesuffix("MetricFamily") if kind else kind
            if kind not in METRIC_TYPES:
                continue
            kwargs = {k.arg: k.value for k in node.keywords}
            name_node = node.args[0] if node.args else kwargs.get("name")
            if not (isinstance(name_node, ast.Constant) and isinstance(name_node.value, str)
                    and name_node.value.startswith("aoi3d_")):
                continue
            labels_node = node.args[2] if len(node.args) > 2 else (
                kwargs.get("labelnames") or kwargs.get("labels"))
            labels = {e.value for e in getattr(labels_node, "elts", [])
                      if isinstance(e, ast.Constant)}
            base = name_node.value
            if kind == "Counter":
                base = base.removesuffix("_total")
            for suffix in EXPOSED_SUFFIXES[kind]:
                exposed.setdefault(base + suffix, set()).update(labels)
    return exposed
