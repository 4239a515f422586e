"""One scan workflow for the command line and the terminal UI.

- :mod:`lamina_host.workflow.checks`: the rules both front ends apply to what is typed
  (subject codes, plans, the device's limits, a scan's identity), re-exported here;
- :mod:`lamina_host.workflow.results`: typed results (progress, section rows, a processed
  scan) and the device information recorded with a scan;
- :mod:`lamina_host.workflow.job`: the scan request and the scan job that connects,
  calibrates, creates or resumes a scan, fetches and stores its views, processes and
  exports it. The front ends only turn arguments or widgets into a request and show the
  job's progress.

The job lives in its own module, imported by the front ends only: the link and the store
import the checks from here, and the job imports both.
"""

from lamina_host.workflow.checks import (
    DEFAULT_PITCH_MM,
    DEFAULT_SECTIONS,
    DEFAULT_VIEWS,
    IDENTITY_KEYS,
    PITCH_MAX_MM,
    SECTIONS_RANGE,
    SUBJECT_PATTERN,
    SUBJECT_RULE,
    VIEWS_RANGE,
    InputError,
    check_count,
    check_plan,
    check_plan_limits,
    check_positive_mm,
    check_subject,
    identity_difference,
    printable,
    scan_identity,
    spawned_source,
)

__all__ = [
    "DEFAULT_PITCH_MM",
    "DEFAULT_SECTIONS",
    "DEFAULT_VIEWS",
    "IDENTITY_KEYS",
    "PITCH_MAX_MM",
    "SECTIONS_RANGE",
    "SUBJECT_PATTERN",
    "SUBJECT_RULE",
    "VIEWS_RANGE",
    "InputError",
    "check_count",
    "check_plan",
    "check_plan_limits",
    "check_positive_mm",
    "check_subject",
    "identity_difference",
    "printable",
    "scan_identity",
    "spawned_source",
]
