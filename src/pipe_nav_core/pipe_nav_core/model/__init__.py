"""What the estimators assume about the pig and its sensors: the nominal state and its error-state
layout (:mod:`state`), the strapdown mechanization (:mod:`mechanization`), the error-state
process (:mod:`process`), the sensor error specifications (:mod:`sensors`, :mod:`imu_noise`) and
one module per measurement (:mod:`measurements`), shared by the filter, the smoothers and the
factor graph.
"""
