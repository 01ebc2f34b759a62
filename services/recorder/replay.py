"""Replay a recording on the virtual clock: the same arrivals, any policy (``aoi3d replay``).

What a recording holds per site (:func:`load`): the delivered frames (pixels joined back from
their Foxglove images), the truth frames, the decisions with their AoI vectors, the renders
and their Quality. A replay takes every recorded decision epoch t again with the one
decision step every setting shares (:func:`aoi3d.policy.decide`), rebuilds the renders with
the live worker's own code (:class:`services.recon.core.ReconCore`: the job's backend, carry,
steps, seed and scene box, which the Render carries) and scores them with the live metrics
code (:class:`services.metrics.core.MetricsCore`: pairing, dynamic region, reward).

**Arrivals.** A frame counts for a decision at s iff it had *arrived at the scheduler* by s.
The recording holds each frame's delivery stamp (the network's), and each decision's AoI
vector — the scheduler's own U(s). The two agree but where a frame delivered at (or just
before) s reached the scheduler's process after its decision thread ran (a race on a busy
machine). A frame's arrival is therefore its delivery stamp, or — when the first decision at
or after that stamp did not know it — the first decision that did (:func:`arrivals`; counted
``late_arrivals``). With these arrivals U(s) at every recorded decision is the recorded one,
so a deterministic policy reproduces its selections, and any other policy is judged on
exactly the arrivals the recorded one saw. Frames the scheduler knew from before the
recording began enter as known without pixels (a render that needs one is not redone).

**Scores.** Only the decisions the live pool rendered and scored are rebuilt (their epochs
are the pairing of the counterfactual table). Under the recorded policy each is rebuilt from
the frames the live job carried (the Render lists them; the trainer may have missed one);
under another policy from its selection. Exact reproduction needs the ``fresh`` carry (each
render depends on its decision alone); ``warm``/``fork`` renders depend on the worker's
history and are refused.
"""

from __future__ import annotations

import bisect
import math
from collections import defaultdict
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from aoi3d.policy import Policy, decide, parse_policy
from aoi3d.quality import RewardWeights
from services.kit.pb import aoi3d_pb2 as pb
from services.recon.core import JobFailed
from services.recorder.core import segments, sim_ms_of, sim_ns

__all__ = ["Recorded", "ReplayResult", "SiteRecord", "arrivals", "load", "replay"]

_TOL_MS = 1e-6
_CLASSES = {cls.DESCRIPTOR.full_name: cls for cls in (pb.Frame, pb.Decision, pb.Render,
                                                      pb.Quality, pb.Outcome)}
SCORES = ("psnr_db", "ssim", "lpips", "reward", "psnr_dynamic_db", "ssim_dynamic")
"""The Quality fields compared (each where both have it)."""


@dataclass
class SiteRecord:
    deliveries: list[pb.Frame] = field(default_factory=list)
    truth: list[pb.Frame] = field(default_factory=list)
    decisions: list[pb.Decision] = field(default_factory=list)
    renders: dict[tuple[int, int], pb.Render] = field(default_factory=dict)
    qualities: dict[tuple[int, int], pb.Quality] = field(default_factory=dict)
    outcomes: list[pb.Outcome] = field(default_factory=list)
    frames_without_pixels: int = 0


@dataclass
class Recorded:
    path: Path
    files: list[Path]
    metadata: dict[str, str]
    sites: dict[str, SiteRecord]


def load(path: Path) -> Recorded:
    """Every message of ``path`` and its segments, decoded with the schemas in the file."""
    files = segments(Path(path))
    if not files:
        raise FileNotFoundError(f"no recording at {path}")
    sites: dict[str, SiteRecord] = defaultdict(SiteRecord)
    images: dict[tuple[str, int], bytes] = {}
    metadata: dict[str, str] = {}
    for f in files:
        with open(f, "rb") as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for record in reader.iter_metadata():
                if record.name == "aoi3d" and not metadata:
                    metadata = dict(record.metadata)
            for schema, channel, _message, msg in reader.iter_decoded_messages(
                    log_time_order=False):
                topic = channel.topic
                parts = topic.strip("/").split("/")
                if topic == "/tf" or parts[-1] == "calibration":
                    continue
                site, what = parts[0], "/".join(parts[1:])
                if schema.name.startswith("aoi3d."):  # decoded with the file's schema; as
                    msg = _CLASSES[schema.name].FromString(msg.SerializeToString())  # ours
                if what.endswith("image"):
                    if what != "render/image":
                        images[(msg.frame_id, sim_ns(sim_ms_of(msg.timestamp)))] = msg.data
                elif what == "delivery":
                    sites[site].deliveries.append(msg)
                elif what == "truth":
                    sites[site].truth.append(msg)
                elif what == "decision":
                    sites[site].decisions.append(msg)
                elif what == "render":
                    sites[site].renders[(msg.decision_incarnation, msg.decision_id)] = msg
                elif what == "quality":
                    sites[site].qualities[(msg.decision_incarnation, msg.decision_id)] = msg
                elif what == "outcome":
                    sites[site].outcomes.append(msg)
    for site, rec in sites.items():
        for frames, name in ((rec.deliveries, None), (rec.truth, "truth")):
            for fr in frames:
                data = images.get((f"{site}/{name or f'cam{fr.camera_id}'}",
                                   sim_ns(fr.generation_ms)))
                if data is None:
                    rec.frames_without_pixels += 1
                else:
                    fr.image.data = data
        rec.deliveries.sort(key=lambda fr: (fr.delivery_ms, fr.camera_id))
        rec.truth.sort(key=lambda fr: fr.generation_ms)
        rec.decisions.sort(key=lambda d: (d.time_ms, d.decision_id))
    return Recorded(Path(path), files, metadata, dict(sites))


