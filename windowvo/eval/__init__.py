"""Evaluation against ground truth (ATE, RPE, drift), built on evo."""
