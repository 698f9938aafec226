"""torchrun for the fit app, keeping its promise of one line: rank 0's status, no summary.

    python experiments/launch.py --standalone --nproc_per_node=2 problem=arm3d threads=1
    scripts/fit.sh --standalone --nproc_per_node=2 problem=arm3d threads=1     # the same

The leading ``--`` arguments are torchrun's (``--name=value``: ``--standalone``,
``--nproc_per_node=2``, ``--nnodes=...``, ``--rdzv_endpoint=...``), the rest the overrides of
``experiments/fit.py``; it runs what ``torchrun <those> experiments/fit.py <overrides>``
runs, in this process. torchrun itself ends any job with a failed rank by its exit status 1
and a 30-line summary (a traceback and a ``ChildFailedError`` table) after the job's own
output; where rank 0 ended the job with its one ``error:`` line (status 2: the settings
refused, nothing written; 3: another rank stopped answering, the run resumable, the line
gives the command) this exits with rank 0's status and prints nothing more. Any other
failure gets torchrun's summary and its log lines, as torchrun gives them (held until the
end). ``OMP_NUM_THREADS`` defaults to 1, what torchrun sets with its banner (the fit's own
knob is ``threads=``).
"""
from __future__ import annotations

import logging
import os
import shlex
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: rank 0's exit statuses that come with their one line (experiments/app.py)
REPORTED = (2, 3)


class _Held(logging.Filter):
    """Holds torchrun's log records (its banner, ``Sending process ... SIGTERM``, ``failed
    (exitcode: 2)``) until the end: dropped where rank 0 said it all, else shown."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []
        self.holding = True

    def filter(self, record: logging.LogRecord) -> bool:
        if self.holding and record.name.startswith("torch.distributed"):
            self.records.append(record)
            return False
        return True


def split_arguments(argv: list[str]) -> tuple[list[str], list[str]]:
    """torchrun's leading ``--`` arguments, then the fit's overrides."""
    count = next((i for i, a in enumerate(argv) if not a.startswith("--")), len(argv))
    return argv[:count], argv[count:]


def main(argv: list[str]) -> int:
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.run import parse_args, run

    flags, overrides = split_arguments(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    # rank 0's resume command names this launch (experiments/fit.py torchrun_resume_command)
    os.environ["TORCHFIT_LAUNCH"] = " ".join(
        [os.environ.get("TORCHFIT_LAUNCHER", "python experiments/launch.py"),
         *(shlex.quote(f) for f in flags)])
    args = parse_args([*flags, str(REPO / "experiments" / "fit.py"), *overrides])
    held = _Held()
    handlers = [h for name in ("torch", "torch.distributed", "")
                for h in logging.getLogger(name).handlers]
    for handler in handlers:
        handler.addFilter(held)
    quiet = False
    try:
        run(args)
        return 0
    except ChildFailedError as failed:
        leader = failed.failures.get(0)
        if leader is not None and leader.exitcode in REPORTED:
            quiet = True
            return leader.exitcode
        raise
    finally:
        held.holding = False
        if not quiet:
            for record in held.records:
                logging.getLogger(record.name).handle(record)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
