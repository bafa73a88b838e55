"""Offline smoothing of a recorded run, one job a module:

- :mod:`.passes`: ``smooth_log``, the passes over the log and the method of each;
- :mod:`.methods`: the methods' names and the default one;
- :mod:`.forward`: one filter pass over the log, telling its progress;
- :mod:`.heading`: the initial heading of the smoothing passes, from the markers;
- :mod:`.rts`: the compiled Rauch-Tung-Striebel smoother over a recorded pass;
- :mod:`.two_filter`: the forward pass fused with a backward filter;
- :mod:`.slips`: the odometer epochs that disagree with the smoothed path;
- :mod:`.centreline`: the smoothed centreline, its chainage, residuals and summary
  (``SmoothResult``);
- :mod:`.logs`: sensor logs sliced, cut and turned in time.
"""
