"""Published water optics the code uses (re-typed from the references in docs/water.md).

Effective RGB attenuation coefficients (1/m; R, G, B), range-averaged for a white target under D65
seen by a Nikon D5100, for Jerlov water types; type I is given at 1 m range.
"""

EFFECTIVE_RGB_ATTENUATION_PER_M: dict[str, tuple[float, float, float]] = {
    "I": (0.210, 0.060, 0.025),     # clear open ocean
    "III": (0.281, 0.136, 0.129),   # open ocean, more particles
    "3C": (0.338, 0.239, 0.331),    # coastal
    "9C": (0.693, 0.826, 1.29),     # turbid coastal
}
