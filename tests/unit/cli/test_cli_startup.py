"""A first run that works (issue 9 §4): a light command line, `aoi3d up`'s checks before start.

`import aoi3d_cli` imports neither torch nor kornia; `aoi3d --help` and `aoi3d up --help` take
well under a second of CPU; `aoi3d up` stops with one line, before starting anything, when a
port is taken or the dataset folder does not exist (and generates only where it may). The
processes take ports of their own (from this process's pid); CPU limits and waits scale with
AOI3D_TEST_TIMEOUT_SCALE.
"""

from __future__ import annotations

import json
import resource
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from tests.support.ports import block
from tests.support.timeouts import timeout_scale

SCALE = timeout_scale()
_PORTS = block("cli-startup")
PORT_OFFSET = _PORTS.rest_offset
ZENOH_PORT = _PORTS.zenoh
ROOT = Path(__file__).resolve().parents[3]
HELP_CPU_LIMIT_S = 1.5
"""CPU seconds `aoi3d --help` may take (the goal is under 1 s; measured ≈ 0.4 s)."""


def aoi3d(*args: str, cwd: Path = ROOT, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "aoi3d_cli", *args], cwd=cwd, text=True,
                          capture_output=True, timeout=timeout * SCALE)


def cpu_seconds(*args: str) -> float:
    """User + system CPU time of one `aoi3d …` process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = aoi3d(*args)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert done.returncode == 0, done.stderr[-2000:]
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def test_importing_the_cli_imports_neither_torch_nor_kornia() -> None:
    code = ("import json, sys, aoi3d_cli; print(json.dumps(sorted(m for m in "
            "('torch', 'kornia', 'scipy', 'matplotlib', 'zenoh', 'fastapi') "
            "if m in sys.modules)))")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, text=True,
                          capture_output=True, timeout=60 * SCALE)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == []


@pytest.mark.parametrize("args", [("--help",), ("up", "--help"), ("experiment", "--help")])
def test_help_takes_well_under_a_second_of_cpu(args: tuple[str, ...]) -> None:
    used = cpu_seconds(*args)
    assert used < HELP_CPU_LIMIT_S * SCALE, f"aoi3d {' '.join(args)}: {used:.2f} s of CPU"


def test_help_texts_name_the_real_presets() -> None:
    """The preset names in --help are constants (no engine import); they must stay true."""
    from aoi3d.experiment.config import PRESETS
    from aoi3d.rl.presets import PPO_PRESETS
    from aoi3d_cli.experiment import PRESET_NAMES
    from aoi3d_cli.ppo import PPO_PRESET_NAMES

    assert tuple(PRESETS) == PRESET_NAMES
    assert tuple(PPO_PRESETS) == PPO_PRESET_NAMES


def test_the_scene_defaults_are_the_experiments() -> None:
    from aoi3d.experiment.config import EXPERIMENT_DATASET, EXPERIMENT_SCENE
    from aoi3d.scene import SceneConfig
    from aoi3d.scene.framings import DEFAULT_FRAMING, FRAMING_DATASETS, FRAMING_SCENES
    from services.kit.settings import CommonSettings

    assert FRAMING_SCENES[DEFAULT_FRAMING] == EXPERIMENT_SCENE
    assert FRAMING_DATASETS[DEFAULT_FRAMING] == EXPERIMENT_DATASET
    assert FRAMING_SCENES["site"] == SceneConfig()
    assert CommonSettings.model_fields["dataset"].default == Path(EXPERIMENT_DATASET)


def test_the_live_group_is_registered() -> None:
    import typer

    from aoi3d_cli import app

    assert "live" in typer.main.get_command(app).commands


def test_channel_cli_numbers_cameras_like_the_pipeline() -> None:
    from aoi3d_cli import app

    result = CliRunner().invoke(app, ["channel", "simulate", "--cameras", "3", "--duration-s",
                                      "1", "--json"])
    assert result.exit_code == 0, result.output
    assert [c["camera"] for c in json.loads(result.stdout)["per_camera"]] == [1, 2, 3]
    table = CliRunner().invoke(app, ["channel", "simulate", "--cameras", "3", "--duration-s",
                                     "1"], env={"COLUMNS": "200"})
    rows = [line.split("│")[1].strip() for line in table.stdout.splitlines()
            if line.startswith("│")]
    assert rows[:3] == ["1", "2", "3"] and "0" not in rows


# --- aoi3d up: checks before anything starts --------------------------------------------------
def _listen(port: int) -> socket.socket:
    sock = socket.socket()
    sock.bind(("127.0.0.1", port))
    sock.listen()
    return sock


def _up(tmp_path: Path, *extra: str) -> subprocess.CompletedProcess:
    return aoi3d("up", "--port-offset", str(PORT_OFFSET), "--zenoh-port", str(ZENOH_PORT),
                 "--log-dir", str(tmp_path / "logs"), "--quiet", "--ready-timeout-s", "5",
                 "--duration-s", "1", *extra, cwd=tmp_path)


@pytest.mark.parametrize(("service", "option"), [("scheduler", "--port-offset"),
                                                 ("router", "--zenoh-port")])
def test_up_refuses_a_taken_port_in_one_line(tmp_path: Path, service: str, option: str) -> None:
    from services.supervisor import DEFAULT_PORTS

    port = ZENOH_PORT if service == "router" else DEFAULT_PORTS[service] + PORT_OFFSET
    with _listen(port):
        done = _up(tmp_path, "--dataset", str(tmp_path / "nowhere"))
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("error: ") and str(port) in lines[0] and option in lines[0]
    assert "pipeline up" not in done.stdout
    assert not (tmp_path / "logs").exists()  # nothing started, no log folder
    assert not (tmp_path / "nowhere").exists()


def test_up_does_not_generate_a_scene_at_a_typo(tmp_path: Path) -> None:
    done = _up(tmp_path, "--dataset", str(tmp_path / "typo"))
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert f"{tmp_path / 'typo'} does not exist" in lines[0] and "--generate" in lines[0]
    assert not (tmp_path / "typo").exists() and not (tmp_path / "logs").exists()


@pytest.mark.parametrize(("args", "folder", "framing"), [
    ((), "data/turbine-rotor", "rotor"),
    (("--framing", "site"), "data/turbine", "site"),
    (("--dataset", "mine", "--generate"), "mine", "rotor"),
    (("--dataset", "mine", "--generate", "--framing", "site"), "mine", "site"),
])
def test_up_generates_only_in_the_framings_folder_or_when_asked(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, args: tuple[str, ...], folder: str,
        framing: str) -> None:
    """Which scene `aoi3d up` generates where (generation and the pipeline are stand-ins)."""
    import aoi3d.scene
    import services.supervisor
    from aoi3d.scene import SceneConfig, generate_dataset
    from aoi3d.scene.framings import FRAMING_SCENES
    from aoi3d_cli import app

    small = generate_dataset(tmp_path / "small", SceneConfig(width=8, height=6, fps=10,
                                                             duration_s=0.5, n_train=2, spp=1,
                                                             rotor_rpm=120.0))
    asked = []

    def fake_ensure(path, cfg, progress=None, **_):
        asked.append((Path(path), cfg))
        return small

    class FakeSupervisor:
        def __init__(self, cfg, on_ready=None):
            self.cfg, self.failure = cfg, None

        def run(self) -> int:
            return 0

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(aoi3d.scene, "ensure_dataset", fake_ensure)
    monkeypatch.setattr(services.supervisor, "Supervisor", FakeSupervisor)
    monkeypatch.setattr(services.supervisor, "taken_ports", lambda cfg: [])
    result = CliRunner().invoke(app, ["up", *args])
    assert result.exit_code == 0, result.output
    assert asked == [(Path(folder), FRAMING_SCENES[framing])]


def test_up_reads_another_folder_as_it_is(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                          ) -> None:
    import aoi3d.scene
    import services.supervisor
    from aoi3d.scene import SceneConfig, generate_dataset
    from aoi3d_cli import app

    generate_dataset(tmp_path / "mine", SceneConfig(width=8, height=6, fps=10, duration_s=0.5,
                                                    n_train=2, spp=1, rotor_rpm=120.0))
    started = []

    class FakeSupervisor:
        def __init__(self, cfg, on_ready=None):
            self.cfg, self.failure = cfg, None

        def run(self) -> int:
            started.append(self.cfg.dataset)
            return 0

    monkeypatch.setattr(aoi3d.scene, "ensure_dataset", lambda *a, **k: pytest.fail("generated"))
    monkeypatch.setattr(services.supervisor, "Supervisor", FakeSupervisor)
    monkeypatch.setattr(services.supervisor, "taken_ports", lambda cfg: [])
    result = CliRunner().invoke(app, ["up", "--dataset", str(tmp_path / "mine")])
    assert result.exit_code == 0, result.output
    assert started == [tmp_path / "mine"] and "aoi3d layout" in " ".join(result.output.split())


def test_ppo_commands_take_their_own_options_then_the_shared_ones() -> None:
    """`aoi3d ppo train` and `eval` share their options the way the experiment commands do
    (cli.common.with_shared_options), not by copied lists."""
    import typer.main

    from aoi3d_cli.ppo import app

    shared = ["dataset", "steps_per_epoch", "processes", "threads", "cache", "no_cache", "device",
              "lpips", "set_"]
    commands = typer.main.get_command(app).commands
    for name in ("train", "eval"):
        names = [p.name for p in commands[name].params]
        assert names[-len(shared):] == shared, name
        assert not set(names[:-len(shared)]) & set(shared), name
