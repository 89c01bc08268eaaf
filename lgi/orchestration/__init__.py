"""Prefect 3 tasks and flows over the job layer (:mod:`lgi.jobs`). Imported only when a flow runs: the
library's algorithms and jobs do not need Prefect. The top-level ``flows/`` and ``tasks/`` files that
``prefect.yaml`` points at re-export these."""
