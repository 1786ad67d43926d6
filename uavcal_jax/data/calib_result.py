"""``RUN/result.json``: the summary ``uavcal calib train`` writes over a run's trials.

One JSON object (indented, a newline at the end): ``run`` (the run folder), ``validation``
(the scheme: ``split``, ``loo`` or ``kfold``), ``protocol`` (the offset injection protocol),
``seeds`` (models trained at once), ``trials`` (one object per trial: its fit's summary, with
``held_out``, the sources of its validation side) and ``mean_std`` (per headline validation
metric, ``{"mean", "std", "values"}`` over the trials; a metric without a value is left out).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

__all__ = ["RESULT_FILE", "write_calib_result"]

#: The file's name in the run folder.
RESULT_FILE = "result.json"


def write_calib_result(run_dir: str | Path, *, validation: str, protocol: str, seeds: int,
                       trials: Sequence[Mapping], mean_std: Mapping) -> dict:
    """Write ``run_dir/result.json`` atomically (a temporary file renamed); returns the
    object written."""
    run_dir = Path(run_dir)
    summary = {"run": str(run_dir), "validation": validation, "protocol": protocol,
               "seeds": seeds, "trials": list(trials), "mean_std": dict(mean_std)}
    tmp = run_dir / f".{RESULT_FILE}.tmp"
    tmp.write_text(json.dumps(summary, indent=2) + "\n")
    tmp.replace(run_dir / RESULT_FILE)
    return summary
