"""``aoi3d field backends`` and ``aoi3d field train`` on a tiny dataset (typer's CliRunner)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import pytest
from PIL import Image
from typer.testing import CliRunner

from aoi3d.field import BACKENDS, GridConfig
from aoi3d.scene import SceneConfig, SceneDataset, generate_dataset
from aoi3d_cli import app as root_app
from aoi3d_cli import field as field_cli

runner = CliRunner()


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> SceneDataset:
    cfg = SceneConfig(width=40, height=32, fps=10, duration_s=0.2, n_train=4, spp=1)
    return generate_dataset(tmp_path_factory.mktemp("scene") / "tiny", cfg, processes=1)


@dataclass(frozen=True)
class DescribedGrid(GridConfig):
    """A small grid for the tests.

    Not on the summary line."""

    grid_sizes: tuple[int, ...] = (12,)
    upsample_steps: tuple[int, ...] = ()
    background_size: tuple[int, int] = (8, 16)


@dataclass(frozen=True)
class Undocumented(GridConfig):
    batch_rays: int = 64


def test_backends_lists_every_registered_one(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(BACKENDS, "small", DescribedGrid)
    monkeypatch.setitem(BACKENDS, "bare", Undocumented)
    result = runner.invoke(root_app, ["field", "backends"])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert any("grid" in ln and "GridConfig" in ln for ln in lines)
    assert any("small" in ln and "A small grid for the tests." in ln for ln in lines)
    assert "Not on the summary line" not in result.output
    assert any("bare" in ln and "(no description)" in ln for ln in lines)
    assert field_cli.backend_summary(DescribedGrid) == "A small grid for the tests."


def test_parse_cameras(dataset: SceneDataset) -> None:
    parse = field_cli.parse_cameras
    assert parse("1-4", dataset) == [1, 2, 3, 4]
    assert parse("3,1, 2-3", dataset) == [3, 1, 2]
    for spec, message in [("0-2", "held-out"), ("1-9", "do not exist"), ("4-2", "before"),
                          ("a-b", "bad camera range"), (" , ", "no cameras")]:
        with pytest.raises(ValueError, match=message):
            parse(spec, dataset)


def test_train_scores_the_novel_view_and_writes_it(dataset: SceneDataset, tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(BACKENDS, "small", DescribedGrid)
    out = tmp_path / "views" / "novel.png"
    result = runner.invoke(root_app, [
        "field", "train", "--backend", "small", "--dataset", str(dataset.root), "--cameras",
        "1-3", "--frame", "1", "--seconds", "0.6", "--every", "0.25", "--threads", "1",
        "--device", "cpu", "--out", str(out)])
    assert result.exit_code == 0, result.output
    scores = [ln for ln in result.output.splitlines() if "PSNR" in ln and "step" in ln]
    assert len(scores) >= 3  # at 0.25, 0.5 and 0.6 s of training
    assert "cameras [1, 2, 3] at frame 1" in result.output
    assert "novel view after" in result.output and "LPIPS" in result.output
    with Image.open(out) as img:
        assert img.size == (dataset.width, dataset.height) and img.mode == "RGB"


@pytest.mark.parametrize(("args", "message"), [
    (["--backend", "instant-nerf"], "available: " + ", ".join(BACKENDS)),
    (["--cameras", "0-2"], "held-out"),
    (["--frame", "7"], "0..1"),
    (["--seconds", "0"], "must be > 0"),
    (["--device", "tpu"], "accepted: auto, cpu, cuda"),  # aoi3d.device's message
])
def test_train_refuses_bad_options(dataset: SceneDataset, args: list[str], message: str) -> None:
    result = runner.invoke(root_app, ["field", "train", "--dataset", str(dataset.root), *args])
    assert result.exit_code == 2
    text = " ".join(re.sub(r"[│╭╮╰╯─]", " ", result.output).split())  # unwrap rich's box
    assert message in text


def test_train_reports_a_missing_dataset(tmp_path: Path) -> None:
    result = runner.invoke(root_app, ["field", "train", "--dataset", str(tmp_path / "none")])
    assert result.exit_code == 1 and "error" in result.output
