"""Synthetic sequences: a ray-cast textured world, robot paths, imperfect wheel odometry,
and a feature-level simulator that can stand in for the front end."""
