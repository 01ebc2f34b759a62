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
the frames the live job carried (the Render lists them; the trainer may have missed one);
under another policy from its selection. Exact reproduction needs the ``fresh`` carry (each
render depends on its decision alone); ``warm``/``fork`` renders depend on the worker's
history and are refused.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass

import numpy as np

from aoi3d.policy import Policy, decide, parse_policy
from services.kit.pb import aoi3d_pb2 as pb
from services.recon.core import JobFailed
from services.recorder.arrivals import TOL_MS, arrivals, job_frames
from services.recorder.recording import Recorded
from services.recorder.scoring import SCORES, Scorer, job_budgets

__all__ = ["DecisionReplay", "ReplayResult", "rebuildable_keys", "replay", "score_diffs"]


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


@dataclass
class ReplayResult:
    policy: str
    decisions: list[DecisionReplay]

    @property
    def selections_equal(self) -> int:
        return sum(d.selected == d.recorded for d in self.decisions)


def _selection(sel, camera_ids) -> tuple[tuple[int, float], ...]:
    return tuple((int(c), float(g)) for c, g in zip(sel.cameras(camera_ids), sel.gen_ms,
                                                    strict=True))


def _recorded_selection(d: pb.Decision) -> tuple[tuple[int, float], ...]:
    return tuple((int(r.camera_id), float(r.generation_ms)) for r in d.selected)


def replay(rec: Recorded, policy: str | None = None, *, sites: Sequence[str] | None = None,
           score: bool = True, max_renders: int | None = None, threads: int | None = None,
           scorers: dict[str, Scorer] | None = None,
           only: Collection[tuple[str, tuple[int, int]]] | None = None,
           progress: Callable[[int, int], None] | None = None) -> ReplayResult:
    """Replay every recorded decision under ``policy`` (None: each decision's recorded
    policy) and, with ``score``, rebuild and score the decisions the live pool scored (those
    in ``only``, (site, key) pairs, when given; the first ``max_renders`` of them that can be
    rebuilt). Without ``score`` each scored decision still says whether it could be rebuilt
    (``DecisionReplay.rebuildable``): :func:`rebuildable_keys` pairs policies with it."""
    results: list[DecisionReplay] = []
    cache: dict[str, Policy] = {}
    threads = threads or int(rec.metadata.get("recon_torch_threads", "1") or 1)

    def policy_of(spec: str) -> Policy:
        if spec not in cache:
            cache[spec] = parse_policy(spec)
        return cache[spec]

    chosen = policy_of(policy) if policy is not None else None
    for site in sites or sorted(rec.sites):
        srec = rec.sites[site]
        if not srec.decisions:
            continue
        arr = arrivals(srec)
        scored = {k for k in ((d.incarnation, d.decision_id) for d in srec.decisions)
                  if k in srec.renders and k in srec.qualities
                  and (only is None or (site, k) in only)}
        if score and any(srec.renders[k].carry != "fresh" for k in scored):
            raise ValueError("replay rebuilds renders of the fresh carry only (a warm or fork "
                             "render depends on the worker's history); give --no-score")
        total = len(scored) if max_renders is None else min(max_renders, len(scored))
        scorer = None
        done = attempted = 0
        budgets = job_budgets(srec)
        for d in srec.decisions:
            rec_policy = policy_of(d.policy)
            t = d.time_ms - rec_policy.wait_ms
            p = chosen or rec_policy
            sel = decide(p, t, arr.newest_at)
            recorded_aoi = np.asarray(d.aoi_ms, dtype=np.float64)
            same_time = abs(sel.eval_ms - d.time_ms) <= TOL_MS
            aoi_equal = same_time and bool(np.allclose(sel.aoi_ms, recorded_aoi, atol=1e-6,
                                                       equal_nan=True))
            selected = _selection(sel, arr.camera_ids)
            key = (d.incarnation, d.decision_id)
            out = DecisionReplay(site, key, float(sel.eval_ms), selected,
                                 _recorded_selection(d), aoi_equal,
                                 float(np.mean(sel.selected_aoi_ms)) if sel.mask.any()
                                 else math.nan)
            results.append(out)
            if key not in scored:
                continue
            render = srec.renders[key]
            used = list(render.frame_generation_ms) if chosen is None else None
            frames = job_frames(selected, used, arr, render.frame_camera_ids,
                                lambda f, site=site: rec.has_pixels(site, f))
            out.rebuildable = frames is not None
            if frames is None:
                out.skipped = "frames_not_recorded"
                continue
            if not score or (max_renders is not None and attempted >= max_renders):
                continue
            attempted += 1
            replayed = pb.Decision(decision_id=d.decision_id, incarnation=d.incarnation,
                                   time_ms=sel.eval_ms, camera_ids=list(arr.camera_ids),
                                   aoi_ms=[float(a) for a in sel.aoi_ms], policy=p.spec)
            for cam, g in selected:
                replayed.selected.add(camera_id=cam, generation_ms=g,
                                      aoi_ms=float(sel.eval_ms - g))
            if scorer is None:
                if scorers is not None and site in scorers:
                    scorer = scorers[site]
                else:
                    q0 = srec.qualities[key]
                    scorer = Scorer(rec, site, lpips="lpips" in q0.reward_terms,
                                    threads=threads)
                    if scorers is not None:
                        scorers[site] = scorer
            try:
                out.quality = scorer.score(replayed, render, frames, budgets[key])
            except JobFailed as err:
                out.skipped = f"render_failed: {err}"
                continue
            done += 1
            if progress is not None:
                progress(done, total)
    return ReplayResult(chosen.spec if chosen else "recorded", results)


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


def score_diffs(rec: Recorded, result: ReplayResult) -> dict[str, float]:
    """Largest |replayed − recorded| of each score over the rebuilt decisions."""
    diffs: dict[str, float] = {}
    for d in result.decisions:
        if d.quality is None:
            continue
        live = rec.sites[d.site].qualities[d.key]
        for name in SCORES:
            if name in ("lpips", "psnr_dynamic_db", "ssim_dynamic") and not (
                    live.HasField(name) and d.quality.HasField(name)):
                continue
            diff = abs(getattr(d.quality, name) - getattr(live, name))
            diffs[name] = max(diffs.get(name, 0.0), diff)
    return diffs
