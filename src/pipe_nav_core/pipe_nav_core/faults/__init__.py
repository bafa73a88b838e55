"""Damaged field data, found and named before and after estimation: holes in the time line
(:mod:`gaps`), impossible IMU samples (:mod:`imu`), an IMU or a magnetometer on a clock of its
own (:mod:`clock_offset`, :mod:`mag_clock`), wheel odometer faults (:mod:`odometer`), markers
that contradict the run (:mod:`markers`) or are stamped on another clock (:mod:`marker_clock`)
and the run's verdict (:mod:`quality`).
"""
