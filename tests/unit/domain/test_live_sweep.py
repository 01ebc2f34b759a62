"""`aoi3d live sweep`'s statistics: per-policy summaries and the unpaired interior-maximum test;
its progress lines print policy specs as they are."""

from __future__ import annotations

import pytest

from aoi3d.experiment.optimum import unpaired_interior_maximum
from aoi3d.live import Measurement, points_rows, render_rows, summarise, with_sim


def stat(mean: float | None, ci95: float | None) -> dict:
    return {"mean": mean, "ci95": ci95, "n": 10}


def results(*points: tuple[str, float, float]) -> list[dict]:
    return [{"policy": p, "psnr_db": stat(m, h), "lpips": stat(-m / 100, h / 100)}
            for p, m, h in points]


def test_unpaired_interior_maximum_needs_the_difference_to_both_ends_significant() -> None:
    clear = unpaired_interior_maximum(results(("mat:40", 20.0, 1.0), ("mat:70", 26.0, 0.5),
                                     ("all", 24.0, 0.3)), "psnr_db")
    assert clear["best"] == "mat:70" and clear["interior"] and clear["beyond_ci"]
    assert clear["best_minus_end"]["all"]["difference"] == pytest.approx(2.0)
    # Welch by hand: standard errors 0.5/t(.975, 9) = 0.2210 and 0.3/t(.975, 9) = 0.1326,
    # Welch–Satterthwaite dof 14.7, t(.975, 14.7) = 2.135: 2.135 · √(0.2210² + 0.1326²)
    assert clear["best_minus_end"]["all"]["ci95"] == pytest.approx(0.550, abs=0.002)
    close = unpaired_interior_maximum(results(("mat:40", 20.0, 1.0), ("mat:70", 26.0, 0.8),
                                     ("all", 25.5, 0.3)), "psnr_db")
    assert close["interior"] and not close["beyond_ci"]
    end = unpaired_interior_maximum(results(("mat:40", 20.0, 1.0), ("mat:70", 23.0, 0.5),
                                   ("all", 24.0, 0.3)), "psnr_db")
    assert end["best"] == "all" and not end["interior"] and not end["beyond_ci"]
    # LPIPS: lower is better
    low = unpaired_interior_maximum(results(("a", 20.0, 1.0), ("b", 26.0, 0.5), ("c", 24.0, 0.3)),
                           "lpips")
    assert low["best"] == "b" and low["beyond_ci"]
    # an unknown CI never counts as separated; too few policies or a missing metric: None
    unknown = unpaired_interior_maximum([*results(("a", 20.0, 1.0)),
                                {"policy": "b", "psnr_db": stat(26.0, None)},
                                *results(("c", 24.0, 0.3))], "psnr_db")
    assert unknown["interior"] and not unknown["beyond_ci"]
    assert unpaired_interior_maximum(results(("a", 1.0, 0.1), ("b", 2.0, 0.1)), "psnr_db") is None
    assert unpaired_interior_maximum([{"policy": p, "psnr_db": stat(None, None)} for p in "abc"],
                            "psnr_db") is None


def test_welch_matches_scipy_on_raw_samples() -> None:
    import numpy as np
    from scipy import stats

    from aoi3d.stats import mean_ci95, welch_ci95

    rng = np.random.default_rng(0)
    a, b = rng.normal(25, 2, 40), rng.normal(24, 1, 25)
    half = welch_ci95(mean_ci95(list(a)), mean_ci95(list(b)))
    assert welch_ci95(mean_ci95(list(a)).to_dict(), mean_ci95(list(b)).to_dict()) == half
    res = stats.ttest_ind(a, b, equal_var=False)
    lo, hi = res.confidence_interval(0.95)
    assert half == pytest.approx((hi - lo) / 2, rel=1e-9)


def test_summarise_groups_by_policy_over_repeats() -> None:
    def decision(n: int, aoi: float) -> dict:
        return {"policy": "mat:70", "selected": [{"aoi_ms": aoi}] * n}

    ms = [
        Measurement("mat:70", 0, 1, 9, 10.0, [{"psnr_db": 25.0, "n_views": 4},
                                              {"psnr_db": 27.0, "n_views": 6}],
                    [decision(4, 30.0), decision(6, 60.0)]),
        Measurement("all", 0, 10, 19, 10.0, [{"psnr_db": 24.0, "n_views": 18}], []),
        Measurement("mat:70", 1, 20, 29, 10.0, [{"psnr_db": 26.0, "n_views": 5}],
                    [decision(5, 60.0), decision(0, 0.0)]),
    ]
    out = summarise(ms, ["mat:70", "all"])
    assert [r["policy"] for r in out] == ["mat:70", "all"]
    first = out[0]
    assert first["n"] == 3
    assert first["psnr_db"]["mean"] == pytest.approx(26.0) and first["psnr_db"]["ci95"] > 0
    assert first["cameras_used"]["mean"] == pytest.approx(15 / 4)
    assert first["aoi_used_ms"]["mean"] == pytest.approx(50.0)  # empty decisions have none
    assert first["psnr_dynamic_db"] == {"mean": None, "ci95": None, "n": 0}
    assert out[1]["psnr_db"] == {"mean": 24.0, "ci95": None, "n": 1}


