"""Open a mesh stage's mosaic and DEM with GDAL, as QGIS does, and compare its placement with the files' own tags.

    python benchmarks/studies/gdal_check.py OUT_DIR

``OUT_DIR``: a mesh stage's output folder (``WS/09_mesh``, or ``run_mesh_folder``'s ``out_dir``) holding
``mosaic.tif``, ``dem.tif`` and ``mosaic.png`` with its world file. Needs rasterio (GDAL's Python binding, with
GDAL inside its wheel), which watergan does not depend on: run it with a Python that has rasterio and tifffile
(``python -m venv V && V/bin/pip install rasterio tifffile``). Prints, for each file, the CRS GDAL reads, its
affine transform, and the largest difference between GDAL's placement of a few pixels and the GeoTIFF tags'
(ModelTransformation, or pixel scale and tie point); exits 1 when GDAL finds no CRS or the placements differ by
more than a micrometre.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np


def tag_transform(path: Path) -> np.ndarray:
    """The 4x4 raster-to-model matrix of a GeoTIFF's tags."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        tags = tif.pages[0].tags
        if "ModelTransformationTag" in tags:
            return np.array(tags["ModelTransformationTag"].value, float).reshape(4, 4)
        sx, sy, _ = tags["ModelPixelScaleTag"].value
        _, _, _, x, y, _ = tags["ModelTiepointTag"].value
    return np.array([[sx, 0, 0, x], [0, -sy, 0, y], [0, 0, 0, 0], [0, 0, 0, 1.0]])


def main(out_dir: Path) -> int:
    import rasterio

    failed = False
    for name in ("mosaic.tif", "dem.tif", "mosaic.png"):
        path = out_dir / name
        with rasterio.open(path) as ds:
            corners = [(0, 0), (ds.width, ds.height), (ds.width / 3, ds.height / 2)]
            gdal = np.array([ds.transform * c for c in corners])
            crs = ds.crs.to_string() if ds.crs else None
            line = f"{name}: CRS {crs}, {ds.count} band(s) {ds.dtypes[0]}, no-data {ds.nodata}, transform " \
                   f"{tuple(round(v, 6) for v in ds.transform[:6])}"
        if name.endswith(".tif"):
            matrix = tag_transform(path)
            tags = np.array([(matrix @ [c, r, 0, 1])[:2] for c, r in corners])
            error = float(np.abs(gdal - tags).max())
            line += f"; GDAL against the tags: {error:.2e} m"
            failed |= error > 1e-6
        failed |= crs is None and name != "mosaic.png"
        print(line)
    return int(failed)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    raise SystemExit(main(Path(sys.argv[1])))
