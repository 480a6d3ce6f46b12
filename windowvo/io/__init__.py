"""Input and output: sequence folders, trajectory files, wheel odometry, stats."""
