"""Real sky in: star identification (tetra3rs), centroids from images, image files.

numpy/scipy and tetra3rs only (no ROS): used by replay, batch, the calibrator node, the
``star_extractor`` node and ``stellar-cal solve``.
"""
