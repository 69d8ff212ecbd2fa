"""Structure from motion: the aerial reconstruction (aerial.py: features, pairs from the POS, mapping,
the georeference, report and exports) and the combined aerial + ground one (combined/). What the
other steps use is named here."""

from .aerial import SfmError, confs, main
from .georef import Georef, GeorefError, read_georef_frame, write_georef

__all__ = ["Georef", "GeorefError", "SfmError", "confs", "main", "read_georef_frame", "write_georef"]
