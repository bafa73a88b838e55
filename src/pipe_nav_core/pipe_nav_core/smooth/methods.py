"""The smoothing methods by name, and the default one: what ``pipe-nav smooth --method``, the
smoother node's ``method`` parameter and :func:`.passes.smooth_log` take. A module of its own so
that the command line can offer them without importing the numerics."""

METHODS = ("forward", "rts", "two-filter", "graph")
# the method used unless told: the best overall on the bench, whose table
# (pipe_nav_core.bench.accuracy.default_against_best) compares it with the best per scenario
DEFAULT_METHOD = "rts"
