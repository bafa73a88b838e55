"""The smoothing methods by name, the default one and the most passes: what ``pipe-nav smooth
--method`` and ``--iterations``, the smoother node's parameters of those names and
:func:`.passes.smooth_log` take. A module of its own so
that the command line can offer them without importing the numerics."""

METHODS = ("forward", "rts", "two-filter", "graph")
# the method used unless told: the best overall on the bench, whose table
# (pipe_nav_core.bench.accuracy.default_against_best) compares it with the best per scenario
DEFAULT_METHOD = "rts"
# smoothing passes at most; they stop once converged (.passes.CONVERGED_RAD), after 2 to 4 on
# the bench's scenarios
MAX_PASSES = 5
