"""The built-in effects, one per file. Importing this package registers them."""

from . import (  # noqa: F401
    ambient_depth,
    artificial_light,
    attenuation,
    backscatter,
    backscatter_coefficient,
    backscatter_conv,
    caustics,
    forward_scatter,
    gain,
    marine_snow,
    sensor_response,
    vignetting,
    vignetting_offcentre,
    wideband_attenuation,
)
