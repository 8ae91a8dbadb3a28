"""The paper's experiment (docs/method.md section 6): trials with a pose-error model, maps built with direct and
robust registration on the same data, classification error against the blueprint, CSV, box plot, sweep.

Modules: ``metrics`` (classifier and map metrics), ``pose_error`` (the correlated pose-error model),
``trial`` (one trial: simulate, map with every method, score), ``experiment`` (many trials in a process
pool, CSV, box plot, sigma sweep).
"""
