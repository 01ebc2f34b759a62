"""A replay's reconstruction jobs, run again worker by worker (see :mod:`services.recorder.replay`).

A ``stream`` render depends on the worker's history: each live worker (``Render.worker_id``)
ran its jobs in order on one model, warm-started from its previous job's model unless that is
missing or more than ``max_gap_ms`` of scene time away (a new model, too, when the job's
backend, seed, scene box or model epoch changes: :class:`services.recon.core.ReconCore`).
The replay rebuilds that chain: one :class:`ReconCore` per recorded worker, its recorded jobs
run in the worker's order (``Render.job_index``; a recording from before it: the renders'
decision times, the dispatch order), each with the settings its Render names (model epoch,
budget, cold budget and gap; a recording from before them: inferred from the renders, see
:func:`job_settings`). Every job of the chain is run, scored or not, up to the worker's last
job the replay scores (a job that only carries the model on: ``carried``).

A render is reproduced exactly only if its worker's chain up to it is the recorded one.
It is not (``exact`` False; scored all the same, and counted: ``not_exact``) after a **break**
— a gap in ``job_index`` (jobs the recording does not hold: it began mid-run, or a render was
lost), a job of the chain the replay cannot run (a frame or its decision not recorded; a
counterfactual selection naming a frame with no pixels: ``skipped``, the model goes on without
it), a job whose replayed warm start differs from the recorded one — until the worker's next
cold start that the run it stands for took too: one the live worker took as well (under the
recorded policy), or one the replay takes after it has trained on a job's frames since the
break (the time of the model's last decision, which decides a cold start, is then the run's),
or a job without frames (a reset either way). A worker whose first recorded job is not its
first starts its model where the recording begins.

``fresh`` renders do not depend on history: a worker whose recorded jobs are all fresh has
its scored jobs rebuilt alone, on the site scorer's own core, cached by job
(:meth:`Scorer.score`). ``warm`` and ``fork`` train the worker's model between jobs, on the
wall clock, which no recording holds: :func:`check_carries` refuses them.
"""

from __future__ import annotations

import heapq
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

from aoi3d.field.carry import BACKGROUND_MODES
from services.kit.pb import aoi3d_pb2 as pb
from services.recon.core import JobFailed, ReconCore

if TYPE_CHECKING:
    from aoi3d.field import FieldConfig
    from services.recorder.scoring import Scorer

__all__ = ["ChainCounts", "ChainJob", "JobSettings", "check_carries", "job_settings",
           "run_jobs", "worker_chains"]

HISTORY_CARRIES = frozenset({"stream"})
"""The carries whose render depends on the worker's earlier jobs (and is rebuilt in a chain)."""


@dataclass
class ChainJob:
    """A recorded render's job, to run again: on ``decision`` (the replayed policy's; None:
    not recorded) with ``frames`` (None: one has no pixels on record); ``wanted``: scored
    (else run only to carry its worker's model on); ``budget``: the job budget a recording
    from before ``Render.job_steps`` implies (:func:`services.recorder.scoring.job_budgets`).
    The run fills in ``quality``, ``exact`` (stream chains only), ``skipped``."""

    site: str
    key: tuple[int, int]
    render: pb.Render
    decision: pb.Decision | None
    frames: list[pb.Frame] | None
    wanted: bool
    budget: int
    quality: pb.Quality | None = None
    exact: bool | None = None
    skipped: str | None = None


@dataclass
class ChainCounts:
    """What the chains of a replay met (all 0 for a replay of fresh renders)."""

    gaps: int = 0
    """Breaks in a worker's recorded chain: its model had jobs the recording does not hold."""
    skipped: int = 0
    """Jobs of a chain not run (a frame or the decision not recorded, the render failed)."""
    carried: int = 0
    """Jobs run only to carry their worker's model on (not scored, or not asked for)."""
    not_exact: int = 0
    """Scored renders after a break, before their worker's next cold start."""

    def to_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass(frozen=True)
