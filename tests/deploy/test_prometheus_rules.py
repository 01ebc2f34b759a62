"""The alert rules in deploy/prometheus/rules/: promtool checks and unit-tests them (when
promtool is installed: `.ci/setup/30-prometheus.sh` installs Debian's prometheus in CI), and
every series they name is one the code exports."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from tests.support.compose_file import defined_metrics

ROOT = Path(__file__).resolve().parents[2]
PROM = ROOT / "deploy" / "prometheus"
RULES = sorted((PROM / "rules").glob("*.yml"))
RULE_TESTS = sorted((PROM / "tests").glob("*.yml"))
PROMTOOL = shutil.which("promtool")
needs_promtool = pytest.mark.skipif(
    PROMTOOL is None, reason="promtool not installed (Debian: apt-get install prometheus; "
                             ".ci/setup/30-prometheus.sh does it in CI)")


def rules() -> list[dict]:
    return [r for f in RULES for g in yaml.safe_load(f.read_text())["groups"]
            for r in g["rules"]]


def with_service_down_after(for_: str) -> str:
    """The rule file with the service-down alert's ``for:`` changed (parsed, not patched as
    text: the file is generated)."""
    doc = yaml.safe_load(RULES[0].read_text())
    changed = 0
    for group in doc["groups"]:
        for rule in group["rules"]:
            if rule.get("alert") == "AoI3DServiceDown":
                rule["for"] = for_
                changed += 1
    assert changed == 1
    return yaml.safe_dump(doc, sort_keys=False, allow_unicode=True)


def test_the_alerts_the_operators_asked_for_exist() -> None:
    names = {r["alert"] for r in rules() if "alert" in r}
    assert names == {"AoI3DServiceDown", "AoI3DNoQuality", "AoI3DPSNRDrop",
                     "AoI3DNoCameraSelected", "AoI3DTrainerStalled",
                     "AoI3DRejectedMessagesRising", "AoI3DPoolEmpty", "AoI3DDecisionsLost",
                     "AoI3DCameraTopicUnpublished", "AoI3DRecordingFailed"}
    config = yaml.safe_load((PROM / "prometheus.yml").read_text())
    assert config["rule_files"] == ["rules/*.yml"]


def test_rules_name_only_exported_series() -> None:
    exported = set(defined_metrics()) | {"up"}
    for rule in rules():
        for name in re.findall(r"\b(aoi3d_[a-z0-9_]+|up)\b", rule["expr"]):
            assert name in exported, f"{rule}: {name} is not exported by the code"


@needs_promtool
def test_promtool_checks_the_config_and_rules() -> None:
    out = subprocess.run([PROMTOOL, "check", "config", "prometheus.yml"], cwd=PROM,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    out = subprocess.run([PROMTOOL, "check", "rules", *map(str, RULES)], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr


@needs_promtool
def test_promtool_rule_unit_tests_pass() -> None:
    assert RULE_TESTS
    out = subprocess.run([PROMTOOL, "test", "rules", *map(str, RULE_TESTS)],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr


@needs_promtool
def test_a_broken_rule_fails_its_unit_test(tmp_path: Path) -> None:
    """The unit tests can fail: a service-down rule that waits 5 min does not fire at 90 s."""
    (tmp_path / "rules").mkdir()
    text = with_service_down_after("5m")
    (tmp_path / "rules" / RULES[0].name).write_text(text)
    (tmp_path / "tests").mkdir()
    test_file = tmp_path / "tests" / RULE_TESTS[0].name
    test_file.write_text(RULE_TESTS[0].read_text())
    out = subprocess.run([PROMTOOL, "test", "rules", str(test_file)], capture_output=True,
                         text=True, timeout=300)
    assert out.returncode != 0 and "AoI3DServiceDown" in out.stdout + out.stderr