def display_windows() -> list[Measurement]:
    """Two policies' windows whose renders were scored at the decision's time and at display
    time (the metrics service's ``psnr_display_db``; absent where it had no truth then)."""
    def q(psnr: float, shown: float | None) -> dict:
        return {"decision_id": 1, "psnr_db": psnr, "psnr_display_db": shown, "n_views": 4}

    return [Measurement("mat:70@50", 0, 1, 9, 10.0, [q(26.0, 24.0), q(28.0, 26.0)], []),
            Measurement("all", 0, 10, 19, 10.0, [q(24.0, 23.0), q(25.0, None)], [])]


def test_the_display_time_psnr_is_summarised_beside_the_decision_time_psnr() -> None:
    out = summarise(display_windows(), ["mat:70@50", "all"])
    assert out[0]["psnr_db"]["mean"] == pytest.approx(27.0)
    assert out[0]["psnr_display_db"]["mean"] == pytest.approx(25.0)
    assert out[0]["psnr_display_db"]["n"] == 2
    assert out[1]["psnr_display_db"] == {"mean": 23.0, "ci95": None, "n": 1}  # one had none
    sim = {"mat:70@50": {"psnr_db": stat(26.5, 0.5), "psnr_display_db": stat(24.0, 0.5)},
           "all": {"psnr_db": stat(25.0, 0.2)}}  # a virtual clock without display scores
    with_sim(out, sim)
    assert out[0]["live_minus_sim_db"] == pytest.approx(0.5)
    assert out[0]["sim_psnr_display_db"] == stat(24.0, 0.5)
    assert out[0]["live_minus_sim_display_db"] == pytest.approx(1.0)
    assert out[1]["sim_psnr_display_db"] is None and out[1]["live_minus_sim_display_db"] is None


def test_points_csv_keeps_its_columns_and_adds_the_display_time_psnr() -> None:
    out = summarise(display_windows(), ["mat:70@50", "all"])
    sim = {p: {"psnr_db": stat(25.0, 0.2), "psnr_display_db": stat(24.0, 0.3)}
           for p in ("mat:70@50", "all")}
    rows = points_rows(out, sim)
    before = ["policy", "n"]  # the columns points.csv had before the display-time PSNR
    for metric in ("psnr_db", "psnr_dynamic_db", "ssim", "lpips", "reward", "cameras_used",
                   "aoi_used_ms"):
        before += [metric, f"{metric}_ci95", *(["sim_psnr_db"] if metric == "psnr_db" else [])]
    assert list(rows[0]) == [*before, "psnr_display_db", "psnr_display_db_ci95",
                             "sim_psnr_display_db", "psnr_dynamic_display_db",
                             "psnr_dynamic_display_db_ci95"]  # (issue 41: the blades too)
    assert rows[0]["psnr_display_db"] == pytest.approx(25.0)
    assert rows[0]["sim_psnr_display_db"] == 24.0
    assert list(points_rows(out, None)[0]) == [c for c in list(rows[0])
                                               if not c.startswith("sim_")]
    # renders.csv: every scored render's fields, the display-time PSNR among them
    assert [r["psnr_display_db"] for r in render_rows(display_windows())] == [24.0, 26.0,
                                                                              23.0, None]


