"""Channels that change: regimes, trace-driven links, a shared cell — and the parity of the
batch simulation with the ``Link`` the live network service uses."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from aoi3d.channel import (
    CellChannel,
    ChannelSpecError,
    DelaySpecError,
    Link,
    RegimeChannel,
    TraceChannel,
    camera_rngs,
    make_links,
    parse_channel,
    simulate,
    transmission_summary,
)

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "traces"
needs_traces = pytest.mark.skipif(
    not TRACES.is_dir(),
    reason=f"the cellular traces are not at {TRACES} (../shared/data/traces beside the "
           f"checkout; mahimahi's traces/ folder, GPL-3.0, not shipped with aoi3d)")


@pytest.fixture
def tiny_trace(tmp_path: Path) -> Path:
    """A 100-ms trace: 1 opportunity every 2 ms, and 4 at once at ms 50."""
    times = [*range(0, 50, 2), 50, 50, 50, 50, *range(52, 101, 2)]
    path = tmp_path / "tiny.up"
    path.write_text("\n".join(str(t) for t in times) + "\n")
    return path


# --- regimes -----------------------------------------------------------------------------------


def test_regimes_parse_cycle_and_round_trip() -> None:
    ch = parse_channel("regimes:exp:20@10s,exp:200@10s")
    assert isinstance(ch, RegimeChannel)
    assert ch.spec == "regimes:exp:20@10s,exp:200@10s"
    assert parse_channel(ch.spec) == ch
    assert ch.cycle_ms == 20_000
    assert ch.mean_ms == pytest.approx(110.0)
    assert [ch.regime_at(t) for t in (0, 9_999, 10_000, 19_999, 20_000, 45_000)] == [
        "exp:20", "exp:20", "exp:200", "exp:200", "exp:20", "exp:20"]
    assert ch.regime_at(10_500, start_ms=1000) == "exp:20"
    assert ch.changes_between(0, 40_000) == [(10_000, "exp:200"), (20_000, "exp:20"),
                                             (30_000, "exp:200"), (40_000, "exp:20")]
    mixed = parse_channel(" REGIMES: const:5@250ms , gamma:2:30@1.5s,exp:60@2000 ")
    assert mixed.spec == "regimes:const:5@250ms,gamma:2:30@1500ms,exp:60@2s"


@pytest.mark.parametrize(("spec", "problem"), [
    ("regimes:", "SPEC@DUR"),
    ("regimes:exp:20", "lacks its duration"),
    ("regimes:exp:20@0s", "from 1 ms"),
    ("regimes:exp:20@1.5ms", "whole number"),
    ("regimes:exp:20@soon", "not a number"),
    ("regimes:exp:-1@1s", "exp MEAN"),
    ("regimes:trace:x@1s", "unknown kind"),
    ("regimes:exp:20@1s,,exp:30@1s", "SPEC@DUR"),
])
def test_bad_regimes_are_refused_saying_why(spec: str, problem: str) -> None:
    with pytest.raises(DelaySpecError, match=problem) as err:
        parse_channel(spec)
    assert "regimes:SPEC@DUR" in str(err.value)  # the forms are listed
    assert "exp:MEAN" in str(err.value)


def test_a_regime_draws_from_the_regime_in_force_at_entry() -> None:
    """const regimes: the delivery slot says which regime the frame entered in."""
    link = Link("regimes:const:5@100ms,const:50@100ms", np.random.default_rng(0))
    assert link.offer(0) == 5
    assert link.offer(99) == 104
    assert link.offer(103) is None  # still in flight
    assert link.offer(104) == 154  # entered in the second regime
    assert link.offer(200) == 205  # the cycle starts again
    late = Link("regimes:const:5@100ms,const:50@100ms", np.random.default_rng(0), start_ms=50)
    assert late.offer(100) == 105  # 50 ms into the schedule


# --- parity: the batch simulation and the live service's Link -----------------------------------


def _link_run(spec: str, n: int, seed: int, period: int, duration: int, phases: list[int],
              sizes=lambda i, g: 12_000) -> tuple[list[list[int]], list[list[int]]]:
    """Frames offered in (slot, camera) order through ``make_links`` — what the network
    service does with the cameras' frames of one slot."""
    links = make_links(spec, camera_rngs(seed, n))
    offers = sorted((g, i) for i in range(n) for g in range(phases[i], duration, period))
    gens: list[list[int]] = [[] for _ in range(n)]
    dels: list[list[int]] = [[] for _ in range(n)]
    for g, i in offers:
        slot = links[i].offer(g, sizes(i, g))
        if slot is not None:
            gens[i].append(g)
            dels[i].append(slot)
    return gens, dels


