"""The GIS outputs' CRS and options."""

import pytest
from pydantic import ValidationError

from services.pipeline import JobOptions
from services.sfm.gis import output_crs


def test_output_crs_is_projected():
    assert output_crs("EPSG:3006", 55.7, 13.19).to_epsg() == 3006  # SWEREF99 TM as given
    assert output_crs("EPSG:4979", 55.7, 13.19).to_epsg() == 32633  # geographic: the UTM zone
    assert output_crs(None, -33.9, 151.2).to_epsg() == 32756  # southern hemisphere
    assert output_crs(None, 55.7, -179.9).to_epsg() == 32601


def test_job_option_out_crs_is_checked():
    assert JobOptions(out_crs="EPSG:32633").out_crs == "EPSG:32633"
    with pytest.raises(ValidationError, match="unknown CRS"):
        JobOptions(out_crs="EPSG:999999")
