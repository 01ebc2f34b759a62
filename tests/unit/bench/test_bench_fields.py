"""bench/fields.py: the radiance-field benchmark harness on a tiny scene with 1-s budgets."""

from __future__ import annotations

import importlib
import json
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import pytest

from aoi3d.field import BACKENDS, FieldConfig, GridConfig
from aoi3d.scene import SceneConfig, SceneDataset, generate_dataset

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    return importlib.import_module("bench.fields")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> SceneDataset:
    cfg = SceneConfig(width=40, height=32, fps=10, duration_s=0.1, n_train=8, spp=1)
    return generate_dataset(tmp_path_factory.mktemp("scene") / "tiny", cfg, processes=1)


@dataclass(frozen=True)
class TinyGrid(GridConfig):
    """A small grid standing in for the reference MLP."""

    grid_sizes: tuple[int, ...] = (16,)
    upsample_steps: tuple[int, ...] = ()
    background_size: tuple[int, int] = (8, 16)


def test_cameras_of_the_cases(bench: ModuleType) -> None:
    ids = list(range(1, 19))
    assert bench.spread(ids, 6) == [1, 4, 8, 11, 15, 18]
    assert bench.case_cameras("6", ids) == [1, 4, 8, 11, 15, 18]
    assert bench.case_cameras("all", ids) == ids
    assert bench.spread(ids, 30) == ids and bench.spread(ids, 1) == [1]
    with pytest.raises(ValueError, match="'all' or a number"):
        bench.case_cameras("some", ids)
    with pytest.raises(ValueError, match="at least 1"):
        bench.spread(ids, 0)
    assert bench.probe_times((5.0, 15.0)) == (1, 2, 3, 4, 5, 6, 8, 10, 12, 15)
    assert bench.probe_times((0.5, 2.5)) == (0.5, 1, 2, 2.5)


def test_time_to_reference_and_speedup(bench: ModuleType) -> None:
    def run(curve: list[tuple[float, float]], budgets: list[float]) -> dict:
        probes = [{"train_s": t, "psnr_db": p} for t, p in curve]
        return {"probes": probes, "checkpoints": [
            {"budget_s": b, "psnr_db": dict(curve)[b]} for b in budgets], "error": None}

    runs = {
        "fast": run([(5, 25.0), (15, 29.6), (60, 31.0)], [5, 15, 60]),
        "slow": run([(5, 20.0), (15, 24.0), (60, 28.0)], [5, 15, 60]),
        "nerf": run([(60, 26.0), (150, 29.5), (180, 29.5)], [60, 180]),
    }
    cmp = bench.compare_to_reference(runs, 180.0)
    assert cmp["target_psnr_db"] == 29.5
    assert cmp["backends"]["fast"] == {"time_s": 15, "speedup": 12.0, "trained_s": 60}
    assert cmp["backends"]["slow"] == {"time_s": None, "speedup": None, "trained_s": 60}
    assert cmp["backends"]["nerf"]["time_s"] == 150
    missing = bench.compare_to_reference({"fast": runs["fast"]}, 180.0)
    assert missing["target_psnr_db"] is None and "not in this run" in missing["note"]
    broken = bench.compare_to_reference({"nerf": {"error": "boom", "probes": []}}, 180.0)
    assert "failed: boom" in broken["note"]


def test_harness_writes_the_json(bench: ModuleType, dataset: SceneDataset, tmp_path: Path,
                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(BACKENDS, "nerf", TinyGrid)  # the reference, whatever is registered
    monkeypatch.setitem(BACKENDS, "broken", FieldConfig)  # builds no field: the run fails
    out = tmp_path / "fields.json"
    result = bench.main([
        "--dataset", str(dataset.root), "--backends", "grid,nerf,broken",
        "--budgets", "0.2,0.4", "--reference-s", "0.6", "--cases", "all,3",
        "--threads", "1", "--no-isolate", "--matmul-size", "128", "--out", str(out)])
    assert json.loads(out.read_text()) == json.loads(json.dumps(result))
    cfg = result["config"]
    assert cfg["budgets_s"] == [0.2, 0.4] and cfg["reference_s"] == 0.6
    assert cfg["backends"] == ["grid", "nerf", "broken"] and cfg["threads"] == 1
    assert result["code_version"] and result["machine"]["matmul_cpu_gflops_start"] > 0
    assert result["machine"]["matmul_cpu_gflops_end"] > 0
    assert set(result["cases"]) == {"all", "3"}
    assert result["cases"]["3"]["cameras"] == [1, 5, 8]
    assert result["cases"]["all"]["cameras"] == list(range(1, 9))
    for case in result["cases"].values():
        grid, nerf, broken = (case["runs"][b] for b in ("grid", "nerf", "broken"))
        assert broken["error"].startswith("NotImplementedError") and broken["checkpoints"] == []
        assert [c["budget_s"] for c in grid["checkpoints"]] == [0.2, 0.4]
        assert [c["budget_s"] for c in nerf["checkpoints"]] == [0.2, 0.4, 0.6]
        for c in grid["checkpoints"] + nerf["checkpoints"]:
            assert c["train_s"] >= c["budget_s"] and c["steps"] > 0
            assert 5 < c["psnr_db"] < 100 and -1 <= c["ssim"] <= 1
            assert c["lpips"] is None or 0 <= c["lpips"] < 2
        assert grid["checkpoints"][0]["lpips"] is not None or "LPIPS" in grid["lpips_note"]
        assert grid["rays_per_s"] > 0 and grid["render_s_median"] > 0
        assert len(grid["render_s_all"]) == cfg["render_repeats"]
        assert grid["memory"]["rss_delta_mb"] is not None and grid["memory"]["hwm_reset"]
        assert grid["config"]["batch_rays"] > 0
        assert grid["config_class"] == "GridConfig" and grid["cameras"] == case["cameras"]
        ref = case["reference"]
        assert ref["target_psnr_db"] == nerf["checkpoints"][-1]["psnr_db"]
        assert ref["backends"]["nerf"]["time_s"] is not None
        assert ref["backends"]["broken"]["time_s"] is None


def test_a_run_in_a_fresh_process(bench: ModuleType, dataset: SceneDataset) -> None:
    spec = bench.RunSpec(dataset=str(dataset.root), backend="grid", cameras=(1, 4, 8), frame=0,
                         budgets_s=(0.3,), probes_s=(0.3,), threads=1, device="cpu",
                         render_repeats=1, lpips=False)
    seen: list[dict] = []
    result = bench.run_isolated(spec, seen.append)
    assert result["error"] is None and result["lpips_note"].startswith("LPIPS disabled")
    assert [c["budget_s"] for c in result["checkpoints"]] == [0.3]
    assert seen and seen[-1]["event"] == "probe" and seen[-1]["steps"] == result["steps"]


def test_a_failing_run_reports_its_error(bench: ModuleType, dataset: SceneDataset,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    spec = bench.RunSpec(dataset=str(dataset.root), backend="no-such-backend", cameras=(1,),
                         frame=0, budgets_s=(0.3,), probes_s=(0.3,), threads=1, device="cpu")
    bench.main(["--run-spec", json.dumps(bench.asdict(spec))])  # what the child process does
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert last["event"] == "result" and "unknown field backend" in last["result"]["error"]