class JobSettings:
    steps: int
    cold_steps: int = 0
    max_gap_ms: float = 0.0
    model_epoch: int = 0


def check_carries(renders: Iterable[pb.Render]) -> None:
    """``ValueError`` when a render to rebuild was made with a carry that trains in the
    background (warm, fork)."""
    carries = sorted({r.carry for r in renders} & BACKGROUND_MODES)
    if carries:
        raise ValueError(f"replay rebuilds renders of the fresh and stream carries; the "
                         f"recording's {' and '.join(carries)} renders depend on the "
                         f"worker's training between jobs, timed by the wall clock and not "
                         f"on record (record with AOI3D_DISPATCHER_CARRY=stream or fresh); give "
                         f"--no-score")


def worker_chains(jobs: Iterable[ChainJob]) -> dict[str, list[ChainJob]]:
    """Each recorded worker's jobs in its order (see the module docstring), those after its
    last wanted job left out (a worker of fresh renders only: its wanted jobs alone)."""
    by: dict[str, list[ChainJob]] = defaultdict(list)
    for j in jobs:
        by[j.render.worker_id].append(j)
    out = {}
    for worker, chain in by.items():
        if all(j.render.HasField("job_index") for j in chain):
            chain.sort(key=lambda j: j.render.job_index)
        else:
            chain.sort(key=lambda j: (j.render.time_ms, j.key))
        if not any(j.render.carry in HISTORY_CARRIES for j in chain):
            chain = [j for j in chain if j.wanted]
        last = max((i for i, j in enumerate(chain) if j.wanted), default=-1)
        if last >= 0:
            out[worker] = chain[:last + 1]
    return out


def _nearest(values: Sequence[int | None], default: int) -> list[int]:
    """Each value, or where None the nearest earlier one's (else the nearest later one's, else
    ``default``)."""
    out: list[int | None] = list(values)
    last: int | None = None
    for i, v in enumerate(out):
        last = v if v is not None else last
        out[i] = last
    nxt: int | None = None
    for i in range(len(out) - 1, -1, -1):
        nxt = values[i] if values[i] is not None else nxt
        out[i] = out[i] if out[i] is not None else nxt
    return [default if v is None else v for v in out]


def job_settings(chain: Sequence[ChainJob]) -> list[JobSettings]:
    """The settings of each job of a worker's chain: those its Render names
    (``job_steps``, ``cold_steps``, ``warm_max_gap_ms``, ``model_epoch``) or, for a recording
    from before them, of a stream render: the warm budget is what a warm render spent (else
    the nearest warm render's), the cold budget what a cold one spent (else the nearest cold
    one's), the gap the worker's default; of a fresh render, ``ChainJob.budget``."""
    warm = _nearest([int(j.render.render_steps) if j.render.warm_start
                     and j.render.render_steps else None for j in chain], 0)
    cold = _nearest([int(j.render.render_steps) if not j.render.warm_start
                     and j.render.render_steps else None for j in chain], 0)
    out = []
    for j, w, c in zip(chain, warm, cold, strict=True):
        r = j.render
        if r.job_steps:
            out.append(JobSettings(r.job_steps, r.cold_steps, r.warm_max_gap_ms, r.model_epoch))
        elif r.carry in HISTORY_CARRIES:
            out.append(JobSettings(w or c or j.budget, c, 0.0, r.model_epoch))
        else:
            out.append(JobSettings(j.budget, 0, 0.0, r.model_epoch))
    return out


@dataclass
class _Worker:
    chain: list[ChainJob]
    settings: list[JobSettings]
    history: bool
    core: ReconCore | None = None
    exact: bool = True
    synced: bool = True
    """No break since the model last trained on a job's frames: the time of its last decision
    (which decides a cold start) is the one the run had."""
    prev_index: int | None = None
    pos: int = 0


