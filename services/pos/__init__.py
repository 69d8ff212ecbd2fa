"""POS (position and orientation) input: formats, attitude conventions, coordinate frames."""

from .attitude import matrix_to_opk, matrix_to_ypr, opk_to_matrix, ypr_to_matrix
from .exif import (
    ExifData,
    camera_from_exif,
    check_image,
    image_paths,
    read_exif,
    read_pos_exif,
    read_xmp,
    record_from_exif,
)
from .frames import CRSError, LocalFrame, from_wgs84, is_wgs84_geographic, parse_crs, to_wgs84
from .io import match_names, read_pos, sniff_format, sniff_text
from .json_format import parse_pos_json, read_pos_json, write_pos_json
from .odm import parse_crs_line, parse_geo_txt, read_geo_txt, write_geo_txt
from .pos_csv import parse_pos_csv, read_pos_csv, write_pos_csv
from .records import (
    DEFAULT_STD_ATT,
    DEFAULT_STD_XY,
    DEFAULT_STD_Z,
    PosError,
    PosRecord,
    check_against_images,
)
from .rows import PosRow

__all__ = [
    "CRSError",
    "DEFAULT_STD_ATT",
    "DEFAULT_STD_XY",
    "DEFAULT_STD_Z",
    "ExifData",
    "LocalFrame",
    "PosError",
    "PosRecord",
    "PosRow",
    "camera_from_exif",
    "check_against_images",
    "check_image",
    "from_wgs84",
    "image_paths",
    "is_wgs84_geographic",
    "match_names",
    "matrix_to_opk",
    "matrix_to_ypr",
    "opk_to_matrix",
    "parse_crs",
    "parse_crs_line",
    "parse_geo_txt",
    "parse_pos_csv",
    "parse_pos_json",
    "read_exif",
    "read_geo_txt",
    "read_pos",
    "read_pos_csv",
    "read_pos_exif",
    "read_pos_json",
    "read_xmp",
    "record_from_exif",
    "sniff_format",
    "sniff_text",
    "to_wgs84",
    "write_geo_txt",
    "write_pos_csv",
    "write_pos_json",
    "ypr_to_matrix",
]
