"""The jobs users run: the smoothing and replay pipeline (:mod:`pipeline`), the ``pipe-nav``
command line (:mod:`cli`), ``info``, the runs commands (:mod:`runs`), the report plot
(:mod:`plots`, drawn in :mod:`plot_process`), the settings template and the one progress
protocol (:mod:`progress`).
"""
