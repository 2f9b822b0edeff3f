"""The thesis's simulation study: its tasks, study runs, the Monte Carlo, reports and
figures, benches, the guided demo and replay of recorded runs.

The top layer of core: it may import every other layer.
"""
