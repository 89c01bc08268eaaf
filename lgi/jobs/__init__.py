"""The job layer: one function and one typed options object per job.

The ``lgi`` command line parses its arguments into a job's options, calls the job and prints the job's
report; the Prefect tasks and flows call the same functions (or the same stages of them) with the same
options, so choosing ``--flow`` changes how the work is scheduled and nothing else.
"""
