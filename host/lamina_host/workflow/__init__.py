"""One scan workflow for the command line and the terminal UI.

- :mod:`lamina_host.workflow.checks`: the rules both front ends apply to what is typed
  (plans, the device's limits, a scan's identity), re-exported here;
- :mod:`lamina_host.workflow.results`: typed results (progress, section rows, a processed
  scan) and the device information recorded with a scan;
- :mod:`lamina_host.workflow.job`: the scan job that connects, calibrates, creates or
  resumes a scan, fetches and stores its views, processes and exports it, made of one
  small part per concern: :mod:`~lamina_host.workflow.device_session` (the connection,
  the device's controls, fetching views), :mod:`~lamina_host.workflow.acquisition` (the
  scan request, calibration, the scan in the library), :mod:`~lamina_host.workflow.processing`
  (its result) and :mod:`~lamina_host.workflow.library_access` (the library). The front
  ends only turn arguments or widgets into a request and show the job's progress.

The job lives in its own modules, imported by the front ends only.
"""

from lamina_host.workflow.checks import (
    DEFAULT_PITCH_MM,
    DEFAULT_SECTIONS,
    DEFAULT_VIEWS,
    PITCH_MAX_MM,
    SECTIONS_RANGE,
    VIEWS_RANGE,
    check_count,
    check_plan,
    check_plan_limits,
    check_positive_mm,
)

__all__ = [
    "DEFAULT_PITCH_MM",
    "DEFAULT_SECTIONS",
    "DEFAULT_VIEWS",
    "PITCH_MAX_MM",
    "SECTIONS_RANGE",
    "VIEWS_RANGE",
    "check_count",
    "check_plan",
    "check_plan_limits",
    "check_positive_mm",
]