@pytest.mark.parametrize("spec", ["regimes:exp:20@1s,exp:200@1s",
                                  "burst:exp:15,gamma:2:100,good=400ms,bad=200ms",
                                  "regimes:gamma:2:10@700ms,lognormal:4:0.5@300ms,const:40@1s",
                                  "trace:{tiny}", "trace:{tiny},offset=7,spread=40,scale=3",
                                  "cell:{tiny}", "cell:{tiny},spread=0,scale=0.5"])
def test_link_and_simulate_agree_on_changing_channels(spec: str, tiny_trace: Path) -> None:
    spec = spec.format(tiny=tiny_trace)
    n, seed, period, duration = 4, 3, 10, 6_000
    phases = [0, 7, 29, 45]
    def sizes(i: int, g: int) -> int:
        return 2_000 + 1_500 * i + (g % 3) * 3_000

    run = simulate(spec, period, n, duration, seed, phase_ms=phases, frame_bytes=sizes)
    gens, dels = _link_run(spec, n, seed, period, duration, phases, sizes)
    for i in range(n):
        np.testing.assert_array_equal(run.gen_ms[i], gens[i])
        np.testing.assert_array_equal(run.delivery_ms[i], dels[i])
    assert run.delay_spec == parse_channel(spec).spec
    assert run.dropped.sum() > 0


def test_stationary_specs_keep_their_fast_path_and_draws() -> None:
    a = simulate("exp:60", 30, 3, 5_000, seed=5)
    b = simulate(parse_channel("exp:60"), 30, 3, 5_000, seed=5)
    for x, y in zip(a.delivery_ms, b.delivery_ms, strict=True):
        np.testing.assert_array_equal(x, y)
    one = simulate("regimes:exp:60@1s", 30, 3, 5_000, seed=5)  # one regime = stationary
    for x, y in zip(a.delivery_ms, one.delivery_ms, strict=True):
        np.testing.assert_array_equal(x, y)


# --- traces ------------------------------------------------------------------------------------


def test_trace_transmission_follows_the_opportunities(tiny_trace: Path) -> None:
    link = Link(f"trace:{tiny_trace},spread=0", np.random.default_rng(0))
    assert link.offer(0, 1500) == 1  # the opportunity at 0 is used: at least 1 slot
    assert link.offer(1, 3000) == 4  # opportunities at 2 and 4
    assert link.offer(49, 6000) == 50  # four at once at ms 50
    assert link.offer(50, 1500) == 52  # the ones at 50 are used
    # the trace repeats with the period of its last time (100), as mahimahi does: its last
    # opportunity (100) and the next loop's first (0 + 100) fall in the same ms
    assert link.offer(99, 4500) == 102
    shifted = Link(f"trace:{tiny_trace},offset=48,spread=0", np.random.default_rng(0))
    assert shifted.offer(0, 6000) == 2
    slow = Link(f"trace:{tiny_trace},spread=0,scale=2", np.random.default_rng(0))
    assert slow.offer(1, 3000) == 8  # opportunities at 4 and 8


def test_cell_cameras_share_the_opportunities(tiny_trace: Path) -> None:
    links = make_links(f"cell:{tiny_trace},spread=0", camera_rngs(0, 3))
    assert [links[i].offer(0, 3000) for i in range(3)] == [2, 6, 10]
    own = make_links(f"trace:{tiny_trace},spread=0", camera_rngs(0, 3))
    assert [own[i].offer(0, 3000) for i in range(3)] == [2, 2, 2]


@pytest.mark.parametrize(("spec", "problem"), [
    ("trace:", "needs a trace path"),
    ("trace:/no/such/file", "cannot read trace"),
    ("trace:{tiny},speed=2", "unknown trace option"),
    ("trace:{tiny},scale=0", "scale must be in"),
    ("trace:{tiny},offset=-5", "whole number of ms"),
    ("cell:{tiny},offset=1,offset=2", "given twice"),
    ("trace:{bad}", "not a mahimahi trace"),
    ("trace:{backwards}", "non-decreasing"),
])
def test_bad_trace_specs_are_refused(spec: str, problem: str, tiny_trace: Path,
                                     tmp_path: Path) -> None:
    bad = tmp_path / "bad.up"
    bad.write_text("secret: not a number\n")
    backwards = tmp_path / "backwards.up"
    backwards.write_text("5\n3\n")
    with pytest.raises(ChannelSpecError, match=problem) as err:
        parse_channel(spec.format(tiny=tiny_trace, bad=bad, backwards=backwards))
    assert "secret" not in str(err.value)  # the file's contents are not echoed


def test_trace_specs_round_trip(tiny_trace: Path) -> None:
    for spec in (f"trace:{tiny_trace}", f"trace:{tiny_trace},offset=10,spread=0,scale=1.5",
                 f"cell:{tiny_trace},spread=20"):
        ch = parse_channel(spec)
        assert ch.spec == spec
        assert parse_channel(ch.spec) == ch
    assert isinstance(parse_channel(f"cell:{tiny_trace}"), CellChannel)
    assert isinstance(parse_channel(f"trace:{tiny_trace}"), TraceChannel)