def run_jobs(jobs: Iterable[ChainJob], scorer_of: Callable[[str], Scorer], *, threads: int,
             recorded_policy: bool, configs: dict[str, FieldConfig] | None = None,
             progress: Callable[[int, int], None] | None = None) -> ChainCounts:
    """Run every worker's chain (:func:`worker_chains`), the workers' jobs merged by decision
    time (each worker's in its order), and score the wanted ones with their site's scorer;
    ``recorded_policy``: the jobs are the recorded selections (a replayed warm start that
    differs from the recorded one is then a break)."""
    workers = {w: _Worker(c, job_settings(c), any(j.render.carry in HISTORY_CARRIES for j in c))
               for w, c in worker_chains(jobs).items()}
    total = sum(j.wanted for w in workers.values() for j in w.chain)
    heads = [(w.chain[0].render.time_ms, name) for name, w in workers.items()]
    heapq.heapify(heads)
    done = 0
    counts = ChainCounts()
    while heads:
        _, name = heapq.heappop(heads)
        w = workers[name]
        j = w.chain[w.pos]
        if w.history:
            if w.core is None:
                w.core = ReconCore(worker_id=f"replay-{name}", device="cpu",
                                   num_threads=threads, configs=configs)
            _chain_step(w, j, scorer_of(j.site), counts, recorded_policy)
        else:
            _fresh_step(j, w.settings[w.pos], scorer_of(j.site))
        done += j.wanted and j.quality is not None
        if progress is not None and j.wanted and j.quality is not None:
            progress(done, total)
        w.pos += 1
        if w.pos < len(w.chain):
            heapq.heappush(heads, (w.chain[w.pos].render.time_ms, name))
        else:
            w.core = None  # its model is not needed again
    return counts


def _fresh_step(j: ChainJob, s: JobSettings, scorer: Scorer) -> None:
    assert j.decision is not None and j.frames is not None  # wanted: rebuildable
    try:
        j.quality = scorer.score(j.decision, j.render, j.frames, s.steps)
    except JobFailed as err:
        j.skipped = f"render_failed: {err}"


def _chain_step(w: _Worker, j: ChainJob, scorer: Scorer, counts: ChainCounts,
                recorded_policy: bool) -> None:
    """One job of a worker's stream chain: breaks found, the job run on the worker's model,
    scored when wanted (see the module docstring)."""
    r = j.render
    if r.HasField("job_index"):
        expected = 0 if w.prev_index is None else w.prev_index + 1
        if r.job_index != expected:
            counts.gaps += 1
            w.exact = w.synced = False
        w.prev_index = r.job_index
    elif w.pos == 0 and r.warm_start:  # a recording from before job_index: began mid-chain
        counts.gaps += 1
        w.exact = w.synced = False
    if j.decision is None or j.frames is None:
        j.skipped = j.skipped or ("decision_not_recorded" if j.decision is None
                                  else "frames_not_recorded")
        counts.skipped += 1
        w.exact = w.synced = False
        return
    s = w.settings[w.pos]
    assert w.core is not None
    # the live worker told its model when the render was ready (the stream carry's gap
    # leaves the job's own time out): the replayed chain is told the recorded time
    ready = r.ready_ms if r.HasField("ready_ms") else None
    try:
        outcome = w.core.run(scorer.job(j.decision, r, j.frames, s.steps,
                                        cold_steps=s.cold_steps, max_gap_ms=s.max_gap_ms,
                                        model_epoch=s.model_epoch),
                             now_ms=None if ready is None else (lambda: ready))
        outcome.render.ClearField("ready_ms")  # scored at its decision's time, as compared
    except JobFailed as err:
        j.skipped = f"render_failed: {err}"
        counts.skipped += 1
        w.exact = w.synced = False
        return
    warm, views = outcome.render.warm_start, outcome.render.n_views > 0
    if recorded_policy and warm != r.warm_start:
        w.exact = False  # the replayed chain is not the live one
    elif not warm and (recorded_policy or not views or w.synced):
        w.exact = True  # a cold start the run it stands for took too: alike from here on
    w.synced = w.synced or views
    if not j.wanted:
        counts.carried += 1
        return
    j.quality = scorer.quality(outcome.render)
    j.exact = w.exact
    counts.not_exact += not w.exact
