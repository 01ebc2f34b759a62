"""Replay a recording on the virtual clock: the same arrivals, any policy (``aoi3d replay``).

What a recording holds per site (:func:`services.recorder.recording.load`): the delivered
frames (pixels joined back from their Foxglove images), the truth frames, the decisions with
their AoI vectors, the renders and their Quality. A replay takes every recorded decision epoch
t again with the one decision step every setting shares (:func:`aoi3d.policy.decide`),
rebuilds the renders with the live worker's own code (:class:`services.recon.core.ReconCore`:
the job's backend, carry, steps, seed and scene box, which the Render carries) and scores them
with the live metrics code (:class:`services.metrics.core.MetricsCore`: pairing, dynamic
region, reward; :mod:`services.recorder.scoring`).

**Arrivals.** A frame counts for a decision at s iff it had *arrived at the scheduler* by s.
The recording holds each frame's delivery stamp (the network's), and each decision's AoI vector
— the scheduler's own U(s). The two agree but where a frame delivered at (or just before) s
reached the scheduler's process after its decision thread ran (a race on a busy machine). A
frame's arrival is therefore its delivery stamp, or — when the first decision at or after that
stamp did not know it — the first decision that did
(:func:`services.recorder.arrivals.arrivals`; counted ``late_arrivals``). With these arrivals
U(s) at every recorded decision is the recorded one, so a deterministic policy reproduces its
selections, and any other policy is judged on exactly the arrivals the recorded one saw. Frames
the scheduler knew from before the recording began enter as known without pixels (a render that
needs one is not redone).

**Scores.** Only the decisions the live pool rendered and scored are rebuilt (their epochs
are the pairing of the counterfactual table). Under the recorded policy each is rebuilt from
the frames the live job carried (the Render lists them; the dispatcher may have missed one);
under another policy from its selection. A ``fresh`` render depends on its decision alone
and is rebuilt alone. A ``stream`` render (the live default) depends on its worker's history:
the replay runs each recorded worker's jobs again in the worker's order on one model, as the
worker did (:mod:`services.recorder.chains`: ``Render.job_index`` orders them and shows a
gap; a render after a gap, before its worker's next cold start, is scored but marked not
exact, ``DecisionReplay.exact``). Under another policy the recorded pool schedule is kept —
the same decisions rendered by the same workers in the same order — and each job trains on
that policy's selection, so the warm chain runs through the counterfactual's own renders (a
job whose frames were not recorded is skipped: its worker's model does not train on it;
counted, ``ReplayResult.chains``). ``warm`` and ``fork`` renders also depend on training
between jobs, timed by the wall clock, and are refused.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from aoi3d.metric import BY_NAME, REWARD
from aoi3d.metric import SCORES as QUALITY
from aoi3d.policy import Policy, Selection, decide, parse_policy
from aoi3d.stats import MeanCI, mean_ci95
from services.kit.pb import aoi3d_pb2 as pb
from services.recorder.arrivals import TOL_MS, arrivals, job_frames
from services.recorder.chains import ChainCounts, ChainJob, check_carries, run_jobs
from services.recorder.recording import Recorded
from services.recorder.scoring import SCORES, Scorer, job_budgets

if TYPE_CHECKING:
    from aoi3d.field import FieldConfig

__all__ = ["Counterfactual", "DecisionReplay", "ReplayResult", "rebuildable_keys", "replay",
           "score_diffs"]


@dataclass
class DecisionReplay:
    site: str
    key: tuple[int, int]
    time_ms: float
    selected: tuple[tuple[int, float], ...]
    recorded: tuple[tuple[int, float], ...]
    aoi_equal: bool
    mean_aoi_selected_ms: float
    quality: pb.Quality | None = None
    skipped: str | None = None
    rebuildable: bool | None = None
    """For a decision the live pool scored: whether every frame it needs was recorded."""
    exact: bool | None = None
    """For a rebuilt stream render: whether its worker's chain of jobs up to it is the
    recorded one (False: after a break, see :mod:`services.recorder.chains`); None: a render
    that depends on its decision alone (fresh), or none rebuilt."""


@dataclass
class ReplayResult:
    policy: str
    decisions: list[DecisionReplay]
    chains: ChainCounts = field(default_factory=ChainCounts)

    @property
    def selections_equal(self) -> int:
        return sum(d.selected == d.recorded for d in self.decisions)


def _selection(sel: Selection, camera_ids: Sequence[int]) -> tuple[tuple[int, float], ...]:
    return tuple((int(c), float(g)) for c, g in zip(sel.cameras(camera_ids), sel.gen_ms,
                                                    strict=True))


def _recorded_selection(d: pb.Decision) -> tuple[tuple[int, float], ...]:
    return tuple((int(r.camera_id), float(r.generation_ms)) for r in d.selected)


def _replayed_decision(d: pb.Decision, sel: Selection, camera_ids: Sequence[int],
                       selected: tuple[tuple[int, float], ...], spec: str) -> pb.Decision:
    """The Decision the replayed policy took in place of ``d`` (the job's input)."""
    replayed = pb.Decision(decision_id=d.decision_id, incarnation=d.incarnation,
                           time_ms=sel.eval_ms, camera_ids=list(camera_ids),
                           aoi_ms=[float(a) for a in sel.aoi_ms], policy=spec)
    for cam, g in selected:
        replayed.selected.add(camera_id=cam, generation_ms=g,
                              aoi_ms=float(sel.eval_ms - g))
    return replayed


class _Policies:
    """Parsed policies by spec (one object each: a policy may keep state across decisions)."""

    def __init__(self) -> None:
        self._cache: dict[str, Policy] = {}

    def __call__(self, spec: str) -> Policy:
        if spec not in self._cache:
            self._cache[spec] = parse_policy(spec)
        return self._cache[spec]


def replay(rec: Recorded, policy: str | None = None, *, sites: Sequence[str] | None = None,
           score: bool = True, max_renders: int | None = None, threads: int | None = None,
           scorers: dict[str, Scorer] | None = None,
           only: Collection[tuple[str, tuple[int, int]]] | None = None,
           progress: Callable[[int, int], None] | None = None,
           configs: dict[str, FieldConfig] | None = None) -> ReplayResult:
    """Replay every recorded decision under ``policy`` (None: each decision's recorded
    policy) and, with ``score``, rebuild and score the decisions the live pool scored (those
    in ``only``, (site, key) pairs, when given; per site the first ``max_renders`` of them
    that can be rebuilt), stream renders through their worker's chain of jobs
    (:mod:`services.recorder.chains`). Without ``score`` each scored decision still says
    whether it could be rebuilt (``DecisionReplay.rebuildable``): :func:`rebuildable_keys`
    pairs policies with it. ``progress(done, total)``: after each scored render;
    ``configs``: field configs by backend in place of the defaults (tests)."""
    threads = threads or int(rec.metadata.get("recon_torch_threads", "1") or 1)
    policy_of = _Policies()
    chosen = policy_of(policy) if policy is not None else None
    results: list[DecisionReplay] = []
    jobs: list[tuple[ChainJob, DecisionReplay | None]] = []
    for site in sites or sorted(rec.sites):
        if rec.sites[site].decisions:
            jobs += _site_jobs(rec, site, chosen, policy_of, results, only=only,
                               score=score, max_renders=max_renders)
    result = ReplayResult(chosen.spec if chosen else "recorded", results)
    if not score:
        return result
    check_carries(j.render for j, _ in jobs if j.wanted)
    made: dict[str, Scorer] = {} if scorers is None else scorers

    def scorer_of(site: str) -> Scorer:
        if site not in made:
            q0 = next(iter(rec.sites[site].qualities.values()), pb.Quality())
            made[site] = Scorer(rec, site, lpips="lpips" in q0.reward_terms or q0.lpips_skipped,
                                threads=threads, configs=configs)
        return made[site]

    result.chains = run_jobs([j for j, _ in jobs], scorer_of, threads=threads,
                             recorded_policy=chosen is None, configs=configs,
                             progress=progress)
    for j, out in jobs:
        if out is not None and j.wanted:
            out.quality, out.exact, out.skipped = j.quality, j.exact, j.skipped
    return result


def _site_jobs(rec: Recorded, site: str, chosen: Policy | None,
               policy_of: Callable[[str], Policy], results: list[DecisionReplay], *,
               only: Collection[tuple[str, tuple[int, int]]] | None, score: bool,
               max_renders: int | None) -> list[tuple[ChainJob, DecisionReplay | None]]:
    """Replay the site's decisions (appended to ``results``) and make the job of each
    recorded render again: on the replayed selection, wanted when the live pool scored it
    and it is asked for (``only``, ``max_renders``) and can be rebuilt."""
    srec = rec.sites[site]
    arr = arrivals(srec)
    budgets = job_budgets(srec)
    jobs: list[tuple[ChainJob, DecisionReplay | None]] = []
    attempted = 0
    seen = set()
    for d in srec.decisions:
        rec_policy = policy_of(d.policy)
        p = chosen or rec_policy
        sel = decide(p, d.time_ms - rec_policy.wait_ms, arr.newest_at)
        same_time = abs(sel.eval_ms - d.time_ms) <= TOL_MS
        aoi_equal = same_time and bool(np.allclose(
            sel.aoi_ms, np.asarray(d.aoi_ms, dtype=np.float64), atol=1e-6, equal_nan=True))
        selected = _selection(sel, arr.camera_ids)
        key = (d.incarnation, d.decision_id)
        out = DecisionReplay(site, key, float(sel.eval_ms), selected, _recorded_selection(d),
                             aoi_equal, float(np.mean(sel.selected_aoi_ms)) if sel.mask.any()
                             else math.nan)
        results.append(out)
        render = srec.renders.get(key)
        if render is None:
            continue
        seen.add(key)
        used = list(render.frame_generation_ms) if chosen is None else None
        frames = job_frames(selected, used, arr, render.frame_camera_ids,
                            functools.partial(rec.has_pixels, site))
        scored = key in srec.qualities and (only is None or (site, key) in only)
        if scored:
            out.rebuildable = frames is not None
            out.skipped = "frames_not_recorded" if frames is None else None
        wanted = (scored and frames is not None and score
                  and (max_renders is None or attempted < max_renders))
        attempted += wanted
        jobs.append((ChainJob(site, key, render,
                              _replayed_decision(d, sel, arr.camera_ids, selected, p.spec),
                              frames, wanted, budgets.get(key, 1)),
                     out if scored else None))
    for key, render in srec.renders.items():  # renders of decisions not on record
        if key not in seen:
            jobs.append((ChainJob(site, key, render, None, None, False, 1), None))
    return jobs


def rebuildable_keys(rec: Recorded, policies: Sequence[str | None], *,
                     sites: Sequence[str] | None = None) -> set[tuple[str, tuple[int, int]]]:
    """The scored decisions (site, key) that every one of ``policies`` (None: the recorded
    one) can rebuild: pairing policies on these compares them on the same epochs. A
    counterfactual selection that names a frame known only from before the recording (a
    camera whose newest frame then had been delivered before the recorder subscribed) cannot
    be rebuilt; the recorded policy, holding its older frames, often can."""
    common: set[tuple[str, tuple[int, int]]] | None = None
    for p in policies:
        mine = {(d.site, d.key) for d in replay(rec, p, sites=sites, score=False).decisions
                if d.rebuildable}
        common = mine if common is None else common & mine
    return common or set()


def score_diffs(rec: Recorded, result: ReplayResult, *, exact: bool = True
                ) -> dict[str, float]:
    """Largest |replayed − recorded| of each score over the rebuilt decisions that are
    reproduced exactly (``exact`` False: over those that are not, the stream renders after a
    break in their worker's chain); LPIPS and the reward only where the recording scored them
    (not on a render it marked ``lpips_skipped``)."""
    diffs: dict[str, float] = {}
    for d in result.decisions:
        if d.quality is None or (d.exact is not False) != exact:
            continue
        live = rec.sites[d.site].qualities[d.key]
        for name in SCORES:
            if BY_NAME[name].optional and not (
                    live.HasField(name) and d.quality.HasField(name)):
                continue
            if live.lpips_skipped and name == REWARD.name:
                continue
            diff = abs(getattr(d.quality, name) - getattr(live, name))
            diffs[name] = max(diffs.get(name, 0.0), diff)
    return diffs


@dataclass(frozen=True)
class Counterfactual:
    """One policy's row of a replay's counterfactual table (``aoi3d replay --policy``): over
    the decisions it rebuilt that the baseline (the recorded policy, replayed) rebuilt too,
    ``n`` of them, the mean of each score of :data:`aoi3d.metric.SCORES` (None where none has
    it), each score's paired difference to the baseline (``vs_recorded``; an optional score,
    LPIPS, only where every decision has it), the cameras used and the mean AoI of the frames
    used."""

    policy: str
    n: int
    means: dict[str, float | None]
    vs_recorded: dict[str, MeanCI]
    cameras_used: float | None
    aoi_selected_ms: float | None

    @classmethod
    def of(cls, result: ReplayResult, baseline: ReplayResult) -> Counterfactual:
        def scored(r: ReplayResult) -> dict[tuple[str, tuple[int, int]], DecisionReplay]:
            return {(d.site, d.key): d for d in r.decisions if d.quality is not None}

        mine, base = scored(result), scored(baseline)
        keys = [k for k in mine if k in base]
        mq = {k: q for k in keys if (q := mine[k].quality) is not None}
        bq = {k: q for k in keys if (q := base[k].quality) is not None}
        means: dict[str, float | None] = {}
        vs: dict[str, MeanCI] = {}
        for metric in QUALITY:
            name = metric.name
            vals = [getattr(mq[k], name) for k in keys
                    if not metric.optional or mq[k].HasField(name)]
            means[name] = float(np.mean(vals)) if vals else None
            if not metric.optional or (vals and len(vals) == len(keys)):
                vs[name] = mean_ci95([getattr(mq[k], name) - getattr(bq[k], name)
                                      for k in keys])
        aoi = [mine[k].mean_aoi_selected_ms for k in keys
               if math.isfinite(mine[k].mean_aoi_selected_ms)]
        return cls(result.policy, len(keys), means, vs,
                   float(np.mean([len(mine[k].selected) for k in keys])) if keys else None,
                   float(np.mean(aoi)) if aoi else None)

    def to_dict(self) -> dict[str, Any]:
        """The row as ``--json`` writes it: ``policy``, ``n``, per score its mean and
        ``<score>_vs_recorded`` (``{"mean", "ci95", "n"}``), ``cameras_used``,
        ``aoi_selected_ms``."""
        out: dict[str, Any] = {"policy": self.policy, "n": self.n}
        for name, mean in self.means.items():
            out[name] = mean
            if name in self.vs_recorded:
                out[f"{name}_vs_recorded"] = self.vs_recorded[name].to_dict()
        out["cameras_used"] = self.cameras_used
        out["aoi_selected_ms"] = self.aoi_selected_ms
        return out