# ---------------------------------------------------------------- arrivals at the scheduler
@dataclass(frozen=True)
class Arrival:
    camera_id: int
    generation_ms: float
    arrival_ms: float
    frame: pb.Frame | None
    """None: a frame the scheduler knew from before the recording (no pixels)."""


class Arrivals:
    """U(s) from the frames that had arrived at the scheduler by s, per camera."""

    def __init__(self, camera_ids: Sequence[int], items: Iterable[Arrival]) -> None:
        self.camera_ids = tuple(camera_ids)
        by_cam: dict[int, list[Arrival]] = defaultdict(list)
        for a in items:
            by_cam[a.camera_id].append(a)
        self._times: dict[int, list[float]] = {}
        self._newest: dict[int, list[float]] = {}  # running max of generation time
        self._frames: dict[tuple[int, float], Arrival] = {}
        for cam, lst in by_cam.items():
            lst.sort(key=lambda a: a.arrival_ms)
            self._times[cam] = [a.arrival_ms for a in lst]
            self._newest[cam] = list(np.maximum.accumulate([a.generation_ms for a in lst]))
            for a in lst:
                self._frames.setdefault((cam, a.generation_ms), a)
        self.late = 0

    def newest_at(self, s_ms: float) -> np.ndarray:
        out = np.full(len(self.camera_ids), np.nan)
        for i, cam in enumerate(self.camera_ids):
            times = self._times.get(cam)
            if times:
                k = bisect.bisect_right(times, s_ms) - 1
                if k >= 0:
                    out[i] = self._newest[cam][k]
        return out

    def frame(self, camera_id: int, generation_ms: float) -> Arrival | None:
        return self._frames.get((camera_id, generation_ms))


def _snap(value: float, candidates: list[float]) -> float:
    k = bisect.bisect_left(candidates, value - 1e-3)
    if k < len(candidates) and abs(candidates[k] - value) <= 1e-3:
        return candidates[k]
    return value


def arrivals(rec: SiteRecord) -> Arrivals:
    """Each delivered frame's arrival at the scheduler (see the module docstring)."""
    if not rec.decisions:
        raise ValueError("the recording holds no decision")
    camera_ids = list(rec.decisions[0].camera_ids)
    gens: dict[int, list[float]] = defaultdict(list)
    for fr in rec.deliveries:
        gens[fr.camera_id].append(fr.generation_ms)
    for cam in gens:
        gens[cam].sort()
    times = [d.time_ms for d in rec.decisions]
    # U_rec(s) per decision and camera, snapped onto the recorded generation times
    known = []
    for d in rec.decisions:
        row = {}
        for cam, aoi in zip(d.camera_ids, d.aoi_ms, strict=True):
            if not math.isnan(aoi):
                row[cam] = _snap(d.time_ms - aoi, gens.get(cam, []))
        known.append(row)
    items: list[Arrival] = []
    late = 0
    for fr in rec.deliveries:
        cam, g, t_del = fr.camera_id, fr.generation_ms, fr.delivery_ms
        first = k = bisect.bisect_left(times, t_del)  # the first decision at or after it
        while k < len(times) and known[k].get(cam, -math.inf) < g - _TOL_MS:
            k += 1
        if first == len(times) or k == first:
            arrival = t_del  # on time (or after the last decision)
        elif k < len(times):
            arrival, late = times[k], late + 1  # reached the scheduler after decision k-1
        else:
            arrival = math.inf  # no later decision knew it: it never counted
        items.append(Arrival(cam, g, arrival, fr))
    # what the scheduler knew at the first decision without a recorded frame behind it
    first = known[0]
    recorded = {(fr.camera_id, fr.generation_ms) for fr in rec.deliveries}
    for cam, g in first.items():
        if (cam, g) not in recorded:
            items.append(Arrival(cam, g, -math.inf, None))
    out = Arrivals(camera_ids, items)
    out.late = late
    return out


# ---------------------------------------------------------------- the replay
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


