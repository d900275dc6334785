"""The record check at the end of a run: ``up`` exits 0 only when the monitor finished the run record and the record
agrees with the sim's own account (the steps, the rows and the summary).

Pure: :func:`monitor_failure` (did the monitor finish well?), :func:`take_record_numbers` (the final line shows the
record's numbers, never a stale live value) and :func:`outcome` (the exit status and the final line's words).
The record itself is read by the monitor's ``check_record``.
"""

from __future__ import annotations

from services.supervisor.children import Child, last_error
from services.supervisor.errors import RunFailed
from services.supervisor.observer import Progress

MONITOR_END_TIMEOUT = 30.0  # seconds the monitor may take after the sim's end to finish the record
STOPPED_FROM_OUTSIDE = 3  # exit status of `up` when someone else's stop ended the run before its steps


def monitor_failure(monitors: list[Child]) -> str | None:
    """Why the record is incomplete on the monitors' side (one still running after its time, or one that failed);
    None when every monitor finished well."""
    for monitor in monitors:
        if monitor.alive():
            return (f"the monitor did not finish the run record within {MONITOR_END_TIMEOUT:.0f} s of the run's "
                    f"end; the record is incomplete")
        code = monitor.proc.returncode
        if code != 0:
            return f"the monitor failed (status {code}): {last_error(monitor)}; the record is incomplete"
    return None


def take_record_numbers(progress: Progress, check) -> None:
    """The run's final numbers from the record's ``check`` (services.monitor.recorder.RecordCheck)."""
    progress.finished = True
    if check.rows:
        progress.t = check.rows - 1 if not check.gaps else max(progress.t, check.rows - 1)
    if check.deliveries is not None:
        progress.deliveries = float(check.deliveries)
    if check.final_links is not None:
        progress.links = float(check.final_links)


def outcome(check) -> tuple[int, str]:
    """``up``'s exit status and how the run ended, from the record's check; RunFailed when the record is
    incomplete."""
    if check.problems:
        raise RunFailed("the run record is incomplete: " + "; ".join(check.problems))
    if check.stopped_early is not None:
        return STOPPED_FROM_OUTSIDE, f"stopped from outside at tick {check.steps} ({check.stopped_early})"
    return 0, "completed"
