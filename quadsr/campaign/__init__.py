"""`quadsr campaign`: robustness studies (grids and seeded Monte-Carlo draws of flights) on a Dask cluster.

spec.py reads and checks the campaign file; tasks.py expands it into tasks with seeds that depend only on the
campaign seed and each task's parameters; task_run.py flies one task (its own SITL child on free ports) in a
worker; results.py keeps one result file per finished task (resume) and writes the table; runner.py submits
the tasks to a local Dask cluster or an existing scheduler; report.py writes report.md and its figures.
"""
