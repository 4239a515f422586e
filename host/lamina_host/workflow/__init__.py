"""One scan workflow for the command line and the terminal UI.

- :mod:`lamina_host.workflow.checks`: the rules both front ends apply to what is typed
  (plans, the device's limits, a scan's identity), re-exported here;
- :mod:`lamina_host.workflow.results`: typed results (progress, section rows, a processed
  scan) and the device information recorded with a scan;
- :mod:`lamina_host.workflow.job`: the scan request and the scan job that connects,
  calibrates, creates or resumes a scan, fetches and stores its views, processes and
  exports it. The front ends only turn arguments or widgets into a request and show the
  job's progress.

The job lives in its own module, imported by the front ends only.
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
