"""One fit over several processes (``torchrun``): a rigged body's poses split over ranks.

Rank 0 runs the fit; every other rank builds the same problem and serves the simulations of
its poses (:mod:`.ranks`); the collectives (:mod:`.channel`), the Jacobian rows kept on
their ranks (:mod:`.rows`) and the matrix-free path through autograd (:mod:`.graph`).
"""
from .ranks import (abandon, check_resume, communication_failure, launched, lead, rank, serve,
                    stop, stopped_answering, world_size)

__all__ = ["abandon", "check_resume", "communication_failure", "launched", "lead", "rank",
           "serve", "stop", "stopped_answering", "world_size"]
