"""Batch (factor-graph) smoothing of a whole run (``--method graph``).

- :mod:`.problem`: the variables (every epoch's error state) and factors (prior, error-state
  dynamics between epochs, measurements) of the batch problem linearized about a trajectory;
- :mod:`.linearize`: builds it from the filter's own epoch and measurement kernels;
- :mod:`.solver`: the sparse least-squares solve (QR elimination in time order) with marginal
  covariances;
- :mod:`.linalg`: its compiled small dense algebra (whiteners, triangular inverses, the
  back-substitution's recursion);
- :mod:`.robust`: robust losses (IRLS weights);
- :mod:`.rotation`: a step's turn of the initial heading applied as an exact rotation;
- :mod:`.batch`: Gauss-Newton with a robust loss on the markers, from the RTS solution,
  solving each linearization as its pass runs.
"""

from pipe_nav_core.graph.batch import GraphResult, graph_smooth
from pipe_nav_core.graph.problem import LinearChain, MeasurementFactor, Prior
from pipe_nav_core.graph.solver import ChainSolution, solve_chain

__all__ = [
    "ChainSolution",
    "GraphResult",
    "LinearChain",
    "MeasurementFactor",
    "Prior",
    "graph_smooth",
    "solve_chain",
]
