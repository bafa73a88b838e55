"""Damaged field data, found and named before and after estimation: holes in the time line
(:mod:`gaps`), impossible IMU samples (:mod:`imu`), wheel odometer faults (:mod:`odometer`),
markers that contradict the run (:mod:`markers`) and the run's verdict (:mod:`quality`).
"""
