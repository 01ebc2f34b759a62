"""A dataset that cannot be read is one line naming the file and what to do (issue 9 §4).

Four kinds of damage — a missing frame, a truncated PNG, a transforms file that is not JSON, a
folder of no known layout — in the readers (:class:`aoi3d.scene.DatasetError`) and in every
command that reads a dataset: ``aoi3d scene info``, ``field train``, ``experiment``, ``up``.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from aoi3d.scene import (
    DatasetError,
    DatasetNotFound,
    SceneConfig,
    ensure_dataset,
    generate_dataset,
    open_dataset,
)
from tests.support.ports import block
from tests.support.timeouts import timeout_scale

SCALE = timeout_scale()
_PORTS = block("dataset-errors")
PORT_OFFSET = _PORTS.rest_offset
ZENOH_PORT = _PORTS.zenoh
SMALL = SceneConfig(width=16, height=12, fps=10, duration_s=0.5, n_train=3, spp=1,
                    rotor_rpm=120.0, framing="rotor")
KINDS = ("missing frame", "truncated png", "bad json", "wrong layout")
WHAT = {  # kind → (the file the line must name, words it must say)
    "missing frame": ("frames/cam02/0000.png", "missing"),
    "truncated png": ("frames/cam01/0000.png", "truncated"),
    "bad json": ("transforms_test.json", "not valid JSON"),
    "wrong layout": ("", "no dataset recognised"),
}


@pytest.fixture(scope="module")
def intact(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return generate_dataset(tmp_path_factory.mktemp("intact") / "scene", SMALL).root


def damaged(intact: Path, where: Path, kind: str) -> Path:
    """A copy of ``intact`` with one kind of damage."""
    root = where / kind.replace(" ", "-")
    shutil.copytree(intact, root)
    if kind == "missing frame":
        (root / "frames/cam02/0000.png").unlink()
    elif kind == "truncated png":
        path = root / "frames/cam01/0000.png"
        path.write_bytes(path.read_bytes()[:len(path.read_bytes()) // 2])
    elif kind == "bad json":
        (root / "transforms_test.json").write_text('{"frames": [')
    elif kind == "wrong layout":
        shutil.rmtree(root)
        root.mkdir()
        (root / "notes.txt").write_text("not a dataset")
    return root


def assert_one_line(text: str, root: Path, kind: str) -> str:
    """``text`` is one ``error:`` line naming the damaged file and what to do."""
    lines = [line for line in text.strip().splitlines() if line.strip()]
    assert len(lines) == 1, text
    line = lines[0]
    file, words = WHAT[kind]
    assert str(root) in line and file in line and words in line, line
    assert "generate" in line, line  # what to do
    assert "Traceback" not in text
    return line


# --- the readers -------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
def test_readers_raise_one_line_naming_the_file(intact: Path, tmp_path: Path, kind: str) -> None:
    root = damaged(intact, tmp_path, kind)
    with pytest.raises(DatasetError) as info:
        open_dataset(root, verify=True)
    assert_one_line(str(info.value), root, kind)
    assert info.value.path is not None and str(info.value.path).startswith(str(root))
    if kind in ("missing frame", "wrong layout"):
        assert isinstance(info.value, DatasetNotFound | FileNotFoundError)


def test_frame_reads_raise_dataset_errors(intact: Path, tmp_path: Path) -> None:
    missing = open_dataset(damaged(intact, tmp_path, "missing frame"))  # opens: not verified
    with pytest.raises(DatasetNotFound, match=r"cam02/0000\.png: frame file is missing"):
        missing.frame_png(2, 0)
    cut = open_dataset(damaged(intact, tmp_path, "truncated png"))
    for read in (cut.frame_png, cut.frame):
        with pytest.raises(DatasetError, match=r"cam01/0000\.png: .*truncated PNG"):
            read(1, 0)
    assert cut.frame(1, 1).shape == (12, 16, 3)  # the other frames still read


def test_check_frames_names_every_bad_file(intact: Path, tmp_path: Path) -> None:
    root = damaged(intact, tmp_path, "missing frame")
    (root / "frames/cam00/0003.png").write_bytes(b"")
    (root / "frames/cam03/0004.png").write_bytes(b"GIF89a" + bytes(100))
    ds = open_dataset(root)
    assert ds.check_frames() == [
        (root / "frames/cam00/0003.png", "empty"),
        (root / "frames/cam02/0000.png", "missing"),
        (root / "frames/cam03/0004.png", "not a PNG"),
    ]
    assert open_dataset(intact).check_frames() == []


def test_the_hint_is_the_command_that_regenerates_the_scene(intact: Path, tmp_path: Path
                                                           ) -> None:
    root = damaged(intact, tmp_path, "missing frame")
    with pytest.raises(DatasetError) as info:
        open_dataset(root, verify=True)
    hint = str(info.value).split("regenerate the dataset: ", 1)[1]
    assert hint == (f"aoi3d scene generate --out {root} --width 16 --height 12 --fps 10 "
                    "--duration-s 0.5 --n-train 3 --rotor-rpm 120 --spp 1 --force")
    from aoi3d_cli import app

    args = hint.split()[3:]  # what `aoi3d scene generate` would parse: the same scene
    generate = __import__("typer").main.get_command(app).commands["scene"].commands["generate"]
    params = generate.make_context("generate", args).params
    from aoi3d_cli.scene import scene_config

    fields = {k: v for k, v in params.items() if k in SceneConfig.__dataclass_fields__}
    assert scene_config(**fields) == SMALL


def test_ensure_dataset_regenerates_a_truncated_frame(intact: Path, tmp_path: Path) -> None:
    root = damaged(intact, tmp_path, "truncated png")
    ds = ensure_dataset(root, SMALL)
    assert ds.check_frames() == [] and ds.frame(1, 0).shape == (12, 16, 3)


def test_dnerf_frames_raise_dataset_errors(intact: Path, tmp_path: Path) -> None:
    from aoi3d.scene import export_dnerf

    out = export_dnerf(open_dataset(intact), tmp_path / "dnerf")
    ds = open_dataset(out)
    path = ds.frame_path(1, 0)
    path.write_bytes(path.read_bytes()[:40])
    with pytest.raises(DatasetError, match=str(path)):
        ds.frame(1, 0)
    path.unlink()
    with pytest.raises(DatasetNotFound, match=f"{path}: image file is missing"):
        ds.frame_png(1, 0)
    with pytest.raises(DatasetNotFound, match=r"image file\(s\) missing"):
        open_dataset(out)


# --- the commands ------------------------------------------------------------------------------
def invoke(*args: str):
    from aoi3d_cli import app

    return CliRunner().invoke(app, list(args), env={"COLUMNS": "80"})


@pytest.mark.parametrize("kind", KINDS)
def test_scene_info_field_train_and_experiment_say_one_line(intact: Path, tmp_path: Path,
                                                           kind: str) -> None:
    root = damaged(intact, tmp_path, kind)
    commands = {
        "scene info": ["scene", "info", str(root)],
        "field train": ["field", "train", "--dataset", str(root), "--frame", "0",
                        "--seconds", "0.1", "--threads", "1"],
        "experiment": ["experiment", "tradeoff", "--dataset", str(root), "--out",
                       str(tmp_path / "out"), "--cache", str(tmp_path / "cache")],
    }
    for name, args in commands.items():
        result = invoke(*args)
        assert result.exit_code == 1, (name, result.output)
        line = assert_one_line(result.stderr, root, kind)
        assert line.startswith("error: "), (name, line)
    assert not (tmp_path / "out").exists()  # nothing half-done


def test_scene_info_exits_non_zero_naming_the_missing_frames(intact: Path, tmp_path: Path
                                                            ) -> None:
    root = damaged(intact, tmp_path, "missing frame")
    (root / "frames/cam03/0001.png").unlink()
    result = invoke("scene", "info", str(root))
    assert result.exit_code == 1
    line = result.stderr.strip()
    assert "2 frame file(s)" in line and "cam02/0000.png (missing)" in line
    assert "cam03/0001.png (missing)" in line
    assert "4 cameras" in " ".join(result.stdout.split())  # the rest of the info is printed
    ok = invoke("scene", "info", str(intact))
    assert ok.exit_code == 0 and "present and whole" in ok.stdout


@pytest.mark.parametrize("kind", KINDS)
def test_up_says_one_line_before_starting_anything(intact: Path, tmp_path: Path,
                                                   kind: str) -> None:
    root = damaged(intact, tmp_path, kind)
    done = subprocess.run(
        [sys.executable, "-m", "aoi3d_cli", "up", "--dataset", str(root), "--port-offset",
         str(PORT_OFFSET), "--zenoh-port", str(ZENOH_PORT), "--log-dir",
         str(tmp_path / "logs"), "--quiet", "--duration-s", "1"],
        text=True, capture_output=True, timeout=60 * SCALE)
    assert done.returncode == 1, done.stdout + done.stderr
    assert_one_line(done.stderr, root, kind)
    assert not (tmp_path / "logs").exists()