class Scorer:
    """Rebuilds renders with the live worker's code and scores them with the metrics code."""

    def __init__(self, rec: Recorded, site: str, *, lpips: bool, threads: int,
                 lpips_fn: Callable | None = None) -> None:
        from services.metrics.core import MetricsCore
        from services.recon.core import ReconCore

        meta = rec.metadata
        weights = RewardWeights(
            psnr=float(meta.get("reward_psnr", RewardWeights().psnr)),
            ssim=float(meta.get("reward_ssim", RewardWeights().ssim)),
            lpips=float(meta.get("reward_lpips", RewardWeights().lpips)),
            psnr_dynamic=float(meta.get("reward_psnr_dynamic", 0.0)),
            ssim_dynamic=float(meta.get("reward_ssim_dynamic", 0.0)))
        if lpips and lpips_fn is None:
            from aoi3d.lpips import load_lpips_fn

            lpips_fn = load_lpips_fn(meta.get("lpips_net", "alex"))
            if lpips_fn is None:
                raise ValueError("the recorded scores used LPIPS but its weights are not "
                                 "cached here (python -m aoi3d.lpips fetch)")
        truth = rec.sites[site].truth
        self.metrics = MetricsCore(truth_period_ms=float(meta.get("truth_period_ms", 30.0)),
                                   truth_frames=max(1, len(truth)), weights=weights,
                                   lpips_fn=lpips_fn if lpips else None, site=site)
        for fr in truth:
            if fr.image.data:
                self.metrics.on_truth(fr.SerializeToString(), math.inf)
        self.recon = ReconCore(worker_id="replay", device="cpu", num_threads=threads)
        self._cache: dict[tuple, pb.Quality] = {}

    def score(self, decision: pb.Decision, render: pb.Render, frames: list[pb.Frame],
              steps: int) -> pb.Quality:
        """The Quality of ``decision`` rebuilt from ``frames`` as the job of ``render`` was
        (``steps``: the job's budget; a render of an empty selection says 0);
        :class:`services.recon.core.JobFailed` when the worker's code refuses it."""
        key = (render.backend, render.carry, steps, render.seed,
               decision.time_ms, tuple((f.camera_id, f.generation_ms) for f in frames))
        if key in self._cache:
            out = pb.Quality()
            out.CopyFrom(self._cache[key])
            out.decision_id = decision.decision_id
            return out
        job = pb.Job(decision=decision, backend=render.backend, carry=render.carry,
                     render_steps=steps, seed=render.seed, model_epoch=0,
                     pose=render.pose, intrinsics=render.intrinsics, aabb=list(render.aabb),
                     site=render.site)
        for f in frames:
            job.frames.add().CopyFrom(f)
        outcome = self.recon.run(job)
        q = self.metrics.score(outcome.render.SerializeToString(), math.inf).message
        self._cache[key] = q
        return q


def _budgets(srec: SiteRecord) -> dict[tuple[int, int], int]:
    """Each rendered decision's job budget (``render_steps``): its Render's, or — for a
    render of an empty selection, which reports 0 — the nearest earlier render's that trained
    (else the nearest later one's)."""
    keys = [(d.incarnation, d.decision_id) for d in srec.decisions
            if (d.incarnation, d.decision_id) in srec.renders]
    steps = [int(srec.renders[k].render_steps) for k in keys]
    out, last = {}, 0
    for k, s in zip(keys, steps, strict=True):
        last = s or last
        out[k] = last
    nxt = 0
    for k, s in zip(reversed(keys), reversed(steps), strict=True):
        nxt = s or nxt
        out[k] = out[k] or nxt or 1
    return out


def _job_frames(selected: Sequence[tuple[int, float]], used: Sequence[float] | None,
                arr: Arrivals, used_cameras: Sequence[int] = ()) -> list[pb.Frame] | None:
    """The frames of a selection (those the live job carried, when ``used`` lists their
    generation times in selection order, and ``used_cameras`` their cameras — a recording
    from before Render.frame_camera_ids has generation times only, which every camera shares
    at k·C); None when one has no pixels in the recording."""
    out, k = [], 0
    cams = list(used_cameras) if used is not None and len(used_cameras) == len(used) else None
    for cam, g in selected:
        if used is not None:
            if (k < len(used) and abs(used[k] - g) <= _TOL_MS
                    and (cams is None or cams[k] == cam)):
                k += 1
            else:
                continue  # the live trainer did not hold it
        a = arr.frame(cam, g)
        if a is None or a.frame is None or not a.frame.image.data:
            return None
        out.append(a.frame)
    return out


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
        budgets = _budgets(srec)
        for d in srec.decisions:
            rec_policy = policy_of(d.policy)
            t = d.time_ms - rec_policy.wait_ms
            p = chosen or rec_policy
            sel = decide(p, t, arr.newest_at)
            recorded_aoi = np.asarray(d.aoi_ms, dtype=np.float64)
            same_time = abs(sel.eval_ms - d.time_ms) <= _TOL_MS
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
            frames = _job_frames(selected, used, arr, render.frame_camera_ids)
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
