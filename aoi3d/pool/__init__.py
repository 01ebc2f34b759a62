"""The pool of reconstruction workers, as pure logic: who reconstructs which decision
(:class:`Dispatcher`) and the values it takes and gives (:mod:`.model`). The live dispatcher
service runs it with real workers; the virtual clock's twin of the pool
(:mod:`aoi3d.experiment.episode.pool`) with simulated ones: the same code in both."""

from aoi3d.pool.dispatcher import POOL_LOST, Dispatcher
from aoi3d.pool.model import (
    Assignment,
    DecisionRef,
    Ended,
    PoolReason,
    PoolStatus,
    Report,
    WorkerView,
)

__all__ = ["POOL_LOST", "Assignment", "DecisionRef", "Dispatcher", "Ended", "PoolReason",
           "PoolStatus", "Report", "WorkerView"]
