"""The Earth and rotations: WGS84 geometry and gravity (:mod:`earth`), quaternions, rotation
vectors and direction cosine matrices (:mod:`attitude`).
"""
