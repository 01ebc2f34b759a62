"""The metrics' table (aoi3d/metric.py): every list of metric names is built from it, and the
lists written to files keep the columns they had."""

from __future__ import annotations

import ast
import dataclasses
import json
import re
from pathlib import Path

import pytest

from aoi3d import metric
from aoi3d.experiment.episode import EpisodeResult, EpochScore
from aoi3d.experiment.optimum import LOWER_IS_BETTER, sign_of
from aoi3d.experiment.oracle import ORACLE_METRICS, OracleSpec
from aoi3d.experiment.sweep import METRICS as SWEEP_METRICS
from aoi3d.experiment.tradeoff import OPTIMUM_METRICS
from aoi3d.live.summary import METRICS as LIVE_METRICS
from aoi3d.metric import BY_NAME, LPIPS, METRICS, PSNR, PSNR_DYNAMIC, REWARD, SSIM, Direction
from aoi3d.policy.adaptive import QUALITY_METRICS
from aoi3d.quality import RewardWeights
from aoi3d.rl.evaluate import EVAL_METRICS
from aoi3d.rl.record import EPISODE_COLUMNS
from services.kit.pb import aoi3d_pb2 as pb
from services.recorder.scoring import SCORES

ROOT = Path(__file__).resolve().parents[3]


def test_the_lists_written_to_files_keep_their_columns() -> None:
    # Spelled out once more, here only: the columns of sweeps' CSV/JSON, a live sweep's
    # points.csv, eval.csv and episodes.csv stay exactly what they were.
    assert SWEEP_METRICS == (
        "psnr_db", "ssim", "lpips", "reward", "psnr_dynamic_db", "ssim_dynamic",
        "dynamic_fraction", "n_selected", "aoi_used_ms", "mean_aoi_all_ms",
        "psnr_display_db", "ssim_display", "lpips_display", "reward_display",
        "psnr_dynamic_display_db", "compute_ms")
    assert OPTIMUM_METRICS == SCORES == (
        "psnr_db", "ssim", "lpips", "reward", "psnr_dynamic_db", "ssim_dynamic")
    # an oracle may maximise a score at display time too (issue 40's oracle:budgets)
    assert ORACLE_METRICS == ("reward", "psnr_db", "ssim", "lpips", "psnr_dynamic_db",
                              "ssim_dynamic", "psnr_display_db", "ssim_display",
                              "lpips_display", "reward_display", "psnr_dynamic_display_db")
    # the live sweep's: issue 40 added the PSNR at display time, written as the last columns
    assert LIVE_METRICS == ("psnr_db", "psnr_dynamic_db", "ssim", "lpips", "reward",
                            "psnr_display_db", "psnr_dynamic_display_db")
    assert QUALITY_METRICS == ("psnr_db", "reward", "ssim", "psnr_dynamic_db")
    assert EVAL_METRICS == ("reward", "psnr", "ssim", "lpips", "n_selected", "aoi_used_ms")
    assert EPISODE_COLUMNS[:7] == ("episode", "seed", "update", "reward", "psnr", "ssim",
                                   "lpips")


def test_every_metric_is_a_field_of_the_results_and_of_the_wire() -> None:
    names = [m.name for m in METRICS]
    assert len(set(names)) == len(names)
    episode = {f.name for f in dataclasses.fields(EpisodeResult)}
    epoch = {f.name for f in dataclasses.fields(EpochScore)}
    quality = set(pb.Quality.DESCRIPTOR.fields_by_name)
    for m in METRICS:
        assert m.name in episode and m.name in epoch and m.name in quality, m.name
        # optional: a Quality field with presence (display-time scores have it too: a render
        # may have no truth at its display time)
        assert pb.Quality.DESCRIPTOR.fields_by_name[m.name].has_presence == (
            m.optional or m.display), m.name
    for m in metric.SCORES:
        assert m.score == m.name and not m.dynamic and not m.display


