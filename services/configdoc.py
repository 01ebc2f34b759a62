"""The configuration reference: every environment variable the processes read.

``python -m services.configdoc`` prints it as a Markdown table; docs/configuration.md embeds
it between markers (``--update`` rewrites it there) and a test fails when the two drift
apart.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from pydantic_settings import BaseSettings

BEGIN, END = "<!-- config:begin -->", "<!-- config:end -->"

#: Variables the domain library reads directly (not through a settings class).
DOMAIN_VARIABLES: dict[str, tuple[str, str]] = {
    "AOI3D_LPIPS_WEIGHTS": ("`$XDG_CACHE_HOME/aoi3d/lpips`",
                            "Folder of the cached LPIPS weights (`python -m aoi3d.lpips fetch` "
                            "writes it, the metrics service reads it)."),
    "AOI3D_CACHE": ("(unset: `~/.cache/aoi3d`)",
                    "Folder whose `native/` holds the compiled fused kernels "
                    "(aoi3d/field/native.py), looked in first; the service image sets it to "
                    "`/opt/aoi3d-cache`, compiled in its build stage."),
    "AOI3D_NATIVE": ("`1`", "0 turns the fused C kernels off: the torch code runs (same "
                            "results up to float rounding, about 3.5× slower: 2.44 s "
                            "against 0.68 s per reconstruction in the service image)."),
}


def settings_classes() -> list[tuple[str, type[BaseSettings]]]:
    from services.kit.settings import CommonSettings
    from services.router import RouterSettings

    out: list[tuple[str, type[BaseSettings]]] = [("all services", CommonSettings),
                                                 ("router", RouterSettings)]
    from services.supervisor import SERVICES

    for name in SERVICES:
        out.append((name, importlib.import_module(f"services.{name}.settings").Settings))
    from services.ingest.settings import Settings as IngestSettings
    from services.recon.settings import Settings as ReconSettings

    out.append(("ingest (real cameras: `aoi3d up --rig`)", IngestSettings))
    out.append(("recon (each worker)", ReconSettings))
    return out


def _default(field) -> str:
    extra = field.json_schema_extra if isinstance(field.json_schema_extra, dict) else {}
    if "doc_default" in extra:  # a default computed from the environment: described instead
        return str(extra["doc_default"])
    value = field.default_factory() if field.default_factory is not None else field.default
    if isinstance(value, Path):
        value = str(value)
    if isinstance(value, list | tuple):
        value = ",".join(str(v) for v in value)
    if isinstance(value, dict):
        value = "{}" if not value else str(value)
    return f"`{value}`" if value not in ("", None) else "(empty)"


def markdown() -> str:
    rows = ["| variable | process | default | meaning |", "|---|---|---|---|"]
    for process, cls in settings_classes():
        prefix = cls.model_config.get("env_prefix", "")
        for name, field in cls.model_fields.items():
            if name == "common":
                continue
            desc = (field.description or "").replace("|", "\\|").replace("\n", " ")
            rows.append(f"| `{prefix}{name.upper()}` | {process} | {_default(field)} | {desc} |")
    for var, (default, desc) in DOMAIN_VARIABLES.items():
        rows.append(f"| `{var}` | aoi3d (domain) | {default} | {desc} |")
    return "\n".join(rows)


#: The page that embeds the table.
PAGE = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"


def embedded(page: str) -> str:
    """The table a page holds between the markers."""
    start, end = page.index(BEGIN) + len(BEGIN), page.index(END)
    return page[start:end].strip()


def update(path: Path = PAGE) -> bool:
    """Rewrite the page's configuration table; True when it changed."""
    text = path.read_text()
    start, end = text.index(BEGIN) + len(BEGIN), text.index(END)
    new = text[:start] + "\n" + markdown() + "\n" + text[end:]
    if new != text:
        path.write_text(new)
    return new != text


if __name__ == "__main__":
    import sys

    if sys.argv[1:] == ["--update"]:
        print(f"{PAGE} updated" if update(PAGE) else f"{PAGE} already current")
    else:
        print(markdown())
