"""Matching (section 3.2.3's input): local features, the pairs to match, and matchers that write the
common match file. What the other steps use is named here; the modules are this step's own.

- `features`: the features of every image (SIFT, ALIKED), cached in an HDF5 file;
- `pairs`: aerial-ground pairs from the POS;
- `direct`: local features matched image to image (the SIFT and ALIKED+LightGlue baselines);
- `views`: every rendered view matched against its candidate aerial and ground images (the method).
"""

from services.matching.direct import match_features, verify_fundamental
from services.matching.features import confs as feature_confs
from services.matching.features import extract, load_features
from services.matching.features import main as extract_features
from services.matching.views import feature_conf as view_feature_conf
from services.matching.views import read_view_matches

__all__ = [
    "extract",
    "extract_features",
    "feature_confs",
    "load_features",
    "match_features",
    "read_view_matches",
    "verify_fundamental",
    "view_feature_conf",
]
