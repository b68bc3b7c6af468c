"""The coordinate system a LAS / LAZ header records, as the OGC WKT our exports write.

LAS 1.4 files with point formats 6-10 (ours) must carry their CRS as WKT; older files and many
tools record it as GeoTIFF keys (the GeoKeyDirectory VLR, record 34735) instead. A WKT VLR is
taken as it is. GeoTIFF keys are read for their EPSG codes: ProjectedCSTypeGeoKey (3072), else
GeographicTypeGeoKey (2048), and VerticalCSTypeGeoKey (4096) for the heights; PROJ's EPSG
database (pyproj, offline) turns them into WKT 1 (the WKT the LAS 1.4 specification names), a
compound CRS when a vertical one is given. A user-defined CRS (code 32767: its parameters spread
over further keys) or a code PROJ does not know gives no WKT, and the line says which.
"""

from __future__ import annotations

import laspy
from laspy.vlrs.known import GeoKeyDirectoryVlr, WktCoordinateSystemVlr

GEO_KEY_DIRECTORY = 34735  # the GeoTIFF key directory VLR's record id
PROJECTED = 3072  # ProjectedCSTypeGeoKey
GEOGRAPHIC = 2048  # GeographicTypeGeoKey
VERTICAL = 4096  # VerticalCSTypeGeoKey
USER_DEFINED = 32767
EPSG_CODES = range(1024, 32767)  # GeoTIFF 1.1: codes in this range are EPSG's


def header_crs(header: laspy.LasHeader, name: str) -> tuple[str | None, str]:
    """(WKT or None, a line saying where it came from or why there is none) for the header of
    the file `name`."""
    wkt = next((v.string for v in header.vlrs if isinstance(v, WktCoordinateSystemVlr)), "")
    if wkt.strip():
        return wkt, f"WKT from the header of {name}"
    directories = [v for v in header.vlrs if isinstance(v, GeoKeyDirectoryVlr)]
    if directories:
        return geotiff_wkt({k.id: k for v in directories for k in v.geo_keys}, name)
    if any(getattr(v, "record_id", None) == GEO_KEY_DIRECTORY for v in header.vlrs):
        return None, f"{name}'s GeoTIFF key directory could not be read, so no CRS is written"
    return None, f"the header of {name} records no CRS"


def geotiff_wkt(keys: dict, name: str) -> tuple[str | None, str]:
    """WKT 1 of the EPSG codes GeoTIFF keys (id -> key with `tiff_tag_location`,
    `value_offset`) name."""
    import pyproj  # PROJ's database loads on first use: only for files that need it

    horizontal_key = PROJECTED if PROJECTED in keys else GEOGRAPHIC
    horizontal = _code(keys.get(horizontal_key))
    if horizontal is None:
        return None, f"{name}'s GeoTIFF keys name no EPSG CRS, so no CRS is written"
    if horizontal == USER_DEFINED:
        return None, (
            f"{name}'s GeoTIFF keys define their own CRS (code 32767) rather than an EPSG one; "
            "mmsclean converts EPSG codes only, so no CRS is written"
        )
    try:
        crs = pyproj.CRS.from_epsg(horizontal)
    except pyproj.exceptions.CRSError:
        return None, f"{name}'s GeoTIFF keys name EPSG:{horizontal}, which PROJ does not know"
    codes = f"EPSG:{horizontal}"
    vertical = _code(keys.get(VERTICAL))
    if vertical is not None and vertical != USER_DEFINED:
        try:
            heights = pyproj.CRS.from_epsg(vertical)
        except pyproj.exceptions.CRSError:
            heights = None
        if heights is not None and heights.is_vertical:
            crs = pyproj.crs.CompoundCRS(f"{crs.name} + {heights.name}", [crs, heights])
            codes += f" + EPSG:{vertical}"
    return crs.to_wkt("WKT1_GDAL"), f"{codes} from the GeoTIFF keys of {name}, as WKT"


def _code(key) -> int | None:
    """A key's code when it is held in the directory itself (not in another VLR)."""
    if key is None or key.tiff_tag_location != 0:
        return None
    code = int(key.value_offset)
    return code if code in EPSG_CODES or code == USER_DEFINED else None
