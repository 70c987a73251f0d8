"""Offline grasp simulation: bin-clearing episodes through the real pipeline, judged by MuJoCo physics, in batches.

`run_scene` simulates one scene; `run_batch` runs many (local processes or Ray) and `write_results` stores the
per-pick CSV, summary.json and plots.
"""
