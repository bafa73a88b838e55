"""Benchmarks, scripts rather than tests: accuracy of every estimator on the simulated scenarios
(:mod:`accuracy`, scored by :mod:`evaluation`), the fault corpus (:mod:`faults`), the integrity
products (:mod:`products`), welds (:mod:`welds`), runs (:mod:`runs`), the error budget of a
scenario (:mod:`sources`), speed and memory at field scale (:mod:`speed`) and the command line's
fixed costs (:mod:`startup`).
"""
