"""Prefect tasks: every task the flows run, importable to compose flows of one's own (``from tasks.shot import
choose_chunk``). Each is defined in :mod:`lgi.orchestration` over a job of :mod:`lgi.jobs`; a test keeps this
package's list complete."""