def test_the_sweep_table_and_figure_show_the_display_time_psnr(tmp_path) -> None:
    from aoi3d.live.figures import plot
    from aoi3d.live.report import LiveSweep
    from aoi3d_cli.common import make_console
    from aoi3d_cli.live import _table

    sim = {p: {m: stat(25.0, 0.2) for m in ("psnr_db", "psnr_dynamic_db", "ssim", "lpips",
                                             "reward", "psnr_display_db", "cameras_used")}
           for p in ("mat:70@50", "all")}
    result = LiveSweep.of(display_windows(), ["mat:70@50", "all"], settings={}, sim=sim)
    assert "psnr_display_db" in result.shape  # judged like every metric
    out = make_console(width=220)
    with out.capture() as cap:
        out.print(_table(result))
    text = cap.get()
    assert "display PSNR" in text and "sim display PSNR" in text
    table = _table(result)  # every cell under a named column, every live metric in one
    assert all(c.header for c in table.columns) and table.row_count == 2
    assert all(len(c._cells) == 2 for c in table.columns)
    from aoi3d.metric import LIVE, LIVE_AT_DISPLAY
    from aoi3d_cli.live import _SHOWN

    assert {m for m, _ in _SHOWN} == {*LIVE, *LIVE_AT_DISPLAY}
    assert "25.00" in text and "23.00" in text  # mat:70@50's and all's display PSNR
    doc = result.document({"live": 1.0})
    assert doc["results"][0]["psnr_display_db"]["mean"] == pytest.approx(25.0)
    result.write(tmp_path, doc)
    header = (tmp_path / "points.csv").read_text().splitlines()[0].split(",")
    assert header[-5:] == ["psnr_display_db", "psnr_display_db_ci95", "sim_psnr_display_db",
                           "psnr_dynamic_display_db", "psnr_dynamic_display_db_ci95"]
    assert plot(result.results, sim, tmp_path / "live_sweep.png", "t").stat().st_size > 0


def test_progress_prints_a_policy_spec_as_it_is() -> None:
    """Rich would turn ``mat:100:`` into an emoji ("mat💯") and eat ``[...]`` as markup."""
    from rich.markup import escape

    from aoi3d_cli.common import make_console

    out = make_console(width=80)  # the live sweep's console, as every command's
    with out.capture() as cap:  # as the sweep prints its progress: user text escaped
        out.print(f"\\[3/8] {escape('mat:100')}: settle 30 s, {escape('ppo:[runs]/final.pt')}")
    assert cap.get().strip() == "[3/8] mat:100: settle 30 s, ppo:[runs]/final.pt"


def test_sweep_refuses_a_bad_channel_before_touching_the_pipeline() -> None:
    from typer.testing import CliRunner

    from aoi3d_cli import live

    result = CliRunner().invoke(live.app, ["--delay", "regimes:exp:20", "--port-offset",
                                           "61000", "--timeout-s", "1"])
    assert result.exit_code == 2, result.output
    assert "lacksitsduration" in "".join(result.output.replace("│", "").split())


def test_the_virtual_clock_gets_the_live_trainers_budget_for_every_carry() -> None:
    # the live default (stream, 25 steps) must make an episode the experiments accept:
    # a warm start's budget and the cold starts' (not render_steps 0, which they refuse)
    from aoi3d.experiment.config import get_preset
    from aoi3d.live.sim import budget

    base = get_preset("quick").episode
    expect = {"fresh": {"steps_per_epoch": 100},
              "stream": {"steps_per_epoch": 100, "render_steps": 25},
              "fork": {"steps_per_epoch": 7, "render_steps": 25},
              "warm": {"steps_per_epoch": 7, "render_steps": 0}}
    for carry, want in expect.items():
        steps = 100 if carry == "fresh" else 25
        got = budget(carry, steps_per_decision=7, render_steps=steps, cold_steps=100)
        assert got == want, carry
        cfg = base.with_(carry=carry, **got)  # the experiments' own checks pass
        assert (cfg.carry, cfg.steps_per_epoch) == (carry, want["steps_per_epoch"])


def test_the_virtual_clock_refuses_a_budget_under_the_warm_carry_before_running(
        dataset, tmp_path) -> None:
    """A sweep of budgeted policies on a warm-carry pipeline keeps its live measurement: the
    virtual clock says why it cannot run them (the command prints it and writes no sim)."""
    from aoi3d.live.sim import SimRefused, simulate

    with pytest.raises(SimRefused, match=r"mat:70@50: .*warm carry"):
        simulate(["all", "mat:70@50"], dataset=dataset.root, delay="exp:60", carry="warm",
                 steps_per_decision=1, render_steps=0, seeds=1, seed_offset=0,
                 cache=tmp_path / "cache", processes=1)
    assert not (tmp_path / "cache").exists()  # nothing ran


def test_sweep_refuses_an_unknown_backend_before_touching_the_pipeline() -> None:
    from typer.testing import CliRunner

    from aoi3d_cli import live

    result = CliRunner().invoke(live.app, ["--backends", "grid,fog", "--port-offset", "61000",
                                           "--timeout-s", "1"])
    assert result.exit_code == 2, result.output
    assert "unknownfieldbackend'fog'" in "".join(result.output.replace("│", "").split())


