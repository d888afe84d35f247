"""What every job reports to the run: its processes, failures and a one-line result."""

from __future__ import annotations

import dataclasses
from typing import Any


@dataclasses.dataclass
class JobSummary:
    """One job's line in the console's job table.

    Attributes
    ----------
    name
        The job's name.
    processes
        Fresh interpreters it started.
    failures
        What went wrong, one entry per failed process.
    note
        Its main result, in a few words.
    seconds
        Its wall time, set by the caller.
    """

    name: str
    processes: int
    failures: list[str]
    note: str
    seconds: float = 0.0


def summarise(name: str, results: list[dict[str, Any]], note: str) -> JobSummary:
    """A summary of the child results of one job."""
    failures = [str(r["error"]) for r in results if "error" in r]
    return JobSummary(name, len(results), failures, note)
