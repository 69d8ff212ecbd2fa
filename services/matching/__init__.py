"""Aerial-ground matchers, one module per method family; each writes the common match file.

- `direct`: local features matched image to image (the SIFT and ALIKED+LightGlue baselines).
"""
