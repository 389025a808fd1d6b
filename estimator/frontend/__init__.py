"""Front end: features, stereo matching and triangulation, matching through time, noise."""