def test_directions_labels_and_units() -> None:
    assert {m.name for m in METRICS if m.direction is Direction.LOWER} == LOWER_IS_BETTER \
        == {"lpips", "lpips_display"}
    assert sign_of("lpips") == sign_of("lpips_display") == -1.0
    assert sign_of("psnr_dynamic_db") == sign_of("reward") == sign_of("n_selected") == 1.0
    assert OracleSpec("rules", "lpips").sign == -1.0 and OracleSpec("rules", "ssim").sign == 1.0
    assert metric.lower_is_better("lpips") and not metric.lower_is_better("psnr")
    assert [m.axis_label for m in METRICS if not m.display] == [
        "PSNR (dB)", "SSIM", "LPIPS (lower is better)", "reward", "dynamic-region PSNR (dB)",
        "dynamic-region SSIM"]
    assert BY_NAME["psnr_dynamic_display_db"].label == "dynamic-region PSNR at display time"
    assert [m.digits for m in (PSNR, PSNR_DYNAMIC, SSIM, LPIPS, REWARD)] == [2, 2, 3, 3, 3]
    assert metric.find("psnr") is PSNR and metric.find("n_selected") is None


def test_the_reward_weighs_the_tables_terms() -> None:
    assert tuple(f.name for f in dataclasses.fields(RewardWeights)) == metric.REWARD_TERMS \
        == ("psnr", "ssim", "lpips", "psnr_dynamic", "ssim_dynamic")
    assert RewardWeights().terms(lpips=True) == ("psnr", "ssim", "lpips")
    assert RewardWeights().terms(lpips=False) == ("psnr", "ssim")


def test_the_console_charts_the_live_metrics() -> None:
    js = (ROOT / "services/console/static/console.js").read_text()
    block = re.search(r"const SERIES = \[(.*?)\];", js, re.S)
    assert block is not None
    series = [json.loads(f"[{m}]")[:2] for m in re.findall(r"\[([^\[\]]+)\]", block.group(1))]
    assert series == [[m.name, f"{m.label} ({m.unit})" if m.unit else m.label]
                      for m in (BY_NAME[n] for n in metric.LIVE)]
    companions = re.search(r"const COMPANIONS = \{(.*?)\};", js, re.S)
    assert companions is not None
    drawn = [json.loads(f"[{m}]")[0] for m in re.findall(r"\[([^\[\]]+)\]", companions.group(1))]
    assert drawn == [metric.PSNR_DISPLAY.name] and set(drawn) <= set(metric.LIVE_AT_DISPLAY)


def _spelled_lists(tree: ast.AST) -> list[tuple[int, list[str]]]:
    """Tuple, list and set literals naming two metrics or more (``__all__`` and OpenAPI
    ``examples=`` left out)."""
    known = {m.name for m in METRICS} | {m.short for m in METRICS}
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == "examples":
            skip.update(id(n) for n in ast.walk(node.value))
        if isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
            skip.update(id(n) for n in ast.walk(node.value))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Tuple | ast.List | ast.Set) and id(node) not in skip:
            hits = [e.value for e in node.elts
                    if isinstance(e, ast.Constant) and e.value in known]
            if len(hits) >= 2:
                out.append((node.lineno, hits))
    return out


def test_the_finder_finds_a_spelled_list() -> None:
    tree = ast.parse('X = ("psnr_db", "lpips")\n__all__ = ["psnr", "ssim"]\n'
                     'f(examples=[["psnr", "ssim"]])\nif m in ("ssim", "reward"): pass\n')
    assert _spelled_lists(tree) == [(1, ["psnr_db", "lpips"]), (4, ["ssim", "reward"])]


@pytest.mark.parametrize("package", ["aoi3d", "aoi3d_cli", "services", "bench", "deploy"])
def test_no_list_of_metric_names_is_spelled_outside_the_table(package: str) -> None:
    found = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel == "aoi3d/metric.py" or path.name.endswith("_pb2.py"):
            continue
        spelled = _spelled_lists(ast.parse(path.read_text(), rel))
        if spelled:
            found[rel] = spelled
    assert not found, f"build these from aoi3d.metric: {found}"