def test_a_sweep_over_backends_with_json_prints_one_document(tmp_path, monkeypatch) -> None:
    """``--backends grid,flow --json``: stdout is the side-by-side document alone (each
    backend's own table went to stdout before it, so it was not JSON)."""
    import json

    from typer.testing import CliRunner

    from aoi3d_cli import live, livehttp

    puts: list[str] = []

    class Pipe:
        def call(self, method: str, service: str, path: str, json: dict | None = None) -> dict:
            if (method, path) == ("PUT", "/backend"):
                puts.append(json["backend"])
            return {"backend": "grid"}

    class Session:
        def __init__(self, pipe: object, console: object) -> None:
            self.pipe, self.proc = Pipe(), None

        @classmethod
        def on(cls, console: object, *where: object) -> Session:
            return cls(None, console)

        def __enter__(self) -> Session:
            return self

        def __exit__(self, *exc: object) -> None:
            pass

        def measure(self, *args: object, **kwargs: object) -> livehttp.SweepWindows:
            status = {"backend": puts[-1], "carry": "stream", "render_steps": 25}
            return livehttp.SweepWindows(display_windows(), status, status, {"delay": "exp:60"})

    monkeypatch.setattr(livehttp, "LiveSession", Session)
    monkeypatch.setattr(live, "_views_figure", lambda *args: None)
    result = CliRunner().invoke(live.app, [
        "--policies", "mat:70@50,all", "--backends", "grid,flow", "--no-sim", "--json",
        "--settle-s", "0", "--measure-s", "1", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert [(r["backend"], r["policy"]) for r in doc["backends"]] == [
        ("grid", "mat:70@50"), ("grid", "all"), ("flow", "mat:70@50"), ("flow", "all")]
    assert doc["backends"][0]["psnr_display_db"]["mean"] == pytest.approx(25.0)
    assert puts == ["grid", "flow", "grid"]  # a pipeline it did not start: grid put back
    assert (tmp_path / "flow/results.json").exists()


def test_the_pool_twin_charges_what_the_live_workers_timed() -> None:
    from aoi3d.experiment.config import EpisodeConfig
    from aoi3d.live.sim import MIN_JOBS, PoolTwin, job_cost, job_table

    job_s = {"grid/stream/25/18": {"median_s": 0.1, "mean_s": 0.12, "n": 300.0},
             "grid/stream/25/6": {"median_s": 0.06, "mean_s": 0.07, "n": 200.0},
             "grid/stream/100/18": {"median_s": 0.7, "mean_s": 0.9, "n": 12.0},
             "grid/stream/50/18": {"median_s": 9.0, "mean_s": 9.0, "n": MIN_JOBS - 1.0},
             "grid/fresh/25/18": {"median_s": 5.0, "mean_s": 5.0, "n": 40.0},
             "ngp/stream/25/18": {"median_s": 5.0, "mean_s": 5.0, "n": 40.0}}
    assert job_table(job_s, "grid", "stream") == ((25, 6, 60.0), (25, 18, 100.0),
                                                  (100, 18, 700.0))
    fixed, step = job_cost(job_s, "grid", "stream")
    assert fixed == 0.0 and 60 / 25 < step < 700 / 100  # cold steps dearer: through 0
    line = job_cost({"grid/stream/25/9": {"median_s": 0.1, "n": 5.0},
                     "grid/stream/100/9": {"median_s": 0.25, "n": 5.0}}, "grid", "stream")
    assert line == pytest.approx((50.0, 2.0))
    assert job_cost({}, "grid", "stream") is None
    # one step count: the default model scaled to it; an older key without frames is read
    fixed1, step1 = job_cost({"grid/fresh/25": {"median_s": 0.2, "n": 9.0}}, "grid", "fresh")
    assert fixed1 + 25 * step1 == pytest.approx(200.0)
    assert job_table({"grid/fresh/25": {"median_s": 0.2, "n": 9.0}}, "grid", "fresh") == (
        (25, -1, 200.0),)
    twin = PoolTwin(2, 0.5, fixed, step, job_table(job_s, "grid", "stream"))
    cfg = EpisodeConfig(carry="stream", steps_per_epoch=100, render_steps=25,
                        **twin.changes())
    assert cfg.compute_ms(25, 18) == pytest.approx(50.0)  # the table, times the time scale
    assert cfg.compute_ms(25, 12) == pytest.approx(40.0)  # between two timed frame counts
    assert cfg.compute_ms(100, 5) == pytest.approx(350.0)  # the step count's one cell
    assert cfg.compute_ms(60) == pytest.approx((fixed + 60 * step) * 0.5)  # the line
    assert EpisodeConfig.from_dict(cfg.to_dict()) == cfg
    assert EpisodeConfig(job_ms=((25, 40.0),)).job_ms == ((25, -1, 40.0),)  # any frames
    for bad in (((25, -1.0),), ((25, 3, -1.0),), (("x",),)):
        with pytest.raises(ValueError, match="job_ms"):
            EpisodeConfig(job_ms=bad)
