"""Front end: feature tracking with persistent ids, outlier rejection, keyframes, quality gates."""
