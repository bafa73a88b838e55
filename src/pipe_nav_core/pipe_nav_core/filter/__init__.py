"""The navigation filter: the compiled epoch loop (:mod:`epoch`, :mod:`kalman`), where epochs end
(:mod:`planner`), the samples' arrival and order (:mod:`ingest`, :mod:`stream`), the static
alignment (:mod:`alignment`), the heading's anchoring (:mod:`anchoring`), the encoder resolution
(:mod:`odometer_resolution`), the estimates (:mod:`estimates`), :class:`navigator.Navigator`
composing them, the live fault guard (:mod:`live_guard`) and seed 002's complementary filter
kept as a baseline (:mod:`complementary`).
"""