README_TABLE = {  # the traces README: 12 kB every 30 ms, mean transmission (ms), drop ratio
    "TMobile-LTE-short.up": (11, 0.07),
    "Verizon-LTE-short.up": (20, 0.18),
    "ATT-LTE-driving-2016.up": (66, 0.63),
    "TMobile-UMTS-driving.up": (99, 0.74),
    "Verizon-EVDO-driving.up": (116, 0.77),
}


@needs_traces
@pytest.mark.parametrize("name", sorted(README_TABLE))
def test_one_camera_replay_matches_the_traces_readme(name: str) -> None:
    mean, drop = README_TABLE[name]
    got = transmission_summary(parse_channel(f"trace:{TRACES / name}"), 12_000, 30)
    assert got["mean_ms"] == pytest.approx(mean, rel=0.10)
    assert got["drop_ratio"] == pytest.approx(drop, abs=0.05)


@needs_traces
@pytest.mark.parametrize("name", sorted(README_TABLE))
def test_cli_simulate_on_a_trace_matches_the_readme(name: str) -> None:
    from typer.testing import CliRunner

    from aoi3d_cli import channel

    mean, drop = README_TABLE[name]
    result = CliRunner().invoke(channel.app, [
        "simulate", "--delay", f"trace:{TRACES / name}", "--frame-bytes", "12000",
        "--cameras", "6", "--duration-s", "300", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    assert data["mean_transmission_ms"] == pytest.approx(mean, rel=0.10)
    assert data["drop_ratio"] == pytest.approx(drop, abs=0.05)
    assert {"mean_aoi_ms", "p99_aoi_ms", "per_camera", "theory", "config"} <= set(data)
    assert data["config"]["frame_bytes"] == 12000


# --- bursts (Gilbert–Elliott) ------------------------------------------------------------------


def test_burst_spec_round_trips_and_refuses_bad_input() -> None:
    ch = parse_channel("burst:exp:20,exp:300")
    assert ch.spec == "burst:exp:20,exp:300,good=5s,bad=1s"
    assert parse_channel(ch.spec) == ch
    assert ch.mean_ms == pytest.approx((5 * 20 + 1 * 300) / 6)
    for bad, why in [("burst:exp:20", "two delay specs"), ("burst:exp:20,nope:1", "BAD"),
                     ("burst:exp:20,exp:30,good=1s,good=2s", "once each"),
                     ("burst:exp:20,exp:30,ugly=1s", "good=DUR")]:
        with pytest.raises(ChannelSpecError, match=why):
            parse_channel(bad)


def test_burst_links_spend_the_right_share_of_time_in_the_bad_state() -> None:
    """const states: each delay says the state; the bad share is bad / (good + bad)."""
    run = simulate("burst:const:1,const:2,good=300ms,bad=100ms", 10, 8, 60_000, seed=2)
    ys = np.concatenate([d - g for g, d in zip(run.gen_ms, run.delivery_ms, strict=True)])
    assert set(np.unique(ys)) == {1, 2}
    assert np.mean(ys == 2) == pytest.approx(0.25, abs=0.03)


def test_experiment_delay_lists_split_on_semicolons_when_a_spec_holds_commas() -> None:
    from aoi3d_cli.experiment import _spec_list

    assert _spec_list("exp:20,exp:60") == ["exp:20", "exp:60"]
    assert _spec_list("regimes:exp:20@1s,exp:200@1s; trace:a.up,offset=5 ;") == [
        "regimes:exp:20@1s,exp:200@1s", "trace:a.up,offset=5"]


def test_an_episode_on_a_trace_sizes_frames_by_their_stored_png(tiny_trace: Path) -> None:
    """The experiments' links on a trace read each frame's stored PNG size (or JPEG's)."""
    from aoi3d.experiment.config import EpisodeConfig
    from aoi3d.experiment.episode import episode_links, frame_sizes
    from aoi3d.scene import open_dataset

    root = Path(__file__).resolve().parents[3] / "data" / "turbine-rotor"
    if not root.is_dir():
        pytest.skip(f"no scene at {root} (aoi3d scene generate)")
    ds = open_dataset(root)
    png = frame_sizes(ds, "png")
    assert png.shape == (len(ds.cameras), ds.n_frames) and png.min() > 0
    cfg = EpisodeConfig(dataset=str(root), delay=f"trace:{tiny_trace},spread=0",
                        warmup_ms=300, scored_ms=300, score_every=1)
    links = episode_links(cfg, ds, seed=3)
    assert links.run.delay_spec == f"trace:{tiny_trace},spread=0"
    with pytest.raises(ValueError, match="frame encoding"):
        EpisodeConfig(frame_encoding="jpeg:0")
