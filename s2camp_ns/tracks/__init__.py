"""Keypoint tracks as the track prior's evidence: an SfM model's own (re-adjusted with a robust loss) or tracks built
from the images (pycolmap), cached, with progress on the terminal."""
